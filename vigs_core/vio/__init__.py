"""Tightly coupled visual-inertial back end (VIGS-SLAM Sec. 3.2-3.3): inertial residual blocks inside dense BA,
IMU keyframe initialisation, three-stage initialisation with map rescaling and gravity alignment, and the
visual-inertial odometry built on the dense front end."""
from vigs_core.vio.config import ABLATIONS, VioConfig
from vigs_core.vio.inertial_terms import AnchorPrior, InertialState, InertialTerms, MarginalPrior
from vigs_core.vio.marginalization import marginalize_keyframe
from vigs_core.vio.keyframe_init import KeyframePrediction, predict_keyframe
from vigs_core.vio.initialization import (InitOutcome, Stage, StagedInitializer, WorldAlignment,
                                          alignment_from_gravity, gravity_from_accelerometer)
from vigs_core.vio.estimator import KeyframeInertial, VisualInertialEstimator
from vigs_core.vio.odometry import VisualInertialOdometry

__all__ = [name for name in dir() if not name.startswith("_")]
