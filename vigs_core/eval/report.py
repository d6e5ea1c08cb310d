"""One call that evaluates an estimated trajectory against ground truth: associate, align, measure."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vigs_core.eval.alignment import Alignment
from vigs_core.eval.alignment import align as fit_alignment
from vigs_core.eval.association import associate
from vigs_core.eval.metrics import error_statistics, recall, rpe, translation_errors
from vigs_core.types import Trajectory


def recall_key(threshold: float) -> str:
    """Result key of one recall threshold, e.g. ``0.05 -> "recall@0.05"``."""
    return f"recall@{threshold:g}"


@dataclass(frozen=True)
class AlignedEstimate:
    """An estimate paired with the ground truth by stamp and aligned onto it (:func:`align_estimate`).

    Attributes:
        i_gt: (K,) int64 index of each pair's ground-truth pose, pairs in time order.
        i_est: (K,) int64 index of each pair's estimated pose.
        alignment: the fitted alignment, mapping the estimate into the ground-truth frame.
        errors: (K,) translation errors (m) of the aligned estimate positions (the ATE per pair).
    """

    i_gt: np.ndarray
    i_est: np.ndarray
    alignment: Alignment
    errors: np.ndarray


def align_estimate(gt: Trajectory, est: Trajectory, align: str = "sim3", max_diff_s: float = 0.02) -> AlignedEstimate:
    """Associate ``est`` with ``gt`` within ``max_diff_s``, fit the alignment ``align`` of the associated estimate
    positions onto the ground truth and measure each pair's translation error (the first steps of
    :func:`evaluate_trajectory`, which raises the same errors)."""
    if max_diff_s < 0:
        raise ValueError(f"evaluate_trajectory: max_diff_s must be >= 0, got {max_diff_s}")
    i_gt, i_est = associate(gt.t_ns, est.t_ns, int(round(max_diff_s * 1e9)))
    if len(i_gt) == 0:
        raise ValueError(
            f"evaluate_trajectory: no estimate stamp lies within {max_diff_s} s of a ground-truth stamp "
            f"(ground truth {gt.t_s[0]:.3f}..{gt.t_s[-1]:.3f} s, estimate {est.t_s[0]:.3f}..{est.t_s[-1]:.3f} s); "
            "expected overlapping stamps on the same clock"
        )
    # Process pairs in time order (association orders them by the sparser sequence's stamps).
    order = np.argsort(gt.t_ns[i_gt], kind="stable")
    i_gt, i_est = i_gt[order], i_est[order]
    alignment = fit_alignment(gt.position[i_gt], est.position[i_est], align)
    errors = translation_errors(gt.position[i_gt], alignment.apply_positions(est.position[i_est]))
    return AlignedEstimate(i_gt, i_est, alignment, errors)


def evaluate_trajectory(
    gt: Trajectory,
    est: Trajectory,
    align: str = "sim3",
    thresholds: Sequence[float] = (0.05, 0.10),
    max_diff_s: float = 0.02,
    rpe_delta: float | None = None,
    rpe_unit: str = "m",
) -> dict:
    """Accuracy of ``est`` against ``gt``.

    Steps: :func:`associate` stamps within ``max_diff_s``; fit the alignment ``align``
    (``"se3" | "sim3" | "posyaw" | "none"``) of the associated estimate positions onto the ground truth;
    ATE statistics of the aligned positions; recall@thresholds over all ground-truth poses (unmatched
    ones are misses); optionally RPE of the aligned poses over ``rpe_delta`` metres (``rpe_unit="m"``)
    or seconds (``"s"``).

    Recall counts every ground-truth pose, so it is capped at ``n_matched / n_gt``: evaluate against
    ground truth sampled like the estimate (e.g. at the camera frames) when that is what it should
    measure. Both trajectories should describe the same frame (e.g. the body/IMU frame); an SE(3) alignment
    does not remove a constant lever arm between camera and body.

    Returns:
        A JSON-ready dict: ``align``, ``n_gt``, ``n_est``, ``n_matched``, ``ate_rmse``, ``ate_mean``,
        ``ate_median``, ``ate_max`` (m), ``scale`` (the Sim(3) scale; 1 otherwise), ``recall@<thr>``
        per threshold (fraction), ``alignment`` ((4, 4) Sim(3) matrix as nested lists, mapping the
        estimate into the ground-truth frame) and, with ``rpe_delta``, ``rpe_delta``, ``rpe_unit``,
        ``rpe_pairs``, ``rpe_trans_{rmse,mean,median,max}`` (m), ``rpe_rot_{rmse,mean,median,max}`` (deg).

    Raises:
        ValueError: too few associated poses for the alignment (the message says how many were found
            and suggests ``max_diff_s``), or an unknown mode.
    """
    pairs = align_estimate(gt, est, align, max_diff_s)
    i_gt, i_est, alignment = pairs.i_gt, pairs.i_est, pairs.alignment

    result: dict = {"align": align, "n_gt": len(gt), "n_est": len(est), "n_matched": int(len(i_gt))}
    result.update({f"ate_{name}": value for name, value in error_statistics(pairs.errors).items()})
    result["scale"] = float(alignment.scale)
    for threshold, fraction in recall(pairs.errors, i_gt, len(gt), thresholds).items():
        result[recall_key(threshold)] = fraction
    result["alignment"] = alignment.matrix().tolist()
    if rpe_delta is not None:
        gt_poses = gt.matrices()[i_gt]
        est_poses = alignment.apply_poses(est.matrices()[i_est])
        stats = rpe(gt_poses, est_poses, gt.t_ns[i_gt], rpe_delta, rpe_unit)
        result.update({"rpe_delta": float(rpe_delta), "rpe_unit": rpe_unit})
        result.update({f"rpe_{name}": value for name, value in stats.items()})
    return result
