"""Reference rasterizer: gradients against finite differences, geometry of a single Gaussian, occlusion,
and invariance to the tiling and chunking choices."""
from __future__ import annotations

import math

import pytest
import torch

from vigs_core.geometry import se3_from_rt, se3_inverse, so3_exp
from vigs_core.mapping import rasterizer as rasterizer_module
from vigs_core.mapping.rasterizer import (
    RenderCamera,
    RenderOutput,
    RenderSettings,
    TorchRasterizer,
    bin_gaussians,
    ellipse_meets_tile,
    frustum_rows,
    make_rasterizer,
    project_gaussians,
)

torch.set_num_threads(1)


def _random_scene(n: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * 0.25 + torch.tensor([0.0, 0.0, 2.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.15 + 0.08
    opac = torch.rand(n, generator=g, dtype=dtype) * 0.7 + 0.2
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    return means, quats, scales, opac, colors


def _camera_pose(dtype: torch.dtype) -> torch.Tensor:
    """A non-trivial T_CW (small rotation and offset)."""
    R = so3_exp(torch.tensor([0.05, -0.08, 0.03], dtype=torch.float64))
    return se3_from_rt(R, torch.tensor([0.05, -0.02, 0.1], dtype=torch.float64)).to(dtype)


def test_gradients_match_finite_differences():
    dtype = torch.float64
    cam = RenderCamera(13, 11, 10.0, 11.0, 6.3, 4.7)
    raster = TorchRasterizer(RenderSettings(tile_size=4, max_per_tile=16))
    inputs = tuple(t.requires_grad_() for t in _random_scene(6, dtype))
    T_CW = _camera_pose(dtype)

    def render(*args):
        out = raster(*args, T_CW, cam)
        return out.color, out.depth, out.alpha

    with torch.no_grad():
        out = raster(*inputs, T_CW, cam)
    assert float(out.alpha.max()) > 0.5, "the test scene must cover the image"
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_single_gaussian_peaks_at_its_projection_with_its_depth():
    dtype = torch.float64
    cam = RenderCamera(40, 30, 35.0, 33.0, 19.0, 14.0)
    T_CW = _camera_pose(dtype)
    # choose the camera-frame point so the mean projects exactly onto pixel centre (u, v) = (23, 11)
    z = 2.5
    p_cam = torch.tensor([(23 - cam.cx) / cam.fx * z, (11 - cam.cy) / cam.fy * z, z], dtype=dtype)
    mean = (se3_inverse(T_CW)[:3, :3] @ p_cam + se3_inverse(T_CW)[:3, 3])[None]
    quats = torch.tensor([[0.9, 0.1, -0.3, 0.2]], dtype=dtype)
    scales = torch.tensor([[0.05, 0.03, 0.04]], dtype=dtype)
    out = TorchRasterizer(RenderSettings(tile_size=8))(
        mean, quats, scales, torch.tensor([0.8], dtype=dtype), torch.tensor([[0.2, 0.5, 0.9]], dtype=dtype), T_CW, cam
    )
    mean2d, _, z_proj = project_gaussians(mean, quats, scales, T_CW, cam, 0.3)
    assert torch.allclose(mean2d[0], torch.tensor([23.0, 11.0], dtype=dtype), atol=1e-9)
    assert math.isclose(float(z_proj[0]), z, rel_tol=1e-12)
    peak = int(out.alpha.argmax())
    assert (peak // cam.width, peak % cam.width) == (11, 23)
    assert math.isclose(float(out.alpha.max()), 0.8, rel_tol=1e-9)
    covered = out.alpha > 0
    assert int(covered.sum()) > 9
    assert torch.allclose(out.depth[covered] / out.alpha[covered], torch.full_like(out.depth[covered], z))
    assert torch.allclose(out.color[11, 23], 0.8 * torch.tensor([0.2, 0.5, 0.9], dtype=dtype))
    assert out.visible.tolist() == [0]


@pytest.mark.parametrize("compiled", [False, True])
def test_front_gaussian_occludes_back_gaussian(compiled):
    dtype = torch.float32
    cam = RenderCamera(24, 24, 30.0, 30.0, 12.0, 12.0)
    means = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.0, 1.5]])  # back first: order must come from depth
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
    scales = torch.tensor([[0.3, 0.3, 0.3], [0.3, 0.3, 0.3]])
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = TorchRasterizer(compiled=compiled)(means, quats, scales, torch.tensor([0.99, 0.99]), colors,
                                             torch.eye(4, dtype=dtype), cam)
    # at the centre pixel both Gaussians have alpha 0.99; the front one (blue, z = 1.5) comes first
    w_front, w_back = 0.99, 0.01 * 0.99
    assert torch.allclose(out.color[12, 12], torch.tensor([w_back, 0.0, w_front]), atol=1e-6)
    assert math.isclose(float(out.depth[12, 12]), w_front * 1.5 + w_back * 3.0, rel_tol=1e-6)
    assert math.isclose(float(out.alpha[12, 12]), 1 - 0.01 * 0.01, rel_tol=1e-6)


def test_tiling_and_chunking_do_not_change_the_image():
    dtype = torch.float64
    cam = RenderCamera(37, 29, 30.0, 30.0, 18.2, 13.9)
    scene = _random_scene(40, dtype, seed=3)
    T_CW = _camera_pose(dtype)
    ref = TorchRasterizer(RenderSettings(tile_size=16, max_per_tile=1000))(*scene, T_CW, cam)
    for settings in (RenderSettings(tile_size=4, max_per_tile=1000), RenderSettings(tile_size=8, chunk_pairs=300)):
        out = TorchRasterizer(settings)(*scene, T_CW, cam)
        assert torch.allclose(out.color, ref.color, atol=1e-12)
        assert torch.allclose(out.depth, ref.depth, atol=1e-12)
        assert torch.allclose(out.alpha, ref.alpha, atol=1e-12)
    assert float(ref.alpha.mean()) > 0.3


@pytest.mark.parametrize("compiled", [False, True])
def test_gaussians_behind_or_outside_the_camera_are_not_drawn(compiled):
    cam = RenderCamera(20, 20, 20.0, 20.0, 9.5, 9.5)
    means = torch.tensor([[0.0, 0.0, -2.0], [50.0, 0.0, 2.0]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
    out = TorchRasterizer(compiled=compiled)(
        means, quats, torch.full((2, 3), 0.1), torch.tensor([0.9, 0.9]), torch.ones(2, 3), torch.eye(4), cam
    )
    assert float(out.alpha.abs().max()) == 0.0
    assert out.visible.numel() == 0


def test_ellipse_tile_test_matches_dense_sampling():
    g = torch.Generator().manual_seed(5)
    n = 4000
    mean = torch.rand(n, 2, generator=g, dtype=torch.float64) * 30.0 - 5.0
    L = torch.randn(n, 2, 2, generator=g, dtype=torch.float64) * 2.0
    cov = L @ L.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    Q = torch.linalg.inv(cov)
    reach = torch.rand(n, generator=g, dtype=torch.float64) * 10.0 + 0.5
    ellipse = torch.cat((mean, Q[:, 0, 0:1], Q[:, 0, 1:2], Q[:, 1, 1:2], reach[:, None]), -1)
    lo = torch.tensor([8.0, 8.0], dtype=torch.float64).expand(n, 2)
    hi = torch.tensor([15.0, 13.0], dtype=torch.float64).expand(n, 2)
    got = ellipse_meets_tile(ellipse, lo, hi)
    # dense sampling of the rectangle (boundary included): the sampled minimum is >= the exact one
    xs = torch.linspace(8, 15, 141, dtype=torch.float64)
    ys = torch.linspace(8, 13, 101, dtype=torch.float64)
    x, y = torch.meshgrid(xs, ys, indexing="ij")
    d = torch.stack((x.reshape(-1), y.reshape(-1)), -1)[None] - mean[:, None]  # (n, S, 2)
    f = torch.einsum("nsi,nij,nsj->ns", d, Q, d).amin(1)
    assert torch.all(got[f <= reach])  # no tile that the ellipse meets is dropped
    clear = f > reach * 1.02 + 0.05  # safely outside (the sampling step cannot hide a hit)
    assert not torch.any(got[clear])
    assert int(got.sum()) > n // 10 and int(clear.sum()) > n // 10  # both cases occur


def test_frustum_and_tile_culling_do_not_change_the_image(monkeypatch):
    dtype = torch.float64
    cam = RenderCamera(37, 29, 30.0, 30.0, 18.2, 13.9)
    T_CW = _camera_pose(dtype)
    means, quats, scales, opac, colors = _random_scene(300, dtype, seed=4)
    # spread sideways (many outside the image, some near its borders), smaller so that many are culled
    means, scales = means * torch.tensor([8.0, 8.0, 1.0], dtype=dtype), scales * 0.3
    settings = RenderSettings(tile_size=8, max_per_tile=1000)
    rows = frustum_rows(means, scales, T_CW, cam, settings)
    assert 0 < rows.numel() < 0.6 * means.shape[0]
    for d in (torch.float64, torch.float32):   # the compiled pass keeps the same rows
        assert torch.equal(frustum_rows(means.to(d), scales.to(d), T_CW.to(d), cam, settings, compiled=True), rows)
    scene = (means, quats, scales, opac, colors)
    for compiled in (False, True):   # the culled rows alone (no gather): the same image, the same gradients
        full, full_grads = _render_and_grads(TorchRasterizer(settings, compiled=compiled), scene, T_CW, cam)
        part, part_grads = _render_and_grads(TorchRasterizer(settings, compiled=compiled),
                                             tuple(t[rows] for t in scene), T_CW, cam)
        assert torch.equal(full.alpha, part.alpha) and torch.equal(full.color, part.color)
        assert rows[part.visible].tolist() == full.visible.tolist()
        for g_full, g_part in zip(full_grads, part_grads):
            assert torch.equal(g_full[rows], g_part) and not bool(g_full.index_fill(0, rows, 0.0).any())
    raster = TorchRasterizer(settings)
    # the same image from bounding-box binning alone: the exact tile test only drops pairs with alpha = 0
    pairs = {}
    exact_binning = rasterizer_module.bin_gaussians

    def bbox_binning(mean2d, half, depth, camera, s, conic, reach):
        pairs["exact"] = int(exact_binning(mean2d, half, depth, camera, s, conic, reach).counts.sum())
        bins = exact_binning(mean2d, half, depth, camera, s)
        pairs["bbox"] = int(bins.counts.sum())
        return bins

    monkeypatch.setattr(rasterizer_module, "bin_gaussians", bbox_binning)
    boxed = raster(means, quats, scales, opac, colors, T_CW, cam)
    assert torch.allclose(boxed.color, full.color, atol=1e-12)
    assert torch.allclose(boxed.alpha, full.alpha, atol=1e-12)
    assert pairs["exact"] < 0.9 * pairs["bbox"]


def _render_and_grads(raster, scene, T_CW, cam):
    """Image (detached) and the gradients of a loss that weighs colour, depth and opacity differently."""
    inputs = tuple(t.detach().clone().requires_grad_() for t in scene)
    out = raster(*inputs, T_CW, cam)
    weights = torch.linspace(0.5, 1.5, 3, dtype=out.color.dtype)
    loss = (out.color * weights).sum() + 0.3 * (out.depth**2).sum() + 0.7 * out.alpha.sum()
    grads = torch.autograd.grad(loss, inputs)
    return RenderOutput(out.color.detach(), out.depth.detach(), out.alpha.detach(), out.visible), grads


def test_compiled_compositing_matches_the_reference():
    """Where no pixel's transmittance reaches the early stop the compiled kernels composite the same slots as the
    reference (whose gradients are checked against finite differences above): equal images and gradients up to
    the kernels' float32 arithmetic."""
    dtype = torch.float64
    cam = RenderCamera(37, 29, 30.0, 30.0, 18.2, 13.9)
    means, quats, scales, opac, colors = _random_scene(40, dtype, seed=6)
    scene = (means, quats, scales, opac * 0.3, colors)
    T_CW = _camera_pose(dtype)
    settings = RenderSettings(tile_size=8, max_per_tile=24)  # some tiles cut at K: the same cut in both
    ref, ref_grads = _render_and_grads(TorchRasterizer(settings), scene, T_CW, cam)
    out, grads = _render_and_grads(TorchRasterizer(settings, compiled=True), scene, T_CW, cam)
    assert 0.3 < float(ref.alpha.max()) < 1.0 - 1e-3, "no early stop may happen in this scene"
    for a, b in ((out.color, ref.color), (out.depth, ref.depth), (out.alpha, ref.alpha)):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)
    assert out.visible.tolist() == ref.visible.tolist()
    for g, g_ref in zip(grads, ref_grads):
        assert torch.allclose(g, g_ref, rtol=1e-4, atol=1e-5 * float(g_ref.abs().max()))


def test_compiled_compositing_stops_early_within_its_bound():
    """Opaque scene: pixels stop compositing once ``T < T_STOP``; the image then differs from the reference by at
    most ``T_STOP`` times the largest feature (depth here), in float32 as the mapper renders."""
    from vigs_core.mapping.rasterizer_numba import T_STOP

    dtype = torch.float32
    cam = RenderCamera(40, 32, 30.0, 30.0, 19.5, 15.5)
    means, quats, scales, opac, colors = _random_scene(120, dtype, seed=7)
    scene = (means, quats, scales * 1.5, torch.full_like(opac, 0.98), colors)
    T_CW = _camera_pose(dtype)
    ref, ref_grads = _render_and_grads(TorchRasterizer(), scene, T_CW, cam)
    out, grads = _render_and_grads(TorchRasterizer(compiled=True), scene, T_CW, cam)
    assert float((1.0 - ref.alpha).min()) < 0.1 * T_STOP, "the scene must saturate some pixels"
    z_max = float(means[:, 2].max()) + 1.0
    assert float((out.depth - ref.depth).abs().max()) <= T_STOP * z_max
    assert float((out.color - ref.color).abs().max()) <= T_STOP * 1.01
    assert float((out.alpha - ref.alpha).abs().max()) <= T_STOP * 1.01
    for g, g_ref in zip(grads, ref_grads):
        assert float((g - g_ref).abs().max()) <= 2e-3 * float(g_ref.abs().max())


def test_backends_on_a_cpu_machine():
    assert make_rasterizer("numba").compiled and not make_rasterizer("torch").compiled
    if not torch.cuda.is_available():
        assert make_rasterizer("auto").compiled, "on CPU the default backend composites with the compiled kernels"


def test_compiled_binning_matches_the_reference():
    from vigs_core.mapping import rasterizer_numba

    dtype = torch.float64
    cam = RenderCamera(61, 45, 40.0, 40.0, 30.2, 21.9)
    means, quats, scales, opac, _ = _random_scene(300, dtype, seed=8)
    means = means * torch.tensor([3.0, 3.0, 1.0], dtype=dtype)  # some beyond the image and its borders
    mean2d, cov2d, z = project_gaussians(means, quats, scales * 0.5, _camera_pose(dtype), cam, 0.3)
    det = cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2
    conic = torch.stack((cov2d[:, 2], -cov2d[:, 1], cov2d[:, 0]), -1) / det[:, None]
    reach = 2.0 * torch.log(255.0 * opac)
    half = torch.sqrt(reach[:, None] * cov2d[:, [0, 2]])
    for max_per_tile in (5, 1000):  # overfull tiles cut to the front-most, and no cut
        settings = RenderSettings(tile_size=8, max_per_tile=max_per_tile)
        ref = bin_gaussians(mean2d, half, z, cam, settings, conic, reach)
        got = rasterizer_numba.bin_gaussians(mean2d, half, z, conic, reach, 8, 6, 8, cam.width, cam.height,
                                             max_per_tile)
        assert ref.tiles.numel() > 10
        for a, b in ((got.tiles, ref.tiles), (got.counts, ref.counts), (got.binned, ref.binned)):
            assert torch.equal(a, b)
        assert got.index.numel() == int(ref.counts.sum())   # flat: the pairs, no padding
        for i, (start, count) in enumerate(zip(got.starts.tolist(), got.counts.tolist())):
            assert torch.equal(got.index[start : start + count], ref.index[i, :count])
    assert 0 < int(ref.binned.sum()) < ref.binned.numel()
    assert int(ref.counts.max()) > 5, "the first pass must cut overfull tiles"


def test_depth_order_is_a_stable_argsort():
    from vigs_core.mapping.rasterizer_numba import depth_order

    g = torch.Generator().manual_seed(5)
    depth = torch.randn(3000, generator=g).mul_(4.0).round_().div_(8.0)   # many ties, negatives and zeros
    depth = torch.cat((depth, torch.tensor([float("inf"), float("-inf"), 1e-30, -1e-30])))
    values = depth.numpy().astype("float32")
    assert torch.equal(torch.from_numpy(depth_order(values)), torch.sort(torch.from_numpy(values), stable=True)[1])


def test_compiled_projection_matches_the_reference_and_finite_differences():
    from vigs_core.mapping.rasterizer_numba import ProjectGaussians

    dtype = torch.float64
    cam = RenderCamera(37, 29, 30.0, 30.0, 18.2, 13.9)
    means, quats, scales, _, _ = _random_scene(200, dtype, seed=3)
    means = means * torch.tensor([6.0, 6.0, 1.0], dtype=dtype)  # rays beyond the clamp too
    T_CW = _camera_pose(dtype)
    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, scales))

    def reference(m, q, s):
        mean2d, cov2d, z = project_gaussians(m, q / q.norm(dim=-1, keepdim=True), s, T_CW, cam, 0.3)
        det = cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2
        return mean2d, torch.stack((cov2d[:, 2], -cov2d[:, 1], cov2d[:, 0]), -1) / det[:, None], z, cov2d

    ref, got = reference(*inputs), ProjectGaussians.apply(*inputs, T_CW, cam, 0.3)
    for a, b in zip(got, ref):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)
    tx = (ref[0][:, 0].detach() - cam.cx) / cam.fx
    assert bool((rasterizer_module._clamped_rays(tx, tx, cam)[0] != tx).any()), "some rays must be clamped"
    weights = [torch.randn_like(t) for t in ref[:3]]
    g_ref = torch.autograd.grad(sum((t * w).sum() for t, w in zip(ref[:3], weights)), inputs)
    g_got = torch.autograd.grad(sum((t * w).sum() for t, w in zip(got[:3], weights)), inputs)
    for a, b in zip(g_got, g_ref):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-10)
    small = tuple(t[:12].detach().clone().requires_grad_() for t in inputs)
    assert torch.autograd.gradcheck(lambda m, q, s: ProjectGaussians.apply(m, q, s, T_CW, cam, 0.3)[:3], small,
                                    eps=1e-6, atol=1e-6, rtol=1e-5)


def test_default_settings_composite_a_crowded_tile_whole():
    """300 faint Gaussians stacked in front of one tile: the default cap composites all of them (accumulated
    opacity ``1 - 0.98^300``), as gsplat would, in the reference and the compiled kernels; a cap of 96 (the old
    default) leaves the tile at ``1 - 0.98^96``, the dark tiles seen on whole-sequence maps."""
    from vigs_core.mapping.mapper import MapperConfig

    dtype = torch.float32
    cam = RenderCamera(24, 16, 20.0, 20.0, 12.0, 8.0)   # the stack projects onto the centre of pixel (12, 8)
    n = 300
    means = torch.zeros(n, 3, dtype=dtype)
    means[:, 2] = torch.linspace(1.0, 2.0, n, dtype=dtype)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype).repeat(n, 1)
    scales = (0.05 * means[:, 2:3]).repeat(1, 3)   # about 1 px wide at every depth
    opac = torch.full((n,), 0.02, dtype=dtype)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=dtype)
    T_CW = torch.eye(4, dtype=dtype)
    assert MapperConfig().max_per_tile == RenderSettings().max_per_tile >= n
    whole = 1.0 - 0.98 ** n
    for compiled in (False, True):
        out = TorchRasterizer(RenderSettings(), compiled=compiled)(means, quats, scales, opac, colors, T_CW, cam)
        assert abs(float(out.alpha[8, 12]) - whole) < 1e-4
        cut = TorchRasterizer(RenderSettings(max_per_tile=96), compiled=compiled)(
            means, quats, scales, opac, colors, T_CW, cam)
        assert abs(float(cut.alpha[8, 12]) - (1.0 - 0.98 ** 96)) < 1e-4
