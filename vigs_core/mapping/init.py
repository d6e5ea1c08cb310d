"""New Gaussians from a keyframe's depth map (VIGS-SLAM Sec. 3.3, "map initialisation / expansion").

Every ``stride``-th pixel ``(u, v)`` with valid depth ``d`` (and inside an optional mask) becomes one
Gaussian at ``mu = T_WC [d (u - cx)/fx, d (v - cy)/fy, d]``, isotropic with standard deviation
``sigma = init_scale * stride * d / f`` metres (``f = (fx + fy)/2``: ``init_scale`` pixel spacings on the
image, so neighbours overlap and cover the surface), identity rotation, opacity 0.5 and the pixel's colour.
"""
from __future__ import annotations

import torch

from vigs_core.mapping.gaussians import GaussianMap


def gaussians_from_depth(
    image: torch.Tensor,
    depth: torch.Tensor,
    T_WC: torch.Tensor,
    camera,
    anchor_id: int,
    first_id: int,
    stride: int = 2,
    init_scale: float = 0.5,
    mask: torch.Tensor | None = None,
) -> GaussianMap:
    """Unproject a keyframe into Gaussians anchored to it.

    Args:
        image: (H, W, 3) RGB in [0, 1], same size as ``camera``.
        depth: (H, W) metres; pixels with depth <= 0 or non-finite are skipped.
        T_WC: (4, 4) world-from-camera pose of the keyframe.
        camera: intrinsics of ``image`` (width, height, fx, fy, cx, cy; pixel centre of ``(i, j)`` at ``(j, i)``).
        anchor_id: keyframe id stored in every new Gaussian.
        first_id: persistent id of the first new Gaussian (the others follow consecutively).
        stride: take every ``stride``-th pixel in each direction.
        init_scale: standard deviation in units of the pixel spacing ``stride``.
        mask: optional (H, W) bool; only pixels where it is true are used.

    Returns:
        The new Gaussians (float dtype of ``image``), possibly empty.
    """
    H, W = depth.shape
    if image.shape != (H, W, 3):
        raise ValueError(f"image must be (H, W, 3) = ({H}, {W}, 3) to match depth, got {tuple(image.shape)}")
    if (camera.width, camera.height) != (W, H):
        raise ValueError(f"camera is {camera.width}x{camera.height} but the depth map is {W}x{H}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    dtype, device = image.dtype, image.device
    off = stride // 2
    d = depth[off::stride, off::stride].to(dtype)
    rgb = image[off::stride, off::stride]
    v = torch.arange(off, H, stride, dtype=dtype, device=device)[:, None].expand_as(d)
    u = torch.arange(off, W, stride, dtype=dtype, device=device)[None, :].expand_as(d)
    ok = torch.isfinite(d) & (d > 0)
    if mask is not None:
        ok &= mask[off::stride, off::stride]
    d, u, v, rgb = d[ok], u[ok], v[ok], rgb[ok]
    p_cam = torch.stack(((u - camera.cx) / camera.fx * d, (v - camera.cy) / camera.fy * d, d), -1)
    T = T_WC.to(dtype=dtype, device=device)
    means = p_cam @ T[:3, :3].T + T[:3, 3]
    n = means.shape[0]
    sigma = init_scale * stride * d / (0.5 * (camera.fx + camera.fy))
    quats = torch.zeros(n, 4, dtype=dtype, device=device)
    quats[:, 0] = 1.0
    return GaussianMap(
        means=means,
        log_scales=sigma.log()[:, None].expand(n, 3).clone(),
        quats=quats,
        opacity_logits=torch.zeros(n, dtype=dtype, device=device),
        colors=rgb.clone(),
        anchor_ids=torch.full((n,), int(anchor_id), dtype=torch.int64, device=device),
        ids=torch.arange(first_id, first_id + n, dtype=torch.int64, device=device),
    )
