"""Image undistortion/rectification to a (pinhole) target camera with OpenCV remap maps.

For every pixel centre ``uv_dst`` of the target camera the map stores where it comes from in the
source image: ``uv_src = src.project(dst.unproject(uv_dst))``. This is the backward mapping that
``cv2.initUndistortRectifyMap`` / ``cv2.fisheye.initUndistortRectifyMap`` build (without a
rectifying rotation), computed here with the project's own camera models in float64, so any pair
of :class:`CameraModel` s works (radtan, equidistant or none, in either role).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from vigs_core.camera.model import CameraModel


def inner_pinhole(
    src: CameraModel, width: int | None = None, height: int | None = None, keep_aspect: bool = False
) -> CameraModel:
    """Pinhole camera whose whole image sees only valid pixels of ``src`` (OpenCV ``alpha = 0``).

    The border pixel centres of ``src`` (``u = 0``, ``u = width - 1``, ``v = 0``, ``v = height - 1``)
    are unprojected to the normalized plane; the largest axis-aligned rectangle
    ``[x_left, x_right] x [y_top, y_bottom]`` inside that boundary (innermost x of the left and right
    edges, innermost y of the top and bottom edges) is mapped onto the target's pixel centres
    ``0 .. width - 1`` and ``0 .. height - 1``::

        fx' = (width - 1) / (x_right - x_left),  cx' = -fx' x_left   (same for y)

    This equals ``cv2.getOptimalNewCameraMatrix(K, dist, size, alpha=0)`` up to OpenCV's coarser
    border sampling. With ``keep_aspect`` the focal lengths keep the ratio ``fx / fy`` of ``src``:
    both are scaled by the larger of the two factors above and the (then smaller) image is centred
    in the rectangle.

    Args:
        src: the distorted camera.
        width, height: target image size in pixels (default: the size of ``src``).
        keep_aspect: keep ``fx' / fy' = fx / fy`` (square pixels stay square).
    """
    width = src.width if width is None else width
    height = src.height if height is None else height
    if width < 2 or height < 2:
        raise ValueError(f"inner_pinhole needs a target image of at least 2x2 pixels, got {width}x{height}")
    us = torch.arange(src.width, dtype=torch.float64)
    vs = torch.arange(src.height, dtype=torch.float64)
    u_last, v_last = float(src.width - 1), float(src.height - 1)
    left = src.unproject(torch.stack((torch.zeros_like(vs), vs), -1))
    right = src.unproject(torch.stack((torch.full_like(vs, u_last), vs), -1))
    top = src.unproject(torch.stack((us, torch.zeros_like(us)), -1))
    bottom = src.unproject(torch.stack((us, torch.full_like(us, v_last)), -1))
    x_left, x_right = left[:, 0].max().item(), right[:, 0].min().item()
    y_top, y_bottom = top[:, 1].max().item(), bottom[:, 1].min().item()
    if not (x_right > x_left and y_bottom > y_top):
        raise ValueError(f"camera {src} has no valid inner rectangle after undistortion")
    fx = (width - 1) / (x_right - x_left)
    fy = (height - 1) / (y_bottom - y_top)
    if not keep_aspect:
        return CameraModel(width, height, fx, fy, -fx * x_left, -fy * y_top)
    scale = max(fx / src.fx, fy / src.fy)
    fx, fy = scale * src.fx, scale * src.fy
    cx = 0.5 * (width - 1) - 0.5 * fx * (x_left + x_right)
    cy = 0.5 * (height - 1) - 0.5 * fy * (y_top + y_bottom)
    return CameraModel(width, height, fx, fy, cx, cy)


class Undistorter:
    """Resample images of camera ``src`` into camera ``dst`` (by default :func:`inner_pinhole`).

    Attributes:
        src, dst: the source and target cameras.
        map_x, map_y: float32 arrays (dst.height, dst.width): source pixel coordinates of each
            target pixel centre, the maps passed to ``cv2.remap``.
        valid_mask: bool array (dst.height, dst.width): target pixels whose source position lies
            between the source's border pixel centres (so bilinear interpolation reads only real pixels).
    """

    def __init__(
        self, src: CameraModel, dst: CameraModel | None = None, interpolation: int = cv2.INTER_LINEAR
    ) -> None:
        if not isinstance(src, CameraModel):
            raise TypeError(f"Undistorter src must be a CameraModel, got {type(src).__name__}")
        if dst is not None and not isinstance(dst, CameraModel):
            raise TypeError(f"Undistorter dst must be a CameraModel or None, got {type(dst).__name__}")
        self.src = src
        self.dst = inner_pinhole(src) if dst is None else dst
        self.interpolation = interpolation
        grid = self.dst.pixel_grid(dtype=torch.float64)
        uv_src = src.project(self.dst.unproject(grid)).numpy()
        self.map_x = np.ascontiguousarray(uv_src[..., 0], dtype=np.float32)
        self.map_y = np.ascontiguousarray(uv_src[..., 1], dtype=np.float32)
        slack = 1e-3
        self.valid_mask = (
            (uv_src[..., 0] >= -slack)
            & (uv_src[..., 0] <= src.width - 1 + slack)
            & (uv_src[..., 1] >= -slack)
            & (uv_src[..., 1] <= src.height - 1 + slack)
        )

    def remap(self, image: np.ndarray, border_value: float = 0.0) -> np.ndarray:
        """Undistort ``image`` (src.height, src.width[, C]) -> (dst.height, dst.width[, C]), same dtype.

        Target pixels that fall outside the source image get ``border_value``.
        """
        image = np.asarray(image)
        if image.ndim not in (2, 3) or image.shape[:2] != (self.src.height, self.src.width):
            raise ValueError(
                f"Undistorter.remap expects an image of shape ({self.src.height}, {self.src.width}[, C]) "
                f"for source camera {self.src.width}x{self.src.height}, got {image.shape}"
            )
        return cv2.remap(
            image,
            self.map_x,
            self.map_y,
            self.interpolation,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=border_value,
        )
