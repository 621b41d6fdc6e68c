"""Parameter tables, example params files and the launch file agree."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from conftest import REPO
from dds_harness import dds_env, pick_domain
from imu_array_ros.nodes.parameters import NODE_PARAMS

NODE_NAMES = {"driver_node": "imu_array_driver", "fusion_node": "imu_array_fusion",
              "calibration_node": "imu_array_calibration"}


@pytest.mark.parametrize("exe", sorted(NODE_PARAMS))
def test_example_params_file_lists_every_parameter_with_its_type(exe):
    doc = yaml.safe_load((REPO / "config" / f"{exe}.params.yaml").read_text())
    values = doc[NODE_NAMES[exe]]["ros__parameters"]
    table = {p.name: p for p in NODE_PARAMS[exe]}
    assert set(values) == set(table)
    for name, value in values.items():
        assert type(value) is type(table[name].default), name
        p = table[name]
        if p.low is not None:
            assert p.low <= value <= p.high, name
        if p.choices:
            assert value in p.choices, name


@pytest.mark.parametrize("exe", sorted(NODE_PARAMS))
def test_node_reads_its_example_params_file(exe, tmp_path):
    """The file parses as ROS parameters: the node gets to its own checks (here: a missing array file)."""
    env = dds_env(pick_domain())  # the tests' own domain range (IMU_ARRAY_TEST_DOMAINS)
    proc = subprocess.run([str(Path(sys.executable).parent / exe), "--ros-args", "--params-file",
                           str(REPO / "config" / f"{exe}.params.yaml"), "-p", f"array_config:={tmp_path}/none.yaml"],
                          capture_output=True, text=True, timeout=30, env=env)
    assert proc.returncode == 2 and f"{tmp_path}/none.yaml" in proc.stderr and "Traceback" not in proc.stderr


def test_launch_file_builds_where_launch_is_installed():
    if importlib.util.find_spec("launch") is None or importlib.util.find_spec("launch_ros") is None:
        pytest.skip("the ROS 2 'launch' package is not on PyPI; checked on full ROS installs")
    spec = importlib.util.spec_from_file_location("imu_array_launch", REPO / "launch" / "imu_array.launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.generate_launch_description().entities
