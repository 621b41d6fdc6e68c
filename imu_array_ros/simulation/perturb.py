"""Seeded random term values: a plausible 'true' array around a nominal one.

``perturb(model, rng, scales)`` adds zero-mean Gaussian errors with the given
1-sigma sizes (per registry name, in the term's parameter units) to the
model's term values, so the same terms that fusion, calibration and
discovery use describe the truth in simulation (``imu-array simulate
--error-seed``).
"""

from __future__ import annotations

import numpy as np

from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.terms import REGISTRY, term_names

__all__ = ["DEFAULT_ERROR_SCALES", "TERM_TEST_SIZES", "TERM_TEST_CENTRES", "perturb"]

#: Default 1-sigma sizes of seeded errors: positions per carlsson2017 Sec. IV
#: (sigma_r = 1 mm would be the paper's pessimistic case; 0.1 mm is PCB placement,
#: skog2016 footnote 5); gain/bias/angles of the order of nilsson2014 Table I.
DEFAULT_ERROR_SCALES = {
    "position": 1e-4,
    "accelerometer_gain": 5e-3,
    "accelerometer_nonorthogonality": np.deg2rad(0.2),
    "accelerometer_misalignment": np.deg2rad(0.5),
    "accelerometer_bias": 0.3,
    "gyroscope_bias": np.deg2rad(1.0),
}

#: A clearly visible 1-sigma size of every registered term (SI units of its parameters),
#: used by the Jacobian tests and the per-term Monte Carlo to exercise each term away from
#: identity; a new term must be added here (test_sensor_terms checks the registry against it).
TERM_TEST_SIZES = {
    "position": 0.01, "axis_offsets": 2e-3, "time_offset": 2e-3,
    "accelerometer_misalignment": 0.01, "accelerometer_nonorthogonality": 0.01, "accelerometer_nonlinearity": 1e-3,
    "accelerometer_gain": 0.02, "accelerometer_bias": 0.3, "bias_drift": 1e-3,
    "gyroscope_misalignment": 0.01, "gyroscope_nonorthogonality": 0.01, "gyroscope_gain": 0.02,
    "gyroscope_g_sensitivity": 1e-3, "gyroscope_bias": 0.01,
    "stamp_clock": 1e-3, "sample_clock": 1e-5, "gyroscope_sample_clock": 1e-5, "accelerometer_sample_clock": 1e-5,
}

#: Terms whose identity value is not a valid place to perturb around: the values (per parameter) the
#: test sizes are added to (a sample clock of period 1 ms, its phase inside the period).
TERM_TEST_CENTRES = {"sample_clock": (1e-3, 1500.0, 4e-4), "stamp_clock": (0.0, 100.0),
                     "gyroscope_sample_clock": (1e-3, -800.0, 2e-4), "accelerometer_sample_clock": (1e-3, 300.0, 1e-4)}


def perturb(model: SensorModel, rng: np.random.Generator, scales: dict[str, float] | None = None) -> SensorModel:
    """``model`` with N(0, sigma^2) added to every parameter of each term in ``scales``
    (registry name -> sigma; 0 leaves the term alone), drawn in registry order."""
    scales = DEFAULT_ERROR_SCALES if scales is None else scales
    unknown = sorted(set(scales) - set(REGISTRY))
    if unknown:
        raise ValueError(f"unknown term {unknown[0]!r} (known: {', '.join(term_names())})")
    values = {}
    for name in term_names():
        sigma = float(scales.get(name, 0.0))
        if sigma:
            v = model.terms[name].values
            values[name] = v + rng.normal(0.0, sigma, v.shape)
    return model.with_terms(**values)
