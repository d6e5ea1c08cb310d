"""Correspondence estimation between two images on a reduced pixel grid (VIGS-SLAM 3.1, DROID-SLAM 3.2).

For a source image ``i`` and a target image ``j`` an estimator returns, for each pixel of the source's reduced
grid, its coordinates ``u*_ij`` in the target and a confidence ``w_ij`` in [0, 1]. Estimators may use an
initial guess of the targets (from the geometric warp with the current poses and depths). The dense solver
only consumes ``(target, weight)``, so a learned operator (DROID's update) fits the same interface.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class PixelGrid:
    """The reduced grid of an image: cell ``(r, c)`` of ``stride x stride`` input pixels has its centre at
    ``(stride c + (stride - 1) / 2, stride r + (stride - 1) / 2)`` input pixels.

    Args:
        width, height: input image size, pixels.
        stride: cell size, pixels (8 = 1/8 of the input resolution).
    """

    width: int
    height: int
    stride: int = 8

    def __post_init__(self) -> None:
        if self.stride < 1 or self.width < self.stride or self.height < self.stride:
            raise ValueError(f"PixelGrid: image {self.width}x{self.height} and stride {self.stride}; expected a "
                             "positive stride no larger than the image")

    @property
    def cols(self) -> int:
        return self.width // self.stride

    @property
    def rows(self) -> int:
        return self.height // self.stride

    @property
    def size(self) -> int:
        """Number of grid pixels ``P``."""
        return self.rows * self.cols

    def coords(self) -> np.ndarray:
        """Cell centres (P, 2) float64, row-major, in input pixels."""
        s = self.stride
        u = s * np.arange(self.cols) + (s - 1) / 2.0
        v = s * np.arange(self.rows) + (s - 1) / 2.0
        uu, vv = np.meshgrid(u, v)
        return np.stack((uu.ravel(), vv.ravel()), -1)

    def cell_of(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flat cell index (N,) of pixel coordinates (N, 2) and whether they fall inside the grid (N,)."""
        c = np.floor(uv[:, 0] / self.stride).astype(np.int64)
        r = np.floor(uv[:, 1] / self.stride).astype(np.int64)
        inside = (c >= 0) & (c < self.cols) & (r >= 0) & (r < self.rows)
        return np.where(inside, r * self.cols + c, 0), inside


@dataclass
class Correspondences:
    """Targets ``(P, 2)`` (input pixels in the target image) and confidences ``(P,)`` in [0, 1] of the source
    grid pixels; ``mean_flow`` is the confidence-weighted mean of ``|target - source|``, pixels."""

    target: np.ndarray
    weight: np.ndarray
    mean_flow: float


class CorrespondenceEstimator(Protocol):
    """Dense correspondences from a source to a target image on the source's reduced grid."""

    grid: PixelGrid

    def estimate(self, source: np.ndarray, target: np.ndarray, initial_target: np.ndarray | None = None,
                 forward_backward: bool = True) -> Correspondences:
        """Correspondences of ``source`` (H, W) uint8 grid pixels in ``target`` (H, W) uint8.

        ``initial_target`` (P, 2): a guess of the targets (e.g. the geometric warp), or None.
        ``forward_backward``: whether the confidences may use a (costly) consistency check; False asks for a
        cheaper estimate (per-frame tracking).
        """

    def estimate_pair(self, a: np.ndarray, b: np.ndarray, initial_ab: np.ndarray | None = None,
                      initial_ba: np.ndarray | None = None) -> tuple[Correspondences, Correspondences]:
        """Correspondences ``a -> b`` and ``b -> a`` (the two edges of a keyframe pair) with the confidences
        of :meth:`estimate`; an estimator may share work between the directions (e.g. each direction's flow
        is the other's backward flow). ``initial_ab`` / ``initial_ba``: guesses of the targets, or None."""
