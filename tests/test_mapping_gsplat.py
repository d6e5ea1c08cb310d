"""Parity of the gsplat backend with the reference rasterizer (runs only where CUDA and gsplat exist)."""
from __future__ import annotations

import pytest
import torch

from vigs_core.mapping.gsplat_backend import gsplat_available
from vigs_core.mapping.rasterizer import RenderCamera, RenderSettings, TorchRasterizer

pytestmark = pytest.mark.skipif(not gsplat_available(), reason="needs CUDA and the gsplat package")


def test_gsplat_matches_the_reference_rasterizer():
    from vigs_core.mapping.gsplat_backend import GsplatRasterizer

    device = "cuda"
    g = torch.Generator().manual_seed(0)
    n = 400
    means = (torch.randn(n, 3, generator=g) * torch.tensor([1.0, 0.7, 0.3]) + torch.tensor([0.0, 0.0, 4.0]))
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = torch.rand(n, 3, generator=g) * 0.08 + 0.02
    opac = torch.rand(n, generator=g) * 0.9 + 0.05  # below both backends' clamps
    colors = torch.rand(n, 3, generator=g)
    cam = RenderCamera(160, 120, 150.0, 150.0, 79.5, 59.5)
    T_CW = torch.eye(4)
    args = [t.to(device).requires_grad_() for t in (means, quats, scales, opac, colors)]
    ref = TorchRasterizer(RenderSettings(tile_size=16, max_per_tile=4096))(*args, T_CW.to(device), cam)
    out = GsplatRasterizer(RenderSettings(tile_size=16))(*args, T_CW.to(device), cam)
    assert (out.alpha - ref.alpha).abs().mean() < 2e-3
    assert (out.color - ref.color).abs().mean() < 2e-3
    assert (out.depth - ref.depth).abs().mean() < 1e-2
    # gradients of the same loss agree in direction
    grads = [
        torch.autograd.grad(o.color.sum() + o.depth.sum(), [args[0], args[4]]) for o in (ref, out)
    ]
    for g_ref, g_out in zip(*grads):
        cos = torch.nn.functional.cosine_similarity(g_ref.flatten(), g_out.flatten(), dim=0)
        assert cos > 0.99
