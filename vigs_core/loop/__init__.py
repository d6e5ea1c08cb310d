"""Loop closure: candidate detection, loop edges and the Sim(3) pose-graph bundle adjustment."""
from vigs_core.loop.pose_graph import PoseGraph, PoseGraphConfig, PoseGraphResult, optimize_pose_graph

__all__ = ["PoseGraph", "PoseGraphConfig", "PoseGraphResult", "optimize_pose_graph"]
