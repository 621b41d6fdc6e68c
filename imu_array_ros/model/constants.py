"""Physical constants, defined once for the whole package."""

STANDARD_GRAVITY = 9.80665
"""m/s^2, standard gravity (the OpenShoe scale and the simulator's gravity)."""

__all__ = ["STANDARD_GRAVITY"]
