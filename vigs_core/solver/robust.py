"""Huber robust kernel on residual norms (pixels), used by iteratively reweighted least squares.

``rho(e) = e^2 / 2`` for ``e <= delta`` and ``delta (e - delta / 2)`` beyond; the IRLS weight is
``rho'(e) / e = min(1, delta / e)`` (Huber 1964; Triggs et al., Bundle Adjustment - A Modern Synthesis, 3.3).
"""
from __future__ import annotations

import torch


def huber_weight(e: torch.Tensor, delta: float) -> torch.Tensor:
    """IRLS weights ``min(1, delta / e)`` for residual norms ``e`` (any shape)."""
    return torch.clamp(delta / e.clamp(min=1e-12), max=1.0)


def huber_cost(e: torch.Tensor, delta: float) -> torch.Tensor:
    """Huber cost ``rho(e)`` elementwise."""
    return torch.where(e <= delta, 0.5 * e * e, delta * (e - 0.5 * delta))
