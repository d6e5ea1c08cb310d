"""Small helpers for code that runs on either torch tensors or NumPy arrays.

The library's algorithms are torch (device-agnostic); a few hot paths on tiny arrays (IMU preintegration, the
inertial factor, per-frame pose alignment) compute in NumPy on the host, where torch's per-operation cost would
dominate, and the SO(3) functions they share accept both. These helpers keep those two worlds in one
implementation:

* :func:`array_module` -- ``numpy`` or ``torch``, whose element-wise functions (``where``, ``sin``, ``sqrt``,
  ``diagonal``, ``linalg.norm``, ...) agree in name and positional arguments;
* :func:`host` -- a tensor (any device) or array-like as a NumPy array;
* :func:`constant_like` -- a constant table (a NumPy array) in the type, dtype and device of an input;
* :func:`take_along` -- ``np.take_along_axis`` / ``torch.take_along_dim``.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import torch


def array_module(x: torch.Tensor | np.ndarray) -> Any:
    """``numpy`` for a NumPy array, else ``torch``."""
    return np if isinstance(x, np.ndarray) else torch


def host(x: Any, dtype: Any = None) -> np.ndarray:
    """A tensor (detached, copied from its device when not on the CPU) or an array-like as a NumPy array,
    converted to ``dtype`` when given (no copy when it already has it)."""
    arr = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    return arr if dtype is None else arr.astype(dtype, copy=False)


def constant_like(constant: np.ndarray, x: torch.Tensor | np.ndarray) -> torch.Tensor | np.ndarray:
    """The constant table ``constant`` (a NumPy array) in ``x``'s dtype, as a NumPy array when ``x`` is one, else
    as a tensor on ``x``'s device."""
    if isinstance(x, np.ndarray):
        return constant if constant.dtype == x.dtype else constant.astype(x.dtype)
    return torch.from_numpy(constant).to(x)


def take_along(x: torch.Tensor | np.ndarray, index: Any, axis: int) -> torch.Tensor | np.ndarray:
    """Values of ``x`` at ``index`` along ``axis`` (``np.take_along_axis`` / ``torch.take_along_dim``)."""
    if isinstance(x, np.ndarray):
        return np.take_along_axis(x, index, axis)
    return torch.take_along_dim(x, index, axis)
