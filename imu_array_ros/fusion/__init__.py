"""Estimators of the array's motion: ML fusion with its Cramér–Rao bound (skog2016).

* :mod:`.ml_fusion` (``MLFusion``): the ML solve of the model's linear form, built on
  :mod:`.validity` (valid-axis masks and patterns), :mod:`.pattern_geometry`
  (matrices per pattern of valid axes), :mod:`.gauss_newton` (the solver) and
  :mod:`.batched_linalg` (batched small inverses); :mod:`.crb` the bound itself;
* :mod:`.model_fusion` (``ModelFusion``): the fusion with every term of the sensor model
  (non-linear terms compensated) -- what the command line, the nodes and the Python API run;
* :mod:`.stream` (chunked fusion of a whole recording), :mod:`.live` (serialized messages in
  and out, for the fusion node), :mod:`.residuals` (normalised residuals: how well the model
  explains the readings), :mod:`.tensor_method` (the angular-acceleration-tensor baseline).
"""
