"""CameraModel and distortion models: against OpenCV, round trips, resizing, gradients, input checks."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from vigs_core.camera import MIN_DEPTH, CameraModel
from vigs_core.camera.distortion import (
    equidistant_distort,
    equidistant_undistort,
    radtan_distort,
    radtan_jacobian,
)

torch.set_num_threads(1)

# EuRoC MAV cam0 (sensor.yaml of every EuRoC sequence): pinhole + radtan, 752x480.
from camera_models import EQUI_STRONG, EUROC_CAM0, RADTAN5, TUMVI_CAM0  # noqa: E402

CAMERAS = [EUROC_CAM0, RADTAN5, TUMVI_CAM0, EQUI_STRONG]
CAMERA_IDS = ["euroc", "radtan5", "tumvi", "equi_strong"]


def random_points(n: int, max_angle_deg: float, seed: int) -> np.ndarray:
    """(n, 3) float64 points in front of the camera within ``max_angle_deg`` of the optical axis."""
    rng = np.random.default_rng(seed)
    theta = np.deg2rad(max_angle_deg) * np.sqrt(rng.uniform(0.0, 1.0, n))
    phi = rng.uniform(-np.pi, np.pi, n)
    depth = rng.uniform(0.3, 20.0, n)
    r = np.tan(theta)
    return np.stack((r * np.cos(phi), r * np.sin(phi), np.ones(n)), -1) * depth[:, None]


def image_points(cam: CameraModel, step: int = 8) -> torch.Tensor:
    """Pixel grid (N, 2) float64 covering the whole image, borders and corners included."""
    u = torch.cat((torch.arange(0, cam.width, step, dtype=torch.float64), torch.tensor([cam.width - 1.0])))
    v = torch.cat((torch.arange(0, cam.height, step, dtype=torch.float64), torch.tensor([cam.height - 1.0])))
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return torch.stack((uu, vv), -1).reshape(-1, 2)


def assert_covers_image(cam: CameraModel, uv: np.ndarray) -> None:
    """The compared points reach every border region, so the test spans the whole field of view."""
    assert len(uv) > 500
    assert uv[:, 0].min() < 0.05 * cam.width and uv[:, 0].max() > 0.95 * cam.width
    assert uv[:, 1].min() < 0.05 * cam.height and uv[:, 1].max() > 0.95 * cam.height


def fov_deg(cam: CameraModel) -> float:
    """Half-angle (degrees) of the cone of test points: reaches beyond every image border."""
    return {EUROC_CAM0: 55.0, RADTAN5: 45.0, TUMVI_CAM0: 88.0, EQUI_STRONG: 88.0}[cam]


# ---------------------------------------------------------------------------------------------- OpenCV
@pytest.mark.parametrize("cam", [EUROC_CAM0, RADTAN5], ids=["euroc", "radtan5"])
def test_project_radtan_matches_opencv(cam):
    pts = random_points(2000, fov_deg(cam), seed=1)
    K, dist = cam.to_opencv()
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    uv = cam.project(torch.from_numpy(pts)).numpy()
    inside = cam.in_image(torch.from_numpy(ref[:, 0])).numpy()
    assert np.abs(uv - ref[:, 0])[inside].max() < 1e-6
    assert_covers_image(cam, uv[inside])


@pytest.mark.parametrize("cam", [TUMVI_CAM0, EQUI_STRONG], ids=["tumvi", "equi_strong"])
def test_project_equidistant_matches_opencv_fisheye(cam):
    pts = random_points(2000, fov_deg(cam), seed=2)
    K, dist = cam.to_opencv()
    ref, _ = cv2.fisheye.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), K, dist)
    uv = cam.project(torch.from_numpy(pts)).numpy()
    inside = cam.in_image(torch.from_numpy(ref[:, 0])).numpy()
    assert np.abs(uv - ref[:, 0])[inside].max() < 1e-6
    assert_covers_image(cam, uv[inside])


def test_project_pinhole_matches_opencv():
    cam = EUROC_CAM0.pinhole()
    pts = random_points(500, 30.0, seed=3)
    K, dist = cam.to_opencv()
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(cam.project(torch.from_numpy(pts)).numpy() - ref[:, 0]).max() < 1e-9


@pytest.mark.parametrize("cam", [EUROC_CAM0, RADTAN5], ids=["euroc", "radtan5"])
def test_unproject_radtan_matches_opencv(cam):
    uv = image_points(cam, step=16)
    K, dist = cam.to_opencv()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    ref = cv2.undistortPoints(uv.numpy()[:, None, :], K, dist, criteria=criteria)[:, 0]
    rays = cam.unproject(uv).numpy()
    np.testing.assert_array_equal(rays[:, 2], 1.0)
    # compared in pixels of the undistorted (pinhole) image
    err_px = np.abs(rays[:, :2] - ref) * max(cam.fx, cam.fy)
    assert err_px.max() < 1e-6


@pytest.mark.parametrize("cam", [TUMVI_CAM0, EQUI_STRONG], ids=["tumvi", "equi_strong"])
def test_unproject_equidistant_matches_opencv_fisheye(cam):
    # pixels inside the 80-degree cone (beyond it z = 1 rays become very long)
    uv = cam.project(torch.from_numpy(random_points(1000, 80.0, seed=4)))
    K, dist = cam.to_opencv()
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    ref = cv2.fisheye.undistortPoints(uv.numpy()[:, None, :], K, dist, criteria=criteria)[:, 0]
    rays = cam.unproject(uv).numpy()
    # relative to the ray length: the normalized radius reaches tan(80 deg) = 5.7
    rel = np.linalg.norm(rays[:, :2] - ref, axis=-1) / np.linalg.norm(rays, axis=-1)
    assert rel.max() < 1e-9


# ---------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("cam", CAMERAS, ids=CAMERA_IDS)
def test_project_unproject_round_trip_over_whole_image(cam):
    uv = image_points(cam)
    if cam.distortion == "equidistant":
        # a fisheye image also holds rays at >= 90 degrees, which z = 1 rays cannot represent
        uv = uv[torch.linalg.norm(cam.unproject(uv)[:, :2], dim=-1) < np.tan(np.deg2rad(85.0))]
    back = cam.project(cam.unproject(uv))
    assert (back - uv).abs().max() < 1e-6


@pytest.mark.parametrize("cam", CAMERAS, ids=CAMERA_IDS)
def test_unproject_inverts_project(cam):
    pts = torch.from_numpy(random_points(1000, fov_deg(cam), seed=5))
    rays = cam.unproject(cam.project(pts))
    assert (rays - pts / pts[:, 2:]).abs().max() < 1e-9
    depth = pts[:, 2]
    assert (cam.backproject(cam.project(pts), depth) - pts).abs().max() < 1e-8


@pytest.mark.parametrize("cam", CAMERAS, ids=CAMERA_IDS)
def test_float32_round_trip_and_dtype(cam):
    pts = torch.from_numpy(random_points(500, fov_deg(cam), seed=6)).float()
    uv = cam.project(pts)
    assert uv.dtype == torch.float32
    rays = cam.unproject(uv)
    assert rays.dtype == torch.float32
    assert (cam.project(rays) - uv).abs().max() < 2e-3
    assert cam.K(torch.float32).dtype == torch.float32


def test_batched_shapes():
    pts = torch.from_numpy(random_points(24, 30.0, seed=7)).reshape(2, 3, 4, 3)
    uv, depth = EUROC_CAM0.project_with_depth(pts)
    assert uv.shape == (2, 3, 4, 2) and depth.shape == (2, 3, 4)
    assert torch.equal(depth, pts[..., 2])
    assert EUROC_CAM0.unproject(uv).shape == (2, 3, 4, 3)
    empty = torch.zeros(0, 3, dtype=torch.float64)
    assert EUROC_CAM0.project(empty).shape == (0, 2)
    assert EUROC_CAM0.unproject(empty[:, :2]).shape == (0, 3)


def test_points_behind_camera_are_finite_and_masked():
    pts = torch.tensor([[0.1, 0.2, -1.0], [0.3, -0.1, 0.0], [0.0, 0.0, 2.0]], dtype=torch.float64)
    for cam in CAMERAS:
        uv, depth = cam.project_with_depth(pts)
        assert torch.isfinite(uv).all()
        assert (depth > MIN_DEPTH).tolist() == [False, False, True]
        assert not cam.in_image(uv[:2]).any()


def test_pinhole_and_optical_axis():
    cam = EQUI_STRONG
    centre = cam.project(torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    assert torch.allclose(centre, torch.tensor([cam.cx, cam.cy], dtype=torch.float64), atol=1e-12)
    pin = cam.pinhole()
    assert (pin.fx, pin.fy, pin.cx, pin.cy, pin.width, pin.height) == (
        cam.fx,
        cam.fy,
        cam.cx,
        cam.cy,
        cam.width,
        cam.height,
    )
    assert pin.distortion == "none" and pin.coeffs == ()
    pts = torch.from_numpy(random_points(100, 40.0, seed=8))
    expected = pts[:, :2] / pts[:, 2:] * torch.tensor([cam.fx, cam.fy], dtype=torch.float64) + torch.tensor(
        [cam.cx, cam.cy], dtype=torch.float64
    )
    assert (pin.project(pts) - expected).abs().max() < 1e-9
    K = cam.K()
    assert K.shape == (3, 3) and K.dtype == torch.float64
    assert torch.allclose((K @ (pts / pts[:, 2:]).T).T[:, :2], expected, atol=1e-9)


# ---------------------------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("cam", CAMERAS, ids=CAMERA_IDS)
def test_project_gradcheck_including_optical_axis(cam):
    pts = torch.from_numpy(random_points(6, fov_deg(cam), seed=9))
    pts = torch.cat((pts, torch.tensor([[0.0, 0.0, 1.5], [1e-9, -2e-9, 2.0]], dtype=torch.float64)))
    pts.requires_grad_(True)
    assert torch.autograd.gradcheck(cam.project, (pts,), eps=1e-7, atol=1e-5)


@pytest.mark.parametrize("cam", CAMERAS, ids=CAMERA_IDS)
def test_unproject_gradient_is_inverse_of_projection_jacobian(cam):
    pts = torch.from_numpy(random_points(5, 0.8 * fov_deg(cam), seed=10))
    rays = pts / pts[:, 2:]
    uv = cam.project(rays).detach()

    def project_normalized(xy: torch.Tensor) -> torch.Tensor:
        return cam.project(torch.cat((xy, xy.new_ones(1))))

    for i in range(len(uv)):
        j_unproject = torch.autograd.functional.jacobian(lambda q: cam.unproject(q)[:2], uv[i])
        j_project = torch.autograd.functional.jacobian(project_normalized, rays[i, :2])
        assert torch.allclose(j_unproject @ j_project, torch.eye(2, dtype=torch.float64), atol=1e-8)


def test_radtan_jacobian_matches_autograd():
    xy = torch.tensor([[0.3, -0.2], [-0.5, 0.4], [0.0, 0.0]], dtype=torch.float64)
    for cam in (EUROC_CAM0, RADTAN5):
        for p in xy:
            auto = torch.autograd.functional.jacobian(lambda q: radtan_distort(q, cam.coeffs), p)
            assert torch.allclose(radtan_jacobian(p, cam.coeffs), auto, atol=1e-12)


def test_equidistant_series_branch_is_continuous():
    coeffs = EQUI_STRONG.coeffs
    for dtype in (torch.float32, torch.float64):
        thr = torch.finfo(dtype).eps ** 0.5
        r = torch.tensor([0.999, 1.001], dtype=torch.float64) * thr**0.5
        xy = torch.stack((r, torch.zeros_like(r)), -1).to(dtype)
        d = equidistant_distort(xy, coeffs)[:, 0].double() / r
        theta = torch.atan(r)
        exact = theta * (1 + coeffs[0] * theta**2 + coeffs[1] * theta**4) / r
        assert torch.allclose(d, exact, rtol=4 * torch.finfo(dtype).eps, atol=0)
        back = equidistant_undistort(equidistant_distort(xy, coeffs), coeffs)
        assert torch.allclose(back, xy, rtol=8 * torch.finfo(dtype).eps, atol=0)


# ---------------------------------------------------------------------------------------------- resizing
@pytest.mark.parametrize("factor", [0.5, 0.25, 0.125, 2.0])
def test_scaled_point_projects_to_scaled_location(factor):
    pts = torch.from_numpy(random_points(200, 40.0, seed=11))
    for cam in (EUROC_CAM0, TUMVI_CAM0):
        small = cam.scaled(factor)
        assert (small.width, small.height) == (cam.width * factor, cam.height * factor)
        expected = (cam.project(pts) + 0.5) * factor - 0.5
        assert (small.project(pts) - expected).abs().max() < 1e-9
        assert small.coeffs == cam.coeffs and small.distortion == cam.distortion
        assert small.cx == pytest.approx((cam.cx + 0.5) * factor - 0.5)


def test_resized_uses_actual_size_ratio():
    cam = EUROC_CAM0.scaled(1.0 / 3.0)  # 752 / 3 = 250.67 -> 251 columns, 480 / 3 = 160 rows
    assert (cam.width, cam.height) == (251, 160)
    assert cam.fx == pytest.approx(EUROC_CAM0.fx * 251 / 752)
    assert cam.fy == pytest.approx(EUROC_CAM0.fy / 3.0)


def test_pyramid_consistency():
    levels = EUROC_CAM0.pyramid(4)
    assert [(c.width, c.height) for c in levels] == [(752, 480), (376, 240), (188, 120), (94, 60)]
    assert levels[0] == EUROC_CAM0
    pts = torch.from_numpy(random_points(100, 40.0, seed=12))
    for k, cam in enumerate(levels):
        direct = EUROC_CAM0.scaled(0.5**k)
        for a, b in ((cam.fx, direct.fx), (cam.fy, direct.fy), (cam.cx, direct.cx), (cam.cy, direct.cy)):
            assert a == pytest.approx(b, abs=1e-12)
        assert torch.allclose(cam.project(pts), (levels[0].project(pts) + 0.5) * 0.5**k - 0.5, atol=1e-9)


def test_half_pixel_convention_matches_cv2_resize():
    """A blob centred at (u, v) lands at ((u + 0.5) s - 0.5, (v + 0.5) s - 0.5) after cv2.resize."""
    cam = EUROC_CAM0.pinhole()
    u0, v0 = 301.3, 187.8
    vv, uu = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    image = np.exp(-((uu - u0) ** 2 + (vv - v0) ** 2) / (2 * 6.0**2))
    for factor in (0.5, 0.25):
        small_cam = cam.scaled(factor)
        small = cv2.resize(image, (small_cam.width, small_cam.height), interpolation=cv2.INTER_AREA)
        sv, su = np.mgrid[0 : small.shape[0], 0 : small.shape[1]]
        centroid = np.array([(small * su).sum(), (small * sv).sum()]) / small.sum()
        ray = cam.unproject(torch.tensor([u0, v0], dtype=torch.float64))
        assert np.abs(small_cam.project(ray).numpy() - centroid).max() < 1e-3


def test_pixel_grid():
    grid = EUROC_CAM0.pixel_grid()
    assert grid.shape == (480, 752, 2) and grid.dtype == torch.float32
    assert grid[0, 0].tolist() == [0.0, 0.0] and grid[479, 751].tolist() == [751.0, 479.0]
    assert grid[10, 20].tolist() == [20.0, 10.0]
    coarse = EUROC_CAM0.pixel_grid(stride=8, dtype=torch.float64)
    assert coarse.shape == (60, 94, 2)
    # its points are the pixel centres of the 1/8 camera: they project to integer pixels there
    small = EUROC_CAM0.scaled(1 / 8)
    ray = EUROC_CAM0.unproject(coarse)
    expected = small.pixel_grid(dtype=torch.float64)
    assert (small.project(ray) - expected).abs().max() < 1e-6
    assert coarse[0, 0].tolist() == [3.5, 3.5]


def test_to_opencv():
    K, dist = EUROC_CAM0.to_opencv()
    assert K.shape == (3, 3) and K.dtype == np.float64
    np.testing.assert_array_equal(K, [[458.654, 0, 367.215], [0, 457.296, 248.375], [0, 0, 1]])
    np.testing.assert_array_equal(dist, EUROC_CAM0.coeffs)
    assert RADTAN5.to_opencv()[1].shape == (5,)
    assert TUMVI_CAM0.to_opencv()[1].shape == (4,)
    np.testing.assert_array_equal(EUROC_CAM0.pinhole().to_opencv()[1], np.zeros(5))


# ---------------------------------------------------------------------------------------------- validation
def test_coefficients_are_normalized_and_model_is_hashable():
    cam = CameraModel(np.int64(640), 480, np.float32(500), 500, 320, 240, "radtan", np.array([0.1, 0.01, 0, 0]))
    assert cam.coeffs == (pytest.approx(0.1), 0.01, 0.0, 0.0) and isinstance(cam.coeffs, tuple)
    assert isinstance(cam.width, int) and isinstance(cam.fx, float)
    assert cam == CameraModel(640, 480, 500.0, 500.0, 320.0, 240.0, "radtan", [np.float64(0.1), 0.01, 0.0, 0.0])
    assert len({cam, cam.pinhole(), cam.pinhole()}) == 2
    with pytest.raises(AttributeError):
        cam.fx = 1.0  # frozen


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        (dict(width=0), ValueError, "width must be a positive integer"),
        (dict(height=-5), ValueError, "height must be a positive integer"),
        (dict(width=640.5), TypeError, "width must be a positive integer"),
        (dict(width=True), TypeError, "width"),
        (dict(fx=0.0), ValueError, "fx must be a finite number > 0"),
        (dict(fy=-1.0), ValueError, "fy must be a finite number > 0"),
        (dict(cx=float("nan")), ValueError, "cx must be a finite number"),
        (dict(cy="abc"), TypeError, "cy must be a real number"),
        (dict(distortion="fisheye"), ValueError, "distortion must be one of"),
        (dict(distortion=["radtan"]), ValueError, "distortion must be one of"),
        (dict(distortion="radtan", coeffs=(0.1, 0.2, 0.3)), ValueError, "needs 4 or 5 coefficients, got 3"),
        (dict(distortion="equidistant", coeffs=(0.1,) * 5), ValueError, "needs 4 coefficients, got 5"),
        (dict(distortion="none", coeffs=(0.1,)), ValueError, "needs 0 coefficients, got 1"),
        (dict(distortion="radtan", coeffs="0.1 0.2"), TypeError, "coeffs must be a sequence"),
        (dict(distortion="radtan", coeffs=(0.1, None, 0, 0)), TypeError, r"coeffs\[1\] must be a real number"),
        (dict(distortion="radtan", coeffs=(0.1, float("inf"), 0, 0)), ValueError, r"coeffs\[1\] must be a finite"),
    ],
)
def test_invalid_construction_raises_clear_errors(kwargs, error, message):
    args = dict(width=640, height=480, fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    args.update(kwargs)
    with pytest.raises(error, match=message):
        CameraModel(**args)


def test_invalid_method_arguments_raise_clear_errors():
    cam = EUROC_CAM0
    with pytest.raises(ValueError, match=r"points of shape \(\.\.\., 3\), got \(5, 2\)"):
        cam.project(torch.zeros(5, 2))
    with pytest.raises(ValueError, match=r"pixels of shape \(\.\.\., 2\), got \(5, 3\)"):
        cam.unproject(torch.zeros(5, 3))
    with pytest.raises(ValueError, match="factor"):
        cam.scaled(0.0)
    with pytest.raises(ValueError, match="factor"):
        cam.scaled(float("inf"))
    with pytest.raises(ValueError, match="levels"):
        cam.pyramid(0)
    with pytest.raises(ValueError, match="stride"):
        cam.pixel_grid(stride=0)
    with pytest.raises(ValueError, match="width"):
        cam.resized(0, 10)


def test_accelerator_device_matches_cpu():
    """Runs on CUDA where available (on CPU-only machines it checks the explicit-device path)."""
    device = "cuda" if torch.cuda.is_available() else "cpu"
    pts = torch.from_numpy(random_points(300, 40.0, seed=13))
    for cam in CAMERAS:
        for dtype, tol in ((torch.float64, 1e-9), (torch.float32, 2e-3)):
            uv = cam.project(pts.to(device, dtype))
            assert uv.device.type == device and uv.dtype == dtype
            assert (uv.cpu().double() - cam.project(pts)).abs().max() < tol
            rays = cam.unproject(uv)
            assert rays.device.type == device
            assert (cam.project(rays) - uv).abs().max() < tol
        grid = cam.pixel_grid(stride=4, device=device)
        assert grid.device.type == device
        assert cam.K(device=device).device.type == device
