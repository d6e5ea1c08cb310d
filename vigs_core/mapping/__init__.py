"""Gaussian-splatting map (VIGS-SLAM Sec. 3.3): state, rasterizers, online mapper, anchoring, PLY.

Layers, top to bottom:

* :class:`GaussianMapper` (``mapper.py``): the online mapping loop fed with keyframes and keyframe pose
  updates, asynchronous on its own thread; renders, saves, reports deltas.
* Map operations: :func:`gaussians_from_depth` (``init.py``), :func:`anchored_update` (``anchor.py``,
  Eq. 6-7), :class:`RowAdam` (``optimizer.py``), PLY I/O (``ply.py``), PSNR/SSIM (``metrics.py``).
* Rasterizers behind one interface (``rasterizer.py``): :class:`TorchRasterizer`, a pure-PyTorch
  tile-based reference with an analytic backward (CPU or GPU), and :class:`GsplatRasterizer`
  (``gsplat_backend.py``) on CUDA when gsplat is installed; :func:`make_rasterizer` picks one.
* State: :class:`GaussianMap` (``gaussians.py``), plain tensors, one row per Gaussian.
"""
from vigs_core.mapping.anchor import anchored_update
from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.init import gaussians_from_depth
from vigs_core.mapping.mapper import GaussianMapper, Keyframe, MapDelta, MapperConfig, MapperStats, MapperSummary
from vigs_core.mapping.metrics import psnr, ssim
from vigs_core.mapping.optimizer import RowAdam
from vigs_core.mapping.ply import load_map, load_ply, save_map, save_ply
from vigs_core.mapping.rasterizer import (
    RenderCamera,
    RenderOutput,
    RenderSettings,
    TorchRasterizer,
    make_rasterizer,
    project_gaussians,
)

__all__ = [
    "GaussianMap",
    "GaussianMapper",
    "Keyframe",
    "MapDelta",
    "MapperConfig",
    "MapperStats",
    "MapperSummary",
    "RenderCamera",
    "RenderOutput",
    "RenderSettings",
    "RowAdam",
    "TorchRasterizer",
    "anchored_update",
    "gaussians_from_depth",
    "load_map",
    "load_ply",
    "make_rasterizer",
    "project_gaussians",
    "psnr",
    "save_map",
    "save_ply",
    "ssim",
]
