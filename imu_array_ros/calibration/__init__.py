"""Calibrations of the array, each returning one :class:`~imu_array_ros.calibration.result.Calibration`
(:mod:`.methods`): accelerometer positions from motion (:mod:`.geometry`, carlsson2017), static poses
(:mod:`.static`, nilsson2014 ML; :mod:`.pca`, rupniewski), the whole array (:mod:`.array`), and the
Bayesian positions (:mod:`.bayes`, carlsson2021); the samples they use (:mod:`.selection`, :mod:`.still`)
and how a calibration is scored (:mod:`.scoring`) and installed (:mod:`.result`)."""
