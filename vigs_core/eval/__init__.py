"""Trajectory evaluation: association by stamp, alignment (SE(3), Sim(3), position+yaw), ATE, RPE, recall.

Pure maths on float64 numpy arrays (evo's ``core`` is the model); file reading lives in
:mod:`vigs_core.io` and the command line in ``vigs eval``.
"""
from vigs_core.eval.alignment import ALIGN_MODES, Alignment, align, position_yaw_alignment, umeyama
from vigs_core.eval.association import associate
from vigs_core.eval.metrics import (
    RPE_UNITS,
    ate,
    error_statistics,
    recall,
    rotation_angle,
    rpe,
    rpe_pairs,
    translation_errors,
)
from vigs_core.eval.report import AlignedEstimate, align_estimate, evaluate_trajectory, recall_key

__all__ = [
    "ALIGN_MODES",
    "AlignedEstimate",
    "Alignment",
    "RPE_UNITS",
    "align",
    "align_estimate",
    "associate",
    "ate",
    "error_statistics",
    "evaluate_trajectory",
    "position_yaw_alignment",
    "recall",
    "recall_key",
    "rotation_angle",
    "rpe",
    "rpe_pairs",
    "translation_errors",
    "umeyama",
]
