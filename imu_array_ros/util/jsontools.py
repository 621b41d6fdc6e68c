"""Strict JSON output: values made safe for ``json.dumps(..., allow_nan=False)``."""

from __future__ import annotations

__all__ = ["json_safe"]


def json_safe(obj):
    """JSON-ready copy for strict JSON (``allow_nan=False``): non-finite floats become ``None`` (``null``),
    tuples and numpy arrays lists, numpy scalars Python scalars, keys strings."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist") and not isinstance(obj, (str, bytes)):  # numpy arrays and scalars
        obj = obj.tolist()
        if isinstance(obj, list):
            return json_safe(obj)
    if isinstance(obj, float) and not (obj == obj and abs(obj) != float("inf")):
        return None
    return obj
