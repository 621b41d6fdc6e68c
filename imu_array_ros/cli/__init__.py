"""``imu-array``: the offline command line (same core functions as the ROS nodes).

* :mod:`.parser` -- argparse with validating types; :func:`main`, :func:`build_parser`;
* :mod:`.commands` -- one typed function per subcommand (``simulate``, ``fuse``,
  ``import_openshoe``, ``residuals``), callable from Python too;
* :mod:`.progress` -- progress and summary lines on stderr.

User mistakes (bad options, bad files, unsafe outputs) print one line
``imu-array: error: ...`` and exit with status 2; nothing is half-written and
nothing the user did not name is replaced (:func:`imu_array_ros.io.outputs.check_output`).
"""

from imu_array_ros.cli.parser import build_parser, main

__all__ = ["main", "build_parser"]
