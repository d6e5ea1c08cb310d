"""Dense bundle adjustment: inverse-depth reprojection, normal equations with the Schur complement on the
diagonal disparity block, Levenberg-Marquardt with Huber weights and gauge fixing, pose-only alignment."""
from vigs_core.solver.projective import Intrinsics, Reprojection, pixel_rays, reproject
from vigs_core.solver.robust import huber_cost, huber_weight
from vigs_core.solver.normal_equations import (EdgeSet, VisualSystem, back_substitute, linearize_visual,
                                               residuals, schur_reduce, visual_cost)
from vigs_core.solver.dense_ba import AdditionalTerms, BAConfig, BAResult, bundle_adjust
from vigs_core.solver.pose_alignment import PoseAlignment, align_pose

__all__ = [name for name in dir() if not name.startswith("_")]
