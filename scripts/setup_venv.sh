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
# the package itself, editable; its build's notes (setuptools: "Editable installation ... folders in your
# working directory with the same name as your package": that folder is this package) only if it fails
if ! out="$(pipq install --no-deps -e "$here" 2>&1)"; then
    printf '%s\n' "$out" >&2
    exit 1
fi
echo "ready: $venv (imu-array: $venv/bin/imu-array)"
