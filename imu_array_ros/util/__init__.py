"""Helpers every layer may use (they import nothing else of the package but :mod:`imu_array_ros.errors`):
safe file writes and YAML reading (:mod:`.files`), strict JSON (:mod:`.jsontools`), optional
dependencies (:mod:`.extras`), the lazy matplotlib import (:mod:`.plotting`) and the did-you-mean of a
mistyped name (:mod:`.names`)."""
