"""Valid ranges of numeric config fields, stated once on the dataclass field::

    min_confidence: float = bounded(0.05, 0, 1)       # [0, 1]
    iterations: int = bounded(8, 0)                   # [0, inf)
    fb_sigma: float = bounded(1.0, 0, lo_open=True)   # (0, inf): zero would divide

The range lives in the field's metadata (:func:`field_range`); parameter files are checked against it
(:func:`vigs_core.system.config.checked_value`, ``vigs launch``) and the ROS nodes declare it in their parameter
descriptors (:func:`vigs_ros.params.declare`). Values set in code are not checked.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Range:
    """``lo <= value <= hi`` (``lo < value`` with ``lo_open``); None: unbounded at that end. NaN is never in it."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def __contains__(self, value: float) -> bool:
        if math.isnan(value):
            return False
        if self.lo is not None and (value < self.lo or (self.lo_open and value == self.lo)):
            return False
        return self.hi is None or value <= self.hi

    def __str__(self) -> str:
        left = "(-inf" if self.lo is None else f"{'(' if self.lo_open else '['}{self.lo:g}"
        right = "inf)" if self.hi is None else f"{self.hi:g}]"
        return f"{left}, {right}"


def bounded(default: Any, lo: float | None = None, hi: float | None = None, *, lo_open: bool = False) -> Any:
    """A dataclass field with ``default`` and the valid :class:`Range` ``[lo, hi]`` (``(lo, hi]`` with
    ``lo_open``); a default outside it is a ValueError at class definition."""
    rng = Range(lo, hi, lo_open)
    if default is not None and default not in rng:
        raise ValueError(f"default {default!r} outside its range {rng}")
    return dataclasses.field(default=default, metadata={"range": rng})


def field_range(f: dataclasses.Field) -> Range | None:
    """The :class:`Range` declared with :func:`bounded` on a dataclass field, or None."""
    return f.metadata.get("range")
