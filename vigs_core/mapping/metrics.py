"""Render-quality metrics: PSNR and SSIM.

PSNR = 10 log10(peak^2 / MSE) (dB). SSIM (Wang et al. 2004, Eq. 13) with the usual settings: an 11x11
Gaussian window of standard deviation 1.5 px, ``C1 = (0.01 peak)^2``, ``C2 = (0.03 peak)^2``, statistics
per channel over the 'valid' window positions (no padding), averaged over positions and channels.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
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
    """Mean SSIM of ``img`` against ``ref`` ((H, W) or (H, W, C), same shape, at least ``window`` px).

    The five local statistics (both means, both second moments, the cross moment) are blurred together, one
    separable float32 filter over their ``5 C`` channels (OpenCV), and cropped to the 'valid' positions; the SSIM
    map is then formed in float64. Identical inputs give exactly 1; the float32 blur moves the mean SSIM by
    about 1e-7. Where every channel of both images is the same (a grey map and its grey frames, as ``vigs run``
    maps them), one channel is measured: the same mean at a third of the cost."""
    a, b = (torch.as_tensor(x).detach().cpu() for x in (img, ref))
    if a.dim() not in (2, 3) or a.shape != b.shape:
        raise ValueError(f"ssim needs images of the same shape (H, W) or (H, W, C), got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")
    if min(a.shape[:2]) < window:
        raise ValueError(f"ssim needs images of at least {window}x{window} px, got {tuple(a.shape[:2])}")
    a, b = (x.reshape(x.shape[0], x.shape[1], -1).to(torch.float32).numpy() for x in (a, b))
    if a.shape[2] > 1 and all((x == x[..., :1]).all() for x in (a, b)):
        a, b = a[..., :1], b[..., :1]
    g = cv2.getGaussianKernel(window, sigma, cv2.CV_32F)   # normalised to sum 1
    r, c = window // 2, a.shape[2]
    stats = np.concatenate([a, b, a * a, b * b, a * b], axis=2)   # (H, W, 5 C)
    blurred = cv2.sepFilter2D(stats, -1, g, g, borderType=cv2.BORDER_REFLECT)[r:-r, r:-r].astype(np.float64)
    mu_a, mu_b, aa, bb, ab = (blurred[..., k * c:(k + 1) * c] for k in range(5))
    c1, c2 = (0.01 * peak) ** 2, (0.03 * peak) ** 2
    var_a, var_b, cov = aa - mu_a ** 2, bb - mu_b ** 2, ab - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(s.mean())
