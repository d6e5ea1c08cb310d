"""Undistorter and inner_pinhole: against OpenCV's maps, straight lines stay straight, input checks."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel, Undistorter, inner_pinhole

torch.set_num_threads(1)

from camera_models import EUROC_CAM0, TUMVI_CAM0  # noqa: E402


def test_maps_match_opencv_radtan():
    dst = EUROC_CAM0.pinhole().scaled(0.9)
    und = Undistorter(EUROC_CAM0, dst)
    K, dist = EUROC_CAM0.to_opencv()
    map_x, map_y = cv2.initUndistortRectifyMap(
        K, dist, np.eye(3), dst.to_opencv()[0], (dst.width, dst.height), cv2.CV_32FC1
    )
    assert und.map_x.shape == (dst.height, dst.width) and und.map_x.dtype == np.float32
    assert np.abs(und.map_x - map_x).max() < 1e-3
    assert np.abs(und.map_y - map_y).max() < 1e-3


def test_maps_match_opencv_fisheye():
    dst = CameraModel(400, 400, 120.0, 120.0, 199.5, 199.5)
    und = Undistorter(TUMVI_CAM0, dst)
    K, dist = TUMVI_CAM0.to_opencv()
    map_x, map_y = cv2.fisheye.initUndistortRectifyMap(
        K, dist, np.eye(3), dst.to_opencv()[0], (dst.width, dst.height), cv2.CV_32FC1
    )
    assert np.abs(und.map_x - map_x).max() < 1e-3
    assert np.abs(und.map_y - map_y).max() < 1e-3
    assert und.valid_mask.all()


def test_default_target_matches_opencv_alpha0():
    und = Undistorter(EUROC_CAM0)
    K, dist = EUROC_CAM0.to_opencv()
    K_cv, _ = cv2.getOptimalNewCameraMatrix(K, dist, (EUROC_CAM0.width, EUROC_CAM0.height), 0.0)
    dst = und.dst
    assert dst.distortion == "none" and (dst.width, dst.height) == (EUROC_CAM0.width, EUROC_CAM0.height)
    # OpenCV samples the border more coarsely, hence the sub-pixel tolerance
    np.testing.assert_allclose(dst.to_opencv()[0], K_cv, atol=0.5)
    # alpha = 0: every target pixel sees the source image, and the rectangle touches the border
    assert und.valid_mask.all()
    for m, last in ((und.map_x, EUROC_CAM0.width - 1), (und.map_y, EUROC_CAM0.height - 1)):
        assert m.min() == pytest.approx(0.0, abs=1e-3) and m.max() == pytest.approx(last, abs=1e-3)


@pytest.mark.parametrize("src", [EUROC_CAM0, TUMVI_CAM0], ids=["euroc", "tumvi"])
def test_inner_pinhole_keep_aspect(src):
    free = inner_pinhole(src)
    square = inner_pinhole(src, keep_aspect=True)
    assert square.fx / square.fy == pytest.approx(src.fx / src.fy)
    assert square.fx >= free.fx - 1e-9 and square.fy >= free.fy - 1e-9
    assert Undistorter(src, square).valid_mask.all()
    small = inner_pinhole(src, width=200, height=100)
    assert (small.width, small.height) == (200, 100)
    assert Undistorter(src, small).valid_mask.all()


def line_image(cam: CameraModel, normal: np.ndarray, sigma: float = 0.01) -> np.ndarray:
    """Float image of the 3D line in the plane through the camera centre with unit ``normal``.

    Pixel intensity is ``exp(-(n . r)^2 / (2 sigma^2))`` for the unit viewing ray ``r`` of the pixel,
    so the bright ridge is the (distorted) image of every 3D line in that plane.
    """
    rays = cam.unproject(cam.pixel_grid(dtype=torch.float64)).numpy()
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    return np.exp(-((rays @ normal) ** 2) / (2 * sigma**2)).astype(np.float32)


def ridge_line_residual(image: np.ndarray, columns: np.ndarray) -> float:
    """Largest distance (px) of the per-column intensity centroid of the ridge from its fitted line."""
    rows = np.arange(image.shape[0], dtype=np.float64)
    centroids = []
    for c in columns:
        w = image[:, c].astype(np.float64)
        w = np.where(w > 0.05 * w.max(), w, 0.0)
        centroids.append((w * rows).sum() / w.sum())
    centroids = np.array(centroids)
    coef = np.polyfit(columns, centroids, 1)
    return float(np.abs(np.polyval(coef, columns) - centroids).max())


@pytest.mark.parametrize("src", [EUROC_CAM0, TUMVI_CAM0], ids=["euroc", "tumvi"])
def test_undistorted_straight_line_is_straight(src):
    # a 3D line crossing the upper part of the view, where distortion bends it most
    p0, p1 = np.array([-3.0, -1.2, 3.0]), np.array([3.0, -1.0, 3.5])
    normal = np.cross(p0, p1)
    normal /= np.linalg.norm(normal)
    distorted = line_image(src, normal)
    und = Undistorter(src)
    rectified = und.remap(distorted)
    assert rectified.shape == (und.dst.height, und.dst.width) and rectified.dtype == np.float32
    margin = und.dst.width // 10
    columns = np.arange(margin, und.dst.width - margin, 4)
    # straight after undistortion (to a fraction of a pixel), clearly curved before
    assert ridge_line_residual(rectified, columns) < 0.1
    src_columns = np.arange(src.width // 10, src.width - src.width // 10, 4)
    assert ridge_line_residual(distorted, src_columns) > 3.0
    # the ridge lies where the pinhole target projects the 3D line
    mid = 0.5 * (p0 + p1)
    u, v = und.dst.project(torch.from_numpy(mid)).tolist()
    col = int(round(u))
    w = rectified[:, col].astype(np.float64)
    w = np.where(w > 0.05 * w.max(), w, 0.0)
    assert (w * np.arange(len(w))).sum() / w.sum() == pytest.approx(v, abs=0.1)


def test_remap_channels_dtypes_and_round_trip():
    src = EUROC_CAM0
    und = Undistorter(src)
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (src.height, src.width), dtype=np.uint8)
    colour = rng.integers(0, 256, (src.height, src.width, 3), dtype=np.uint8)
    assert und.remap(grey).shape == (src.height, src.width) and und.remap(grey).dtype == np.uint8
    assert und.remap(colour).shape == (src.height, src.width, 3)
    # a smooth image undistorted and distorted again comes back (inside the region both maps cover)
    vv, uu = np.mgrid[0 : src.height, 0 : src.width].astype(np.float32)
    smooth = np.sin(uu / 37.0) + np.cos(vv / 23.0)
    back = Undistorter(und.dst, src).remap(und.remap(smooth))
    inner = np.zeros_like(smooth, dtype=bool)
    inner[120:360, 180:570] = True
    assert np.abs(back - smooth)[inner].max() < 0.02


def test_invalid_inputs_raise_clear_errors():
    with pytest.raises(TypeError, match="src must be a CameraModel"):
        Undistorter(EUROC_CAM0.to_opencv()[0])
    with pytest.raises(TypeError, match="dst must be a CameraModel or None"):
        Undistorter(EUROC_CAM0, "pinhole")
    und = Undistorter(EUROC_CAM0)
    with pytest.raises(ValueError, match=r"image of shape \(480, 752\[, C\]\).*got \(240, 376\)"):
        und.remap(np.zeros((240, 376), dtype=np.uint8))
    with pytest.raises(ValueError, match="at least 2x2"):
        inner_pinhole(EUROC_CAM0, width=1)
