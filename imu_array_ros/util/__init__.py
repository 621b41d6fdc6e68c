"""Helpers every layer may use (they import nothing else of the package but :mod:`imu_array_ros.errors`):
safe file writes and YAML reading (:mod:`.files`), strict JSON (:mod:`.jsontools`), optional
dependencies (:mod:`.extras`) and the lazy matplotlib import (:mod:`.plotting`)."""
