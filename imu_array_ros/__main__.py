"""``python -m imu_array_ros``: the same as the ``imu-array`` command."""

import sys

from imu_array_ros.cli import main

if __name__ == "__main__":
    sys.exit(main())
