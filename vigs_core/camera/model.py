"""Monocular camera model: pinhole intrinsics plus an optional lens-distortion model.

Pixel convention (used everywhere in the project): pixel ``(row i, column j)`` has its *centre* at
``(u, v) = (j, i)``; the image covers ``u in [-0.5, width - 0.5]``. This is OpenCV's and Kalibr's
convention, so EuRoC / Kalibr intrinsics are used unchanged.

Projection of a camera-frame point ``P = (X, Y, Z)`` (metres)::

    xy = (X / Z, Y / Z)                  (normalized image plane)
    xy_d = distort(xy)                   (see :mod:`vigs_core.camera.distortion`)
    u = fx * x_d + cx,  v = fy * y_d + cy

Resizing an image by ``s`` maps pixel centres ``u -> (u + 0.5) s - 0.5`` (the half-pixel convention
of ``cv2.resize`` and of area averaging), hence ``fx' = s fx`` and ``cx' = (cx + 0.5) s - 0.5``
(same for y). Distortion acts on the normalized plane, so its coefficients do not change.
"""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.camera.distortion import DISTORTION_COEFF_COUNTS, distort, undistort

MIN_DEPTH = 1e-6
"""Smallest depth (metres) treated as in front of the camera; see :meth:`CameraModel.project`."""


def _positive_int(name: str, value) -> int:
    if isinstance(value, bool):
        raise TypeError(f"CameraModel.{name} must be a positive integer (pixels), got bool {value!r}")
    try:
        result = operator.index(value)
    except TypeError:
        raise TypeError(
            f"CameraModel.{name} must be a positive integer (pixels), got {type(value).__name__} {value!r}"
        ) from None
    if result <= 0:
        raise ValueError(f"CameraModel.{name} must be a positive integer (pixels), got {result}")
    return result


def _finite_float(name: str, value, positive: bool = False) -> float:
    try:
        result = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"CameraModel.{name} must be a real number, got {type(value).__name__} {value!r}") from None
    if not math.isfinite(result) or (positive and result <= 0.0):
        expected = "a finite number > 0" if positive else "a finite number"
        raise ValueError(f"CameraModel.{name} must be {expected}, got {result}")
    return result


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with optional distortion (immutable; validated on construction).

    Args:
        width: image width in pixels.
        height: image height in pixels.
        fx: focal length along u in pixels (> 0).
        fy: focal length along v in pixels (> 0).
        cx: principal point u in pixels (pixel-centre convention, see module docstring).
        cy: principal point v in pixels.
        distortion: ``"none"`` (pinhole), ``"radtan"`` (radial-tangential, OpenCV/EuRoC) or
            ``"equidistant"`` (Kannala-Brandt fisheye, Kalibr ``pinhole-equi`` / ``cv2.fisheye``).
        coeffs: distortion coefficients: ``()`` for none; ``(k1, k2, p1, p2)`` or
            ``(k1, k2, p1, p2, k3)`` for radtan; ``(k1, k2, k3, k4)`` for equidistant.
            Any sequence of numbers is accepted and stored as a tuple of floats.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: str = "none"
    coeffs: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "width", _positive_int("width", self.width))
        set_(self, "height", _positive_int("height", self.height))
        set_(self, "fx", _finite_float("fx", self.fx, positive=True))
        set_(self, "fy", _finite_float("fy", self.fy, positive=True))
        set_(self, "cx", _finite_float("cx", self.cx))
        set_(self, "cy", _finite_float("cy", self.cy))
        if not isinstance(self.distortion, str) or self.distortion not in DISTORTION_COEFF_COUNTS:
            raise ValueError(
                f"CameraModel.distortion must be one of {sorted(DISTORTION_COEFF_COUNTS)}, got {self.distortion!r}"
            )
        if isinstance(self.coeffs, (str, bytes)):
            raise TypeError(f"CameraModel.coeffs must be a sequence of numbers, got {self.coeffs!r}")
        try:
            raw = list(np.ravel(np.asarray(self.coeffs, dtype=object)))
        except TypeError:
            raise TypeError(f"CameraModel.coeffs must be a sequence of numbers, got {self.coeffs!r}") from None
        counts = DISTORTION_COEFF_COUNTS[self.distortion]
        if len(raw) not in counts:
            expected = " or ".join(str(c) for c in counts)
            raise ValueError(
                f"CameraModel with distortion={self.distortion!r} needs {expected} coefficients, got {len(raw)}: {raw}"
            )
        coeffs = tuple(_finite_float(f"coeffs[{i}]", c) for i, c in enumerate(raw))
        set_(self, "coeffs", coeffs)

    # ------------------------------------------------------------------ matrices and conversions
    def K(self, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> torch.Tensor:
        """Intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (3, 3)."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device
        )

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray]:
        """``(K (3, 3), dist (N,))`` as float64 numpy arrays for OpenCV.

        radtan: ``dist = (k1, k2, p1, p2[, k3])`` for ``cv2.projectPoints`` / ``cv2.undistortPoints``;
        equidistant: ``dist = (k1, k2, k3, k4)`` for the ``cv2.fisheye`` functions;
        none: ``dist = zeros(5)`` for the standard (non-fisheye) functions.
        """
        dist = np.zeros(5) if self.distortion == "none" else np.array(self.coeffs, dtype=np.float64)
        return self.K().numpy(), dist

    def pinhole(self) -> CameraModel:
        """The same intrinsics without distortion."""
        return CameraModel(self.width, self.height, self.fx, self.fy, self.cx, self.cy)

    # ------------------------------------------------------------------ resizing
    def resized(self, width: int, height: int) -> CameraModel:
        """Intrinsics for this image resampled to ``width x height`` pixels.

        With ``s_x = width / self.width`` and ``s_y = height / self.height``:
        ``fx' = s_x fx``, ``cx' = (cx + 0.5) s_x - 0.5`` (and the same in y), which is what
        ``cv2.resize(image, (width, height))`` does to pixel centres.
        """
        width = _positive_int("width", width)
        height = _positive_int("height", height)
        sx = width / self.width
        sy = height / self.height
        return CameraModel(
            width,
            height,
            self.fx * sx,
            self.fy * sy,
            (self.cx + 0.5) * sx - 0.5,
            (self.cy + 0.5) * sy - 0.5,
            self.distortion,
            self.coeffs,
        )

    def scaled(self, factor: float) -> CameraModel:
        """Intrinsics for the image resized by ``factor`` (e.g. 0.5 for one pyramid level down).

        The new size is ``round(width * factor) x round(height * factor)`` (at least 1 pixel) and the
        intrinsics follow :meth:`resized`; when ``width * factor`` is an integer this is exactly
        ``fx' = factor fx``, ``cx' = (cx + 0.5) factor - 0.5``.
        """
        factor = _finite_float("scaled(factor)", factor, positive=True)
        return self.resized(max(1, round(self.width * factor)), max(1, round(self.height * factor)))

    def pyramid(self, levels: int) -> list[CameraModel]:
        """``levels`` cameras ``[self, self.scaled(1/2), self.scaled(1/2).scaled(1/2), ...]``.

        Each level halves the previous one (sizes rounded as in :meth:`scaled`), matching an image
        pyramid built by repeated 2x downsampling.
        """
        levels = _positive_int("pyramid(levels)", levels)
        cams = [self]
        for _ in range(levels - 1):
            cams.append(cams[-1].scaled(0.5))
        return cams

    def pixel_grid(
        self, stride: int = 1, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> torch.Tensor:
        """Pixel-centre coordinates ``uv`` (H', W', 2) of the image downsampled by ``stride``.

        ``uv[i, j]`` is the centre of pixel ``(i, j)`` of ``self.scaled(1 / stride)``, expressed in
        *this* camera's pixels: ``u = (j + 0.5) width / W' - 0.5`` (``= j`` for ``stride = 1``).
        """
        stride = _positive_int("pixel_grid(stride)", stride)
        small = self.scaled(1.0 / stride)
        sx = self.width / small.width
        sy = self.height / small.height
        u = (torch.arange(small.width, dtype=dtype, device=device) + 0.5) * sx - 0.5
        v = (torch.arange(small.height, dtype=dtype, device=device) + 0.5) * sy - 0.5
        vv, uu = torch.meshgrid(v, u, indexing="ij")
        return torch.stack((uu, vv), -1)

    # ------------------------------------------------------------------ projection
    def project_with_depth(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Project camera-frame points (..., 3) -> ``(uv (..., 2) pixels, depth Z (...,))``.

        Points with ``Z <= MIN_DEPTH`` (behind or on the camera plane) have no meaningful projection:
        their ``uv`` is computed with ``Z`` replaced by ``MIN_DEPTH`` (finite, usually far outside the
        image). Mask them with ``depth > MIN_DEPTH``. Differentiable; dtype and device follow ``points``.
        """
        if points.shape[-1] != 3:
            raise ValueError(f"project expects points of shape (..., 3), got {tuple(points.shape)}")
        z = points[..., 2]
        xy = points[..., :2] / z.clamp(min=MIN_DEPTH).unsqueeze(-1)
        xy_d = distort(self.distortion, xy, self.coeffs)
        u = self.fx * xy_d[..., 0] + self.cx
        v = self.fy * xy_d[..., 1] + self.cy
        return torch.stack((u, v), -1), z

    def project(self, points: torch.Tensor) -> torch.Tensor:
        """Project camera-frame points (..., 3) to pixels ``uv`` (..., 2) through the distortion.

        See :meth:`project_with_depth` for points with ``Z <= MIN_DEPTH``. Note that radtan and
        equidistant models are only one-to-one inside the lens's field of view.
        """
        return self.project_with_depth(points)[0]

    def unproject(self, uv: torch.Tensor, tol_px: float = 1e-9, max_iters: int = 30) -> torch.Tensor:
        """Back-project pixels ``uv`` (..., 2) to viewing rays (..., 3) with ``z = 1``.

        Removes the distortion iteratively (Newton, see :mod:`vigs_core.camera.distortion`) until
        the reprojection residual is below ``tol_px`` pixels (or the dtype's precision). The rays are
        not normalized: ``P = depth * ray`` is the point at depth ``Z = depth``. Differentiable.
        Fisheye pixels at or beyond 90 degrees from the optical axis have no ``z = 1`` ray; their
        angle is clamped just below 90 degrees (rays about 1e6 long).
        """
        if uv.shape[-1] != 2:
            raise ValueError(f"unproject expects pixels of shape (..., 2), got {tuple(uv.shape)}")
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        tol = max(tol_px / max(self.fx, self.fy), 16.0 * torch.finfo(uv.dtype).eps)
        xy = undistort(self.distortion, torch.stack((xd, yd), -1), self.coeffs, tol, max_iters)
        return torch.cat((xy, torch.ones_like(xy[..., :1])), -1)

    def backproject(self, uv: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """Camera-frame points (..., 3) at pixels ``uv`` (..., 2) and depths ``Z`` (...,) in metres."""
        return self.unproject(uv) * depth.unsqueeze(-1)

    def in_image(self, uv: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Boolean mask (...,) of pixels ``uv`` (..., 2) at least ``margin`` px inside the image area
        ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``."""
        u, v = uv[..., 0], uv[..., 1]
        return (
            (u >= margin - 0.5)
            & (u <= self.width - 0.5 - margin)
            & (v >= margin - 0.5)
            & (v <= self.height - 0.5 - margin)
        )
