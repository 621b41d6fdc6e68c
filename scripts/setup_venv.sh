#!/usr/bin/env bash
# Create a virtual environment with ROS 2 Jazzy from PyPI and imu_array_ros (editable).
# Usage: bash scripts/setup_venv.sh            (creates ./.venv)
#        IMU_ARRAY_VENV=/path bash scripts/setup_venv.sh
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
venv="${IMU_ARRAY_VENV:-$here/.venv}"

# pip, minus the "Location ... is ignored" warnings that a pip.conf with absent local
# index directories prints for every package (real errors still show).
pipq() {
    "$venv/bin/python" -m pip -q --disable-pip-version-check "$@" 2> >(grep -v "^WARNING: Location '" >&2)
}

python3 -m venv "$venv"
pipq install --upgrade pip
pipq install -r "$here/requirements.txt"
pipq install --no-deps -e "$here"
echo "ready: $venv (imu-array: $venv/bin/imu-array)"
