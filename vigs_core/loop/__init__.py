"""Loop closure: candidate detection and dense two-view verification, loop edges, the relative-pose graph, the
Sim(3) pose-graph bundle adjustment on a worker thread, and applying its corrections to the frontend and the
Gaussian map (VIGS-SLAM Sec. 3.1, 3.3)."""
from vigs_core.loop.apply import (apply_to_mapper, apply_to_odometry, corrected_pose, corrections_for,
                                  rotate_velocities)
from vigs_core.loop.closure import LoopClosure, LoopStats
from vigs_core.loop.config import LoopConfig, LoopDetectionConfig, LoopGraphConfig, LoopVerificationConfig
from vigs_core.loop.detection import KeyframeView, LoopDecision, LoopDetector, LoopEdge
from vigs_core.loop.driver import LoopClosureDriver, keyframe_views
from vigs_core.loop.pgba import KeyframePoseGraph, PGBAResult, run_pgba
from vigs_core.loop.pose_graph import PoseGraph, PoseGraphConfig, PoseGraphResult, optimize_pose_graph
from vigs_core.loop.two_view import (TwoViewCorrespondences, TwoViewResult, edge_information,
                                     estimate_relative_sim3)

__all__ = [
    "KeyframePoseGraph", "KeyframeView", "LoopClosure", "LoopClosureDriver", "LoopConfig", "LoopDecision",
    "LoopDetectionConfig", "LoopDetector", "LoopEdge", "LoopGraphConfig", "LoopStats", "LoopVerificationConfig",
    "PGBAResult", "PoseGraph", "PoseGraphConfig", "PoseGraphResult", "TwoViewCorrespondences", "TwoViewResult",
    "apply_to_mapper", "apply_to_odometry", "corrected_pose", "corrections_for", "edge_information",
    "estimate_relative_sim3", "keyframe_views", "optimize_pose_graph", "rotate_velocities", "run_pgba",
]
