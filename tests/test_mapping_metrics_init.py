"""PSNR/SSIM against closed forms, and keyframe depth -> Gaussians."""
from __future__ import annotations

import math

import pytest
import torch

from vigs_core.mapping.init import gaussians_from_depth
from vigs_core.mapping.metrics import psnr, ssim
from vigs_core.mapping.rasterizer import RenderCamera


def test_psnr_of_a_uniform_error():
    ref = torch.rand(20, 30, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 0.8
    assert math.isclose(psnr(ref + 0.1, ref), 20.0, rel_tol=1e-9)
    assert psnr(ref, ref) == math.inf


def test_ssim_closed_forms():
    img = torch.rand(32, 40, generator=torch.Generator().manual_seed(1))
    assert math.isclose(ssim(img, img), 1.0, rel_tol=1e-12)
    # constant images: variances vanish, SSIM = (2ab + C1) / (a^2 + b^2 + C1)
    a, b, c1 = 0.3, 0.6, 0.01**2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    # (the statistics are blurred in float32: a constant's variance comes out about 1e-8 instead of 0)
    assert math.isclose(ssim(torch.full((16, 16), a), torch.full((16, 16), b)), expected, rel_tol=1e-5)
    noisy = (img + 0.2 * torch.randn(32, 40, generator=torch.Generator().manual_seed(2))).clamp(0, 1)
    assert 0.0 < ssim(noisy, img) < 0.9
    # a colour image against the float64 definition (Wang et al. 2004: 11x11 Gaussian, 'valid' positions)
    rgb = torch.rand(24, 30, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    ref = (rgb + 0.1 * torch.randn(24, 30, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64))
    assert math.isclose(ssim(rgb, ref), _ssim_float64(rgb, ref), rel_tol=1e-5)
    # grey images as three equal channels (a grey map): the same value as the definition over all three
    grey, grey_ref = (x[..., :1].expand(-1, -1, 3) for x in (rgb, ref))
    assert math.isclose(ssim(grey, grey_ref), _ssim_float64(grey, grey_ref), rel_tol=1e-5)
    assert math.isclose(ssim(grey, grey_ref), ssim(rgb[..., 0], ref[..., 0]), rel_tol=1e-12)
    with pytest.raises(ValueError, match="same shape"):
        ssim(img, img[:-1])


def _ssim_float64(a: torch.Tensor, b: torch.Tensor) -> float:
    """SSIM written out with an explicit 11x11 window (float64 conv2d), the reference for the fast version."""
    x = torch.arange(11, dtype=torch.float64) - 5.0
    g = torch.exp(-0.5 * (x / 1.5) ** 2)
    w = (g[:, None] * g[None, :] / g.sum() ** 2)[None, None]
    a, b = (t.permute(2, 0, 1)[:, None] for t in (a, b))   # (C, 1, H, W)
    blur = lambda t: torch.nn.functional.conv2d(t, w)   # noqa: E731 - 'valid' positions
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def test_gaussians_from_depth_lie_on_the_unprojected_surface():
    cam = RenderCamera(12, 10, 20.0, 22.0, 5.5, 4.5)
    depth = torch.full((10, 12), 2.0)
    depth[1, 3] = 0.0  # invalid: skipped
    image = torch.rand(10, 12, 3)
    T_WC = torch.eye(4)
    T_WC[:3, 3] = torch.tensor([1.0, 2.0, 3.0])
    g = gaussians_from_depth(image, depth, T_WC, cam, anchor_id=4, first_id=10, stride=2, init_scale=0.5)
    assert len(g) == 6 * 5 - 1  # pixels (1::2, 1::2) minus the invalid one
    assert torch.allclose(g.means[:, 2], torch.full((len(g),), 5.0))
    # samples are pixel centres (u, v) = (1 + 2j, 1 + 2i); the first is (1, 1), the second (5, 1)
    assert torch.allclose(g.means[0, :2], torch.tensor([1.0 + (1 - 5.5) / 20.0 * 2.0, 2.0 + (1 - 4.5) / 22.0 * 2.0]))
    assert torch.allclose(g.means[1, :2], torch.tensor([1.0 + (5 - 5.5) / 20.0 * 2.0, 2.0 + (1 - 4.5) / 22.0 * 2.0]))
    assert torch.allclose(g.colors[1], image[1, 5])
    assert torch.allclose(g.scales(), torch.full((len(g), 3), 0.5 * 2 * 2.0 / 21.0))
    assert torch.allclose(g.opacities(), torch.full((len(g),), 0.5))
    assert g.anchor_ids.unique().tolist() == [4] and g.ids.tolist() == list(range(10, 10 + len(g)))
