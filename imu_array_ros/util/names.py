"""The did-you-mean of a mistyped name (a registry term, a node parameter, ...)."""

from __future__ import annotations

import difflib
from typing import Iterable

__all__ = ["did_you_mean"]


def did_you_mean(name: str, known: Iterable[str]) -> str | None:
    """The closest of ``known`` to ``name`` (difflib's ratio >= 0.6), None when none is close."""
    near = difflib.get_close_matches(str(name), list(known), n=1)
    return near[0] if near else None
