"""gsplat (nerfstudio-project/gsplat) as a rasterizer backend, used on CUDA when the package is installed.

It renders the same model as :class:`vigs_core.mapping.rasterizer.TorchRasterizer` ("classic" 3DGS, 0.3 px^2
low-pass, 16 px tiles, ``render_mode="RGB+D"``: colour and alpha-weighted depth). Differences: gsplat puts
pixel ``(i, j)``'s centre at ``(j + 0.5, i + 0.5)``, so ``cx``/``cy`` are shifted by half a pixel here to
keep the project's convention (centre at ``(j, i)``); gsplat clamps ``o G`` at 0.999 and stops a pixel once
its transmittance falls below 1e-4, where the reference clamps ``o`` at 0.99 and composites all of a tile's
``K`` front-most Gaussians. Results agree to within those effects (tested where CUDA exists).
"""
from __future__ import annotations

import importlib.util

import torch

from vigs_core.mapping.rasterizer import RenderCamera, RenderOutput, RenderSettings


def gsplat_available() -> bool:
    """True when CUDA is usable and the ``gsplat`` package can be imported."""
    return torch.cuda.is_available() and importlib.util.find_spec("gsplat") is not None


class GsplatRasterizer:
    """:class:`vigs_core.mapping.rasterizer.Rasterizer` backed by ``gsplat.rasterization`` (CUDA tensors)."""

    def __init__(self, settings: RenderSettings | None = None) -> None:
        if not gsplat_available():
            raise RuntimeError("GsplatRasterizer needs CUDA and the gsplat package (pip install gsplat)")
        self.settings = settings or RenderSettings()

    def __call__(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        T_CW: torch.Tensor,
        camera: RenderCamera,
    ) -> RenderOutput:
        from gsplat import rasterization

        dtype, device = means.dtype, means.device
        K = torch.tensor(
            [[camera.fx, 0.0, camera.cx + 0.5], [0.0, camera.fy, camera.cy + 0.5], [0.0, 0.0, 1.0]],
            dtype=dtype,
            device=device,
        )
        renders, alphas, meta = rasterization(
            means,
            quats / quats.norm(dim=-1, keepdim=True),   # the Rasterizer protocol: quats of any length
            scales,
            opacities,
            colors,
            T_CW.to(dtype=dtype, device=device)[None],
            K[None],
            camera.width,
            camera.height,
            near_plane=self.settings.near,
            eps2d=self.settings.eps2d,
            packed=False,
            render_mode="RGB+D",
            rasterize_mode="classic",
        )
        radii = meta["radii"][0]
        visible = ((radii > 0).all(-1) if radii.dim() == 2 else radii > 0).nonzero().squeeze(1)
        return RenderOutput(renders[0, ..., :3], renders[0, ..., 3], alphas[0, ..., 0], visible)
