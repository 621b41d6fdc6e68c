"""``imu-array``: the offline command line (the same workflows as the ROS nodes and the Python API).

* :mod:`.parser` -- :func:`build_parser` (assembled from the subcommand modules) and :func:`main`;
* one module per subcommand, its parser (``add_parser``) beside its typed handler (``run``):
  :mod:`.simulate`, :mod:`.fuse`, :mod:`.import_openshoe`, :mod:`.fake_device`, :mod:`.residuals`,
  :mod:`.calibrate` (one module per method), :mod:`.discover`, :mod:`.recover`;
* :mod:`.options` -- validating argument types, the options the subcommands share, reading the inputs;
* :mod:`.progress` -- progress and summary lines on stderr.

User mistakes (bad options, bad files, unsafe outputs) print one line
``imu-array: error: ...`` and exit with status 2; nothing is half-written and
nothing the user did not name is replaced (:func:`imu_array_ros.io.outputs.check_output`).
"""

from imu_array_ros.cli.parser import build_parser, main

__all__ = ["main", "build_parser"]
