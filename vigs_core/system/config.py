"""Configuration of the in-process pipeline (``vigs run``): one dataclass tree with documented defaults, loadable
from ``params/*.yaml`` in the ROS 2 layout ``<node>: ros__parameters: {...}`` (nested mappings follow the
dataclass fields, e.g. ``odometry: {keyframes: {flow_threshold_px: 16.0}}``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vigs_core.frontend.odometry import OdometryConfig
from vigs_core.loop.config import LoopConfig
from vigs_core.system.mapping import MappingConfig
from vigs_core.vio.config import VioConfig

NODE_NAME = "frontend"


@dataclass
class PipelineConfig:
    """Settings of :func:`vigs_core.system.pipeline.run_pipeline`.

    Args:
        width, height: processing resolution, pixels; images are undistorted to a pinhole camera and resized
            to it (376x240 is half of EuRoC's 752x480, cropped to the valid pinhole area).
        torch_threads: ``torch.set_num_threads``; also OpenCV's thread count.
        max_frames: stop after this many frames (None: all).
        frame_stride: use every n-th frame.
        image_topic: bag image topic (None: found by message type).
        max_bad_frames: frames that cannot be read or decoded are skipped with a warning; more than this many
            end the run (its outputs are written) with an error.
        odometry: the frontend's settings.
        imu: visual-inertial settings (:class:`vigs_core.vio.VioConfig`); with ``imu.enabled`` (default) and an
            input that has IMU data the odometry is visual-inertial (metric, gravity-aligned once initialised).
        loop: loop closure (:class:`vigs_core.loop.LoopConfig`); with ``loop.enabled`` (default) detection and
            PGBA run on a worker thread beside tracking and correct the keyframes.
        mapping: the Gaussian mapper (:class:`vigs_core.system.mapping.MappingConfig`); with ``mapping.enabled``
            (default) keyframes are mapped on a worker thread and DIR/map.ply is written. It costs CPU (about
            1-2 s per keyframe on a CPU core at the defaults); ``mapping: {enabled: false}`` for odometry only.
    """

    width: int = 376
    height: int = 240
    torch_threads: int = 1
    max_frames: int | None = None
    frame_stride: int = 1
    image_topic: str | None = None
    max_bad_frames: int = 20
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    imu: VioConfig = field(default_factory=VioConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)


def apply_overrides(obj: Any, values: dict, where: str = "") -> Any:
    """Set dataclass fields of ``obj`` from a (nested) mapping, in place; unknown keys raise ``KeyError``
    naming the valid ones. Returns ``obj``."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in values.items():
        if key not in names:
            raise KeyError(f"unknown parameter {where}{key!r}; expected one of {sorted(names)}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            apply_overrides(current, value, f"{where}{key}.")
        else:
            setattr(obj, key, value)
    if hasattr(obj, "__post_init__"):
        obj.__post_init__()
    return obj


def load_config(path: str | Path | None = None, node: str = NODE_NAME) -> PipelineConfig:
    """Defaults, overridden by ``<node>: ros__parameters:`` of the YAML file ``path`` when given."""
    cfg = PipelineConfig()
    if path is None:
        return cfg
    content = yaml.safe_load(Path(path).read_text()) or {}
    section = content.get(node, {}).get("ros__parameters") if isinstance(content.get(node), dict) else None
    if section is None:
        raise KeyError(f"{path}: no '{node}: ros__parameters:' section (found top-level keys {sorted(content)})")
    return apply_overrides(cfg, section)
