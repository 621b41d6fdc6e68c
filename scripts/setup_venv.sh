#!/usr/bin/env bash
# Create a virtual environment with ROS 2 Jazzy from PyPI and imu_array_ros (editable).
# Usage: bash scripts/setup_venv.sh            (creates ./.venv)
#        IMU_ARRAY_VENV=/path bash scripts/setup_venv.sh
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
venv="${IMU_ARRAY_VENV:-$here/.venv}"
python3 -m venv "$venv"
"$venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
"$venv/bin/python" -m pip install -q --disable-pip-version-check -r "$here/requirements.txt"
"$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps -e "$here"
echo "ready: $venv (imu-array: $venv/bin/imu-array)"
