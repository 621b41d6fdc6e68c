"""Estimators of the array's motion: ML fusion with its Cramér–Rao bound (skog2016),
the angular-acceleration-tensor baseline, and chunked fusion of a whole stream.

The ML fusion is :mod:`.ml_fusion` (``MLFusion``, ``fuse``), built on
:mod:`.validity` (valid-axis masks and patterns), :mod:`.pattern_geometry`
(matrices per pattern of valid axes), :mod:`.gauss_newton` (the solver) and
:mod:`.batched_linalg` (batched small inverses)."""
