"""Packaging: the core installs and runs without the extras, a command whose extra is missing says in one line
which extra to install, and setup.py, requirements.txt and package.xml name the same dependencies.

The extras (setup.py ``extras_require``, :mod:`imu_array_ros.util.extras`): ``plots`` (matplotlib) and
``bayes`` (arviz, h5netcdf, dask[distributed]).  "Not installed" is simulated in a fresh interpreter by
``sys.modules[name] = None`` before anything is imported (``import name`` then raises ImportError), so these
tests run in the full development environment.
"""

from __future__ import annotations

import ast
import importlib
import json
import os
import re
import runpy
import subprocess
import sys
import types
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "imu_array_ros"
SAMPLE = ROOT / "bags" / "twist32_sample"
ARRAY = ROOT / "config" / "array32.yaml"

#: the modules the extras provide (what a core install lacks)
EXTRA_MODULES = ("arviz", "dask", "distributed", "h5netcdf", "matplotlib")
BAYES_MODULES = ("arviz", "dask", "distributed", "h5netcdf")

#: install_requires distribution -> its rosdep key; None: rosdep has none (package.xml names it in its
#: ``no-rosdep-key:`` comment instead of an exec_depend)
ROSDEP = {"numpy": "python3-numpy", "scipy": "python3-scipy", "pyyaml": "python3-yaml", "pyserial": "python3-serial",
          "setuptools": "python3-setuptools", "threadpoolctl": "python3-threadpoolctl", "mcap": None, "rosbags": None, "lz4": None, "zstandard": None}
#: import name -> distribution, where they differ
DISTRIBUTION = {"yaml": "pyyaml", "serial": "pyserial", "distributed": "dask"}
#: ROS 2 packages the nodes and the launch file need (exec_depend)
ROS_PACKAGES = ("rclpy", "rcl_interfaces", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs", "launch",
                "launch_ros", "ament_index_python", "tf2_msgs", "rosgraph_msgs")
#: third-party imports that are neither a requirement nor a ROS package, and why
ALLOWED_IMPORTS = {"backports": "backports.zstd: mcap_format's fallback when zstandard is missing (rosbags brings it)"}


def run_blocked(tmp_path: Path, blocked, body: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``body`` in a new interpreter in which the modules ``blocked`` cannot be imported (a script with a
    ``__main__`` guard: the sampler's worker processes re-import it)."""
    script = tmp_path / "blocked_extras.py"
    script.write_text("import sys\n\n"
                      "if __name__ == '__main__':\n"
                      f"    for _name in {tuple(blocked)!r}:\n"
                      "        sys.modules[_name] = None\n"
                      + "".join(f"    {line}\n" if line else "\n" for line in body.strip("\n").splitlines()),
                      encoding="utf-8")
    return subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True, text=True, timeout=timeout)


def run_cli_blocked(tmp_path: Path, blocked, argv: list[str]) -> subprocess.CompletedProcess:
    """``imu-array argv`` (:func:`imu_array_ros.cli.main`) with the modules ``blocked`` not importable."""
    return run_blocked(tmp_path, blocked, f"from imu_array_ros.cli import main\nsys.exit(main({argv!r}))")


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("imu-array: error: "), proc.stderr
    return lines[0]


# --------------------------------------------------------------------------- a core install runs


def test_every_module_imports_and_fuse_runs_without_the_extras(tmp_path):
    out = tmp_path / "fused.mcap"
    proc = run_blocked(tmp_path, EXTRA_MODULES, f"""
import importlib, json, pkgutil
import imu_array_ros
failed = []
names = sorted(m.name for m in pkgutil.walk_packages(imu_array_ros.__path__, "imu_array_ros.",
                                                      onerror=lambda name: failed.append(name + ": walk")))
for name in names:
    try:
        importlib.import_module(name)
    except Exception as err:
        failed.append(f"{{name}}: {{type(err).__name__}}: {{err}}")
loaded = [m for m in {EXTRA_MODULES!r} if sys.modules.get(m) is not None]
print(json.dumps({{"modules": names, "failed": failed, "loaded": loaded}}))
sys.stdout.flush()
from imu_array_ros.cli import main
sys.exit(main(["fuse", {str(SAMPLE)!r}, "--array", {str(ARRAY)!r}, "--out", {str(out)!r}, "--quiet"]))
""")
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[0])
    assert not report["failed"], "\n".join(report["failed"])
    assert not report["loaded"], report["loaded"]
    modules = report["modules"]
    # the walk saw the whole package, the Bayesian calibration, the CLI and the nodes included
    assert len(modules) > 60, modules
    for expected in ("imu_array_ros.calibration.bayes", "imu_array_ros.cli.calibrate.bayes",
                     "imu_array_ros.util.plotting", "imu_array_ros.nodes.fusion_node"):
        assert any(m == expected or m.startswith(expected + ".") for m in modules), expected
    assert out.is_file() and out.stat().st_size > 0


# --------------------------------------------------------------------------- a missing extra: one line naming it


def test_plot_without_matplotlib_is_one_line_naming_the_plots_extra(tmp_path):
    proc = run_cli_blocked(tmp_path, ("matplotlib",), [
        "calibrate", "geometry", str(SAMPLE), "--array", str(ARRAY), "--out", str(tmp_path / "cal.yaml"),
        "--plot", str(tmp_path / "x.png"), "--quiet"])
    assert proc.returncode == 2, proc.stderr
    line = one_error_line(proc)
    assert line == ("imu-array: error: matplotlib, needed for --plot " + str(tmp_path / "x.png") + ", is not "
                    "installed (pip install 'imu_array_ros[plots]')"), line
    assert not (tmp_path / "x.png").exists()


def test_discover_without_matplotlib_says_the_plots_need_it_or_no_plots(tmp_path):
    """The way around a missing extra in the same line, the sentence grammatical ("plots ... need", not "needs")."""
    proc = run_cli_blocked(tmp_path, ("matplotlib",), [
        "discover", str(SAMPLE), "--array", str(ARRAY), "--report", str(tmp_path / "d"), "--quiet"])
    assert proc.returncode == 2, proc.stderr
    assert one_error_line(proc) == ("imu-array: error: matplotlib, needed for the report's plots, is not installed "
                                    "(pip install 'imu_array_ros[plots]', or pass --no-plots)")
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize("scheduler, missing", [("serial", "arviz"), ("local", "distributed")])
def test_bayes_without_its_extra_is_one_line_naming_the_bayes_extra(tmp_path, scheduler, missing):
    """The sampler's diagnostics need arviz; --scheduler local needs dask.distributed."""
    proc = run_cli_blocked(tmp_path, BAYES_MODULES, [
        "calibrate", "bayes", str(SAMPLE), "--array", str(ARRAY), "--out", str(tmp_path / "cal.yaml"),
        "--samples", "10", "--scheduler", scheduler, "--quiet"])
    assert proc.returncode == 2, proc.stderr
    line = one_error_line(proc)
    assert missing in line and "imu_array_ros[bayes]" in line, line
    assert not (tmp_path / "cal.yaml").exists()


# --------------------------------------------------------------------------- the nodes on a core install (no ROS 2)


def node_entry_points(monkeypatch) -> dict[str, str]:
    """console script name -> ``module:function`` of setup.py's node executables."""
    scripts = dict(line.replace(" ", "").split("=") for line in setup_arguments(monkeypatch)["entry_points"]
                   ["console_scripts"])
    return {name: target for name, target in scripts.items() if name.endswith("_node")}


@pytest.mark.parametrize("executable", ["driver_node", "fusion_node", "calibration_node", "probe"])
def test_a_node_without_ros_says_in_one_line_what_to_install(tmp_path, monkeypatch, executable):
    """``pip install .`` brings no rclpy or message packages: each node's entry point (and the probe) exits 2 with
    one line naming the missing module and the README's ROS 2 install, no traceback."""
    from imu_array_ros.nodes.entry import ROS_MODULES

    if executable == "probe":
        module, function, argv = "imu_array_ros.nodes.probe", "main", ["--out", str(tmp_path / "got.npz")]
    else:
        module, function = node_entry_points(monkeypatch)[executable].split(":")
        argv = ["--ros-args", "-p", f"array_config:={ARRAY}"]
    proc = run_blocked(tmp_path, ROS_MODULES, f"sys.argv = [{executable!r}, *{argv!r}]\n"
                                              f"from {module} import {function}\nsys.exit({function}())")
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    lines = proc.stderr.strip().splitlines()
    prog = "imu_array_ros.nodes.probe" if executable == "probe" else executable
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: the ROS 2 nodes need rclpy"), proc.stderr
    assert "is not installed: pip install 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces, or use a ROS 2 " \
           "Jazzy install" in lines[0]
    assert not (tmp_path / "got.npz").exists()


def runnable_node_modules() -> list[str]:
    """The modules of ``imu_array_ros/nodes`` that run as a program (``python -m imu_array_ros.nodes.NAME``)."""
    return sorted(p.stem for p in (PACKAGE / "nodes").glob("*.py") if 'if __name__ == "__main__":' in p.read_text())


def console_script(path: Path, target: str) -> Path:
    """The script pip (and colcon, into ``lib/imu_array_ros/``, which ``ros2 run`` runs) writes for ``target``."""
    module, function = target.split(":")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"import re\nimport sys\nfrom {module} import {function}\nif __name__ == '__main__':\n"
                    f"    sys.argv[0] = re.sub(r'(-script\\.pyw|\\.exe)?$', '', sys.argv[0])\n"
                    f"    sys.exit({function}())\n", encoding="utf-8")
    return path


def test_every_node_program_is_tested_without_rclpy():
    assert runnable_node_modules() == ["calibration_node", "driver_node", "fusion_node", "probe"]


@pytest.mark.parametrize("node,how", [(node, how) for node in ("driver_node", "fusion_node", "calibration_node")
                                      for how in ("python -m", "lib/imu_array_ros script")] + [("probe", "python -m")])
def test_a_node_run_as_a_program_without_rclpy_says_so_in_one_line(tmp_path, monkeypatch, node, how):
    """``python -m imu_array_ros.nodes.NODE`` and the installed console script, in an environment where
    ``import rclpy`` fails as it does without ROS 2 (a package on PYTHONPATH raising ModuleNotFoundError for
    'rclpy'): one line naming rclpy and how to get it, exit status 2, no traceback."""
    shim = tmp_path / "no_ros" / "rclpy"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(shim.parent), os.environ.get("PYTHONPATH")])))
    if node == "probe":  # (no console script)
        argv, prog = ["--out", str(tmp_path / "got.npz")], "imu_array_ros.nodes.probe"
    else:
        argv, prog = ["--ros-args", "-p", f"array_config:={ARRAY}"], node
    if how == "python -m":
        command = [sys.executable, "-m", f"imu_array_ros.nodes.{node}"]
    else:
        command = [sys.executable, str(console_script(tmp_path / "lib" / "imu_array_ros" / node,
                                                      node_entry_points(monkeypatch)[node]))]
    proc = subprocess.run(command + argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stdout == "", proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: the ROS 2 nodes need rclpy"), proc.stderr
    assert "'rclpy' is not installed: pip install 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces, or use " \
           "a ROS 2 Jazzy install (source /opt/ros/jazzy/setup.bash)" in lines[0], lines[0]


@pytest.mark.parametrize("node", ["driver_node", "fusion_node", "calibration_node"])
def test_node_help_lists_its_parameters_without_ros(tmp_path, node):
    """``python -m imu_array_ros.nodes.NODE --help`` (rclpy hidden): how to start it and every parameter with its
    default, status 0 -- not 'array_config is required' or a missing-ROS error."""
    from imu_array_ros.nodes.parameters import NODE_PARAMS

    shim = tmp_path / "no_ros" / "rclpy"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("raise ModuleNotFoundError(\"No module named 'rclpy'\", name='rclpy')\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(shim.parent), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, "-m", f"imu_array_ros.nodes.{node}", "--help"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert proc.stdout.startswith(f"usage: {node} --ros-args -p array_config:=FILE"), proc.stdout
    listed = re.findall(r"^  (\w+) \(", proc.stdout, flags=re.M)
    assert listed == [p.name for p in NODE_PARAMS[node]], listed
    assert "  array_config (required)" in proc.stdout


def test_rclpy_that_does_not_load_in_this_python_is_told_as_such(tmp_path):
    """A ROS 2 install sourced into a venv of another Python: ``rclpy`` is found but its C extension (built for
    the install's Python) is not. The one line says so and what to do, not that rclpy is missing."""
    shim = tmp_path / "other_python" / "rclpy"
    shim.mkdir(parents=True)
    (shim / "__init__.py").write_text("import importlib\n\nimportlib.import_module('rclpy._rclpy_pybind11')\n")
    (shim / "_rclpy_pybind11.cpython-399-x86_64-linux-gnu.so").write_bytes(b"")  # another Python's build
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(shim.parent), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, "-m", "imu_array_ros.nodes.fusion_node", "--ros-args", "-p",
                           f"array_config:={ARRAY}"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"fusion_node: error: 'rclpy' is installed ({shim}) but "
                                                   "'rclpy._rclpy_pybind11' does not load in this Python "
                                                   f"{sys.version_info.major}.{sys.version_info.minor}"), lines
    assert "source /opt/ros/jazzy/setup.bash" in lines[0] and "pip install 'ros-jazzy-rclpy[fastrtps]'" in lines[0]


def test_only_a_missing_ros_module_is_told_as_missing_ros():
    from imu_array_ros.nodes.entry import ros_missing

    assert "and 'geometry_msgs' is not installed: pip install" in ros_missing(ModuleNotFoundError(name="geometry_msgs.msg"))
    assert ros_missing(ModuleNotFoundError(name="numpy")) is None
    assert ros_missing(ImportError("librcl.so: cannot open shared object file")) is None


# --------------------------------------------------------------------------- setup.py, requirements.txt, package.xml


def setup_arguments(monkeypatch) -> dict:
    """The keyword arguments setup.py passes to ``setuptools.setup`` (run with a stand-in setuptools)."""
    captured: dict = {}
    fake = types.ModuleType("setuptools")
    fake.setup = lambda **kwargs: captured.update(kwargs)
    fake.find_packages = lambda *args, **kwargs: []
    monkeypatch.setitem(sys.modules, "setuptools", fake)
    monkeypatch.chdir(ROOT)
    runpy.run_path(str(ROOT / "setup.py"), run_name="__main__")
    return captured


def name_of(requirement: str) -> str:
    """'dask[distributed]>=2024.1' -> 'dask'."""
    return re.match(r"[A-Za-z0-9_.-]+", requirement).group(0).lower()


def test_the_core_requires_no_extra_and_the_extras_are_those_of_util_extras(monkeypatch):
    from imu_array_ros.util.extras import EXTRAS

    args = setup_arguments(monkeypatch)
    core = {name_of(r) for r in args["install_requires"]}
    extras = args["extras_require"]
    assert core == set(ROSDEP), core
    for extra, modules in EXTRAS.items():
        assert {name_of(r) for r in extras[extra]} == {DISTRIBUTION.get(m, m) for m in modules}, extra
        assert not core & {name_of(r) for r in extras[extra]}, extra
    assert not core & {DISTRIBUTION.get(m, m) for m in EXTRA_MODULES}
    # the test suite exercises the plots and the sampler; "all" is every extra
    assert set(extras["test"]) >= set(extras["plots"]) | set(extras["bayes"]) | {"pytest>=7.4", "hypothesis>=6.0"}
    assert set(extras["all"]) == {r for extra in EXTRAS for r in extras[extra]}


def test_requirements_txt_installs_the_core_and_every_extra(monkeypatch):
    """scripts/setup_venv.sh installs requirements.txt: all the README's two commands need."""
    args = setup_arguments(monkeypatch)
    lines = {ln.strip() for ln in (ROOT / "requirements.txt").read_text(encoding="utf-8").splitlines()
             if ln.strip() and not ln.lstrip().startswith("#")}
    wanted = set(args["install_requires"]) | {r for reqs in args["extras_require"].values() for r in reqs}
    assert not wanted - lines, sorted(wanted - lines)


def package_xml() -> tuple[dict[str, list[str]], str]:
    text = (ROOT / "package.xml").read_text(encoding="utf-8")
    root = ElementTree.fromstring(text)
    tags = {}
    for tag in ("exec_depend", "depend", "test_depend", "build_depend"):
        tags[tag] = [e.text.strip() for e in root.findall(tag)]
    return tags, text


def test_package_xml_names_every_runtime_dependency(monkeypatch):
    args = setup_arguments(monkeypatch)
    tags, text = package_xml()
    runtime = set(tags["exec_depend"]) | set(tags["depend"])
    no_key = re.search(r"no-rosdep-key:([^\n]*)", text)
    no_key = set(no_key.group(1).split()) if no_key else set()
    for requirement in args["install_requires"]:
        name = name_of(requirement)
        key = ROSDEP[name]
        if key is None:
            assert name in no_key, f"{name}: no rosdep key, so package.xml must list it after 'no-rosdep-key:'"
            assert requirement in text, f"package.xml should give the pip requirement {requirement!r}"
        else:
            assert key in runtime, f"{name}: package.xml lacks <exec_depend>{key}</exec_depend>"
    assert no_key <= {n for n, k in ROSDEP.items() if k is None}, no_key
    for pkg in ROS_PACKAGES:
        assert pkg in runtime, f"package.xml lacks <exec_depend>{pkg}</exec_depend>"
    # an extra is not a runtime dependency of the core
    assert "python3-matplotlib" not in runtime


def top_level_imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split(".")[0])
    return out


def test_every_third_party_import_is_a_declared_dependency(monkeypatch):
    """Every module the package and its launch file import is the standard library, a requirement (core or
    an extra), or a ROS 2 package of package.xml."""
    args = setup_arguments(monkeypatch)
    declared = {name_of(r) for r in args["install_requires"]}
    declared |= {name_of(r) for reqs in args["extras_require"].values() for r in reqs}
    tags, _ = package_xml()
    ros = set(tags["exec_depend"]) | set(tags["depend"])
    undeclared = []
    for path in sorted(PACKAGE.rglob("*.py")) + sorted((ROOT / "launch").glob("*.py")):
        for module in top_level_imports(path):
            if module in sys.stdlib_module_names or module == "imu_array_ros" or module in ALLOWED_IMPORTS:
                continue
            if DISTRIBUTION.get(module, module) in declared or module in ros:
                continue
            undeclared.append(f"{path.relative_to(ROOT)}: {module}")
    assert not undeclared, "\n".join(undeclared)


def test_the_extras_modules_are_importable_here():
    """The development environment (requirements.txt) has every extra, so the tests above mean something."""
    for module in EXTRA_MODULES:
        importlib.import_module(module)
