"""Render-quality metrics: PSNR and SSIM.

PSNR = 10 log10(peak^2 / MSE) (dB). SSIM (Wang et al. 2004, Eq. 13) with the usual settings: an 11x11
Gaussian window of standard deviation 1.5 px, ``C1 = (0.01 peak)^2``, ``C2 = (0.03 peak)^2``, statistics
per channel over the 'valid' window positions (no padding), averaged over positions and channels.
"""
from __future__ import annotations

import math

import torch


def _as_chw(img: torch.Tensor) -> torch.Tensor:
    """(H, W) or (H, W, C) -> (C, H, W) float64."""
    img = torch.as_tensor(img)
    if img.dim() == 2:
        img = img[..., None]
    if img.dim() != 3:
        raise ValueError(f"images must be (H, W) or (H, W, C), got shape {tuple(img.shape)}")
    return img.permute(2, 0, 1).to(torch.float64)


def psnr(img: torch.Tensor, ref: torch.Tensor, peak: float = 1.0) -> float:
    """PSNR in dB of ``img`` against ``ref`` ((H, W) or (H, W, C), same shape); ``inf`` when identical."""
    a, b = _as_chw(img), _as_chw(ref)
    if a.shape != b.shape:
        raise ValueError(f"psnr needs images of the same shape, got {tuple(img.shape)} and {tuple(ref.shape)}")
    mse = float(((a - b) ** 2).mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def ssim(img: torch.Tensor, ref: torch.Tensor, peak: float = 1.0, window: int = 11, sigma: float = 1.5) -> float:
    """Mean SSIM of ``img`` against ``ref`` ((H, W) or (H, W, C), same shape, at least ``window`` px)."""
    a, b = _as_chw(img), _as_chw(ref)
    if a.shape != b.shape:
        raise ValueError(f"ssim needs images of the same shape, got {tuple(img.shape)} and {tuple(ref.shape)}")
    if min(a.shape[1:]) < window:
        raise ValueError(f"ssim needs images of at least {window}x{window} px, got {tuple(a.shape[1:])}")
    x = torch.arange(window, dtype=torch.float64) - (window - 1) / 2.0
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    g = (g / g.sum()).tolist()

    def blur(t: torch.Tensor) -> torch.Tensor:
        # the 2D Gaussian window is separable: filter rows then columns ('valid' positions only), as
        # sums of shifted copies (an 11x11 conv2d in float64 goes through a 121x larger im2col buffer)
        h, w = t.shape[-2] - window + 1, t.shape[-1] - window + 1
        rows = sum(gk * t[..., k : k + w] for k, gk in enumerate(g))
        return sum(gk * rows[..., k : k + h, :] for k, gk in enumerate(g))

    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return float(s.mean())
