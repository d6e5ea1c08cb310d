"""Dense monocular frontend: correspondence estimators on a reduced grid (classical DIS flow), keyframe policy,
sliding-window frame graph, and the odometry that tracks every frame and runs dense BA per keyframe."""
from vigs_core.frontend.correspondence import Correspondences, CorrespondenceEstimator, PixelGrid
from vigs_core.frontend.dis_flow import DISFlowConfig, DISFlowEstimator
from vigs_core.frontend.keyframe_policy import KeyframePolicy, KeyframePolicyConfig
from vigs_core.frontend.frame_graph import FrameGraph, FrameGraphConfig
from vigs_core.frontend.odometry import DenseOdometry, Keyframe, OdometryConfig

__all__ = [name for name in dir() if not name.startswith("_")]
