"""The in-process pipeline (``vigs run``): configuration, inputs (EuRoC ASL, ROS bags), the streaming odometry that
``vigs run`` and the frontend node drive, the run loop, outputs."""
from vigs_core.system.config import PipelineConfig, apply_overrides, load_config
from vigs_core.system.sources import InputSequence, open_input
from vigs_core.system.pipeline import run_pipeline
from vigs_core.system.stream import OdometryStream, Preprocessor

__all__ = [name for name in dir() if not name.startswith("_")]
