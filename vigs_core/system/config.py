"""Configuration of the in-process pipeline (``vigs run``): one dataclass tree with documented defaults, loadable
from ``params/*.yaml`` in the ROS 2 layout ``<node>: ros__parameters: {...}`` (nested mappings follow the
dataclass fields, e.g. ``odometry: {keyframes: {flow_threshold_px: 16.0}}``).
"""
from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from vigs_core.frontend.odometry import OdometryConfig
from vigs_core.loop.config import LoopConfig
from vigs_core.ranges import Range, bounded, field_range
from vigs_core.system.mapping import MappingConfig
from vigs_core.vio.config import VioConfig
from vigs_core.viz.rerun_log import RerunConfig

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
        checkpoint_period_s: while running, the pose outputs and a partial report.json are rewritten (atomically)
            every this many seconds of wall time, so a killed run leaves what it had (0: only at the end).
        map_checkpoint_period_s: the same for map.ply (slower to write; 0: only at the end).
        odometry: the frontend's settings.
        imu: visual-inertial settings (:class:`vigs_core.vio.VioConfig`); with ``imu.enabled`` (default) and an
            input that has IMU data the odometry is visual-inertial (metric, gravity-aligned once initialised).
        loop: loop closure (:class:`vigs_core.loop.LoopConfig`); with ``loop.enabled`` (default) detection and
            PGBA run in a worker process beside tracking and correct the keyframes.
        mapping: the Gaussian mapper (:class:`vigs_core.system.mapping.MappingConfig`); with ``mapping.enabled``
            (default) keyframes are mapped in a worker process and DIR/map.ply is written. It takes up to a core
            while it runs (docs/benchmarks.md, issue 23); ``mapping: {enabled: false}`` for odometry only.
        rerun: what ``vigs run --viz`` / ``--rrd`` log how often (:class:`vigs_core.viz.rerun_log.RerunConfig`).
    """

    width: int = bounded(376, 1)
    height: int = bounded(240, 1)
    torch_threads: int = bounded(1, 1)
    max_frames: int | None = bounded(None, 0)
    frame_stride: int = bounded(1, 1)
    image_topic: str | None = None
    max_bad_frames: int = bounded(20, 0)
    checkpoint_period_s: float = bounded(30.0, 0)
    map_checkpoint_period_s: float = bounded(120.0, 0)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    imu: VioConfig = field(default_factory=VioConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    rerun: RerunConfig = field(default_factory=RerunConfig)


class ParameterTypeError(ValueError):
    """A parameter value of the wrong type or outside its range; ``problem`` says what was expected and what
    came."""

    def __init__(self, name: str, problem: str) -> None:
        super().__init__(f"parameter {name}: {problem}")
        self.problem = problem


def checked_value(value: Any, kind: Any, name: str, rng: Range | None = None) -> Any:
    """``value`` as a field of declared type ``kind`` (bool, int, float, str, ``X | None``, ``tuple[...]``, ...)
    and, when it is a number, within ``rng`` (the field's :func:`~vigs_core.ranges.bounded` range); ValueError
    naming ``name``, the expected type or range and the value otherwise. An int is a float; a list is a
    tuple of the declared length. Raises :class:`ParameterTypeError`."""
    args = typing.get_args(kind)
    if type(kind) is types.UnionType or typing.get_origin(kind) is typing.Union:
        if value is None and type(None) in args:
            return None
        errors = []
        for option in (a for a in args if a is not type(None)):
            try:
                return checked_value(value, option, name, rng)
            except ValueError as err:
                errors.append(err)
        raise errors[0]
    origin = typing.get_origin(kind)
    ok = True
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif kind is str:
        ok = isinstance(value, str)
    elif origin is tuple:
        ok = isinstance(value, (list, tuple))
        items = [args[0]] * len(value) if ok and args[-1] is Ellipsis else list(args)
        ok = ok and len(value) == len(items)
        if ok:
            value = tuple(checked_value(v, a, f"{name}[{i}]") for i, (v, a) in enumerate(zip(value, items)))
    if not ok:
        expected = getattr(kind, "__name__", str(kind))
        raise ParameterTypeError(name, f"expected {expected}, got {value!r} ({type(value).__name__})")
    if rng is not None and isinstance(value, (int, float)) and value not in rng:
        raise ParameterTypeError(name, f"expected a value in {rng}, got {value!r}")
    return value


def apply_overrides(obj: Any, values: dict, where: str = "") -> Any:
    """Set dataclass fields of ``obj`` from a (nested) mapping, in place, each checked against its declared type
    and range (:func:`checked_value`); unknown keys raise ``KeyError`` naming the valid ones, a wrong type or a
    value out of range ``ValueError`` naming the key and the expected type or range. Returns ``obj``."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    hints = typing.get_type_hints(type(obj))
    for key, value in values.items():
        if key not in names:
            raise KeyError(f"unknown parameter {where}{key!r}; expected one of {sorted(names)}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"parameter {where}{key}: expected a mapping of {type(current).__name__} fields, "
                                 f"got {value!r} ({type(value).__name__})")
            apply_overrides(current, value, f"{where}{key}.")
        else:
            setattr(obj, key, checked_value(value, hints[key], f"{where}{key}", field_range(names[key])))
    if hasattr(obj, "__post_init__"):
        obj.__post_init__()
    return obj


def read_params_yaml(path: str | Path) -> dict:
    """The top-level mapping of a ROS 2 parameter file, every entry a node section ``<node>: {ros__parameters:
    {...}}`` (or ``/**``); ValueError naming the file for malformed YAML, another top level or an entry of
    another shape (a graph-wide file: each node reads its own section, so a misplaced one would go unread)."""
    try:
        content = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not valid YAML: {' '.join(str(err).split())}") from None
    if not isinstance(content, dict):
        raise ValueError(f"{path}: expected a mapping '<node>: {{ros__parameters: ...}}', got "
                         f"{type(content).__name__}")
    for key, value in content.items():
        if not (isinstance(value, dict) and isinstance(value.get("ros__parameters", 0), (dict, type(None)))):
            raise ValueError(f"{path}: top-level {key!r} is not a '<node>: ros__parameters:' section")
    return content


def load_config(path: str | Path | None = None, node: str = NODE_NAME) -> PipelineConfig:
    """Defaults, overridden by ``<node>: ros__parameters:`` of the YAML file ``path`` when given. Malformed YAML,
    a missing section, a top-level entry that is not a node section, unknown keys, wrong types and values out of
    range raise ``ValueError`` naming the file and the key."""
    cfg = PipelineConfig()
    if path is None:
        return cfg
    content = read_params_yaml(path)
    section = content.get(node, {}).get("ros__parameters")
    if not isinstance(section, dict):
        raise ValueError(f"{path}: no '{node}: ros__parameters:' mapping (found top-level keys {sorted(content)})")
    try:
        return apply_overrides(cfg, section)
    except KeyError as err:
        raise ValueError(f"{path}: {err.args[0]}") from None
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None
