"""The one fitting engine: maximum likelihood of sensor-model terms jointly with every sample's motion
(:func:`fit_terms`), the motion alone (:func:`fit_motion`), and the score test of candidate terms
(:func:`score_blocks`), with the Cramér-Rao bound, gauge fixing and identifiability checks.
Motion models (any rigid motion, static poses on gravity) are in :mod:`.motion_models`."""
