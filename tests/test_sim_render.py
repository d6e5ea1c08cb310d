"""Scene, ray caster and textures: depth is exact through the distorted camera model, images are
deterministic, textured at coarse resolution and anti-aliased."""
import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel
from vigs_core.sim.hybrid import euroc_cam0_calibration
from vigs_core.sim.render import RenderConfig, Renderer
from vigs_core.sim.scene import SceneConfig, build_room_scene

torch.set_num_threads(1)

CAL = euroc_cam0_calibration()


def _look(position, yaw):
    """Camera pose looking horizontally along yaw (rad), z up."""
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    right = np.cross(down, forward)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, forward], axis=1)
    T[:3, 3] = position
    return T


@pytest.fixture(scope="module")
def scene():
    path = np.stack([np.linspace(-1.0, 1.0, 20), np.linspace(0.0, 0.5, 20), np.full(20, 1.2)], axis=1)
    return build_room_scene(path, seed=4, config=SceneConfig(n_objects=10))


def _box_surface_distance(scene, points):
    """(N,) distance of world points (N, 3) to the nearest box surface."""
    c, h, R = scene.centers.numpy(), scene.half_sizes.numpy(), scene.rotations.numpy()
    dists = []
    for b in range(len(c)):
        local = (points - c[b]) @ R[b]
        outside = np.linalg.norm(np.maximum(np.abs(local) - h[b], 0.0), axis=1)
        inside = np.min(h[b] - np.abs(local), axis=1)
        dists.append(np.where(outside > 0, outside, np.abs(inside)))
    return np.min(dists, axis=0)


@pytest.mark.parametrize(
    "camera",
    [
        CAL.camera.scaled(0.25),
        CameraModel(160, 120, 110.0, 110.0, 79.5, 59.5, "equidistant", (0.01, -0.02, 0.005, -0.001)),
    ],
)
def test_rendered_depth_matches_projection_of_scene_points(scene, camera):
    renderer = Renderer(scene, camera)
    T_WC = _look(np.array([0.2, 0.1, 1.3]), 0.7)
    depth = renderer.render(T_WC).depth
    assert depth.shape == (camera.height, camera.width) and np.all(np.isfinite(depth)) and depth.min() > 0
    # 1) every pixel-centre depth back-projects (through the lens model) onto a scene surface
    uv = camera.pixel_grid(dtype=torch.float64).reshape(-1, 2)
    pts_c = camera.backproject(uv, torch.from_numpy(depth.reshape(-1).astype(np.float64))).numpy()
    pts_w = pts_c @ T_WC[:3, :3].T + T_WC[:3, 3]
    assert np.percentile(_box_surface_distance(scene, pts_w), 99.9) < 2e-5 * depth.max() + 1e-5
    # 2) scene points projected with CameraModel.project have the rendered depth at their pixel unless occluded
    rng = np.random.default_rng(0)
    c, h, R = scene.centers.numpy(), scene.half_sizes.numpy(), scene.rotations.numpy()
    b = rng.integers(0, len(c), 4000)
    local = rng.uniform(-1, 1, (4000, 3)) * h[b]
    axis = rng.integers(0, 3, 4000)
    local[np.arange(4000), axis] = np.sign(rng.uniform(-1, 1, 4000)) * h[b, axis]  # onto a face
    world = c[b] + np.einsum("nij,nj->ni", R[b], local)
    cam = (world - T_WC[:3, 3]) @ T_WC[:3, :3]
    front = cam[:, 2] > 0.1
    uv_p, z = camera.project_with_depth(torch.from_numpy(cam[front]))
    inside = camera.in_image(uv_p).numpy()
    rays = camera.unproject(uv_p[inside]).to(torch.float32)
    _, t = renderer.trace(T_WC, rays, torch.zeros(len(rays)))
    z_in = z[inside].numpy()
    err = t.numpy() - z_in
    visible = np.abs(err) < 1e-4 * z_in + 1e-5
    assert visible.sum() > 100, "too few scene points visible for the test to mean anything"
    assert np.all(err[~visible] < 0), "a rendered depth lies behind a scene point that projects there"


def test_render_is_deterministic_and_seed_dependent(scene):
    camera = CAL.camera.scaled(0.25)
    T = _look(np.array([0.0, 0.0, 1.2]), 2.0)
    a = Renderer(scene, camera).render(T)
    point = np.array([[0.0, 0.0, 1.2]])
    b = Renderer(build_room_scene(point, seed=4), camera).render(T)
    assert b.image.tobytes() == Renderer(build_room_scene(point, seed=4), camera).render(T).image.tobytes()
    again = Renderer(scene, camera).render(T)
    assert a.image.tobytes() == again.image.tobytes() and a.depth.tobytes() == again.depth.tobytes()
    other = Renderer(build_room_scene(point, seed=5), camera).render(T)
    assert np.abs(other.image - b.image).mean() > 0.05  # another seed is another scene


def test_textures_are_corner_rich_at_one_eighth_resolution_and_antialiased(scene):
    import cv2

    camera = CAL.camera.scaled(0.5)  # 376 x 240
    T = _look(np.array([-0.5, 0.3, 1.2]), -0.4)
    image = Renderer(scene, camera).render(T).image
    assert 0.0 <= image.min() and image.max() <= 1.0
    small = cv2.resize(image, (camera.width // 8, camera.height // 8), interpolation=cv2.INTER_AREA)
    assert small.std() > 0.08
    corners = cv2.goodFeaturesToTrack(small, maxCorners=500, qualityLevel=0.05, minDistance=2)
    assert corners is not None and len(corners) >= 15
    # the analytic prefilter leaves little for supersampling to remove: 3x3 supersampling changes the
    # image little on average, and far less than the texture's own contrast
    ss = Renderer(scene, camera, RenderConfig(supersample=3)).render(T).image
    assert np.abs(ss - image).mean() < 0.25 * image.std()


def test_objects_keep_clear_of_the_trajectory():
    path = np.stack([np.linspace(-2, 2, 50), np.sin(np.linspace(0, 3, 50)), np.full(50, 1.0)], axis=1)
    config = SceneConfig(n_objects=20, clearance=0.6)
    scene = build_room_scene(path, seed=9, config=config)
    assert scene.num_boxes > 10
    c, h, R = scene.centers.numpy(), scene.half_sizes.numpy(), scene.rotations.numpy()
    for b in range(1, len(c)):
        local = (path - c[b]) @ R[b]
        assert np.linalg.norm(np.maximum(np.abs(local) - h[b], 0.0), axis=1).min() >= 0.6
    lo, hi = c[0] - h[0], c[0] + h[0]
    assert np.all(path > lo) and np.all(path < hi)  # the room encloses the path


def test_photo_textures_cover_surfaces_and_are_mip_mapped():
    from vigs_core.sim.texture import SurfaceTextures

    checker = (np.indices((64, 96)).sum(axis=0) % 2).astype(np.float32)  # 1-texel checkerboard, mean 0.5
    tex = SurfaceTextures(seed=1, num_surfaces=200, photos=[checker], photo_fraction=0.5, photo_size_m=1.0)
    covered = tex.photo_index >= 0
    assert 70 < int(covered.sum()) < 130
    plain = SurfaceTextures(seed=1, num_surfaces=200)
    rng = np.random.default_rng(0)
    uv = torch.from_numpy(rng.uniform(-3, 3, (5000, 2)).astype(np.float32))
    surface = torch.from_numpy(rng.integers(0, 200, 5000))
    on = covered[surface]
    texel = 1.0 / 96
    fine = torch.full((5000,), 0.2 * texel)
    a, b = tex.evaluate(uv, surface, fine), plain.evaluate(uv, surface, fine)
    np.testing.assert_array_equal(a[~on].numpy(), b[~on].numpy())  # other surfaces keep their pattern
    assert (a[on] - b[on]).abs().mean() > 0.1  # the photo shows at texel scale
    # seen from far (footprint of 16 texels) the checkerboard is filtered to its mean, not aliased
    far = torch.full((5000,), 16 * texel)
    photo_part = (tex.evaluate(uv, surface, far)[on] - 0.25 * plain.evaluate(uv, surface, far)[on]) / 0.75
    assert (photo_part - 0.5).abs().max() < 0.02
