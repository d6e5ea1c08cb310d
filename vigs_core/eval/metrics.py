"""Trajectory error metrics on associated, aligned poses (float64 numpy).

* ATE, absolute trajectory error (Sturm et al., IROS 2012, sec. VI-A): ``e_i = ||p_gt,i - p'_est,i||``
  for aligned estimate positions ``p'``; statistics RMSE, mean, median, max (m).
* RPE, relative pose error (Sturm et al. 2012, sec. VI-B; Kuemmerle et al., Auton. Robots 2009):
  ``E_ij = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` for ground-truth poses Q and estimated poses P over pose pairs
  ``(i, j)`` a fixed distance or time apart; translation part ``||t(E_ij)||`` (m) and rotation angle
  of ``R(E_ij)`` (deg).
* Recall@threshold: the fraction of ground-truth poses whose aligned translation error is below the
  threshold; ground-truth poses without an associated estimate count as misses.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

RPE_UNITS = ("m", "s")
RPE_REL_TOL = 0.1


def translation_errors(gt_positions: np.ndarray, est_positions: np.ndarray) -> np.ndarray:
    """(N,) Euclidean distances (m) between associated (N, 3) ground-truth and aligned estimate positions."""
    gt_positions = np.asarray(gt_positions, dtype=np.float64)
    est_positions = np.asarray(est_positions, dtype=np.float64)
    if gt_positions.shape != est_positions.shape:
        raise ValueError(f"translation_errors: shapes differ: {gt_positions.shape} and {est_positions.shape}")
    return np.linalg.norm(gt_positions - est_positions, axis=-1)


def error_statistics(errors: np.ndarray) -> dict[str, float]:
    """``rmse``, ``mean``, ``median``, ``max`` of a non-empty (N,) error array."""
    errors = np.asarray(errors, dtype=np.float64)
    if errors.size == 0:
        raise ValueError("error_statistics: no errors to summarise (no associated poses)")
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "mean": float(np.mean(errors)),
        "median": float(np.median(errors)),
        "max": float(np.max(errors)),
    }


def ate(gt_positions: np.ndarray, est_positions: np.ndarray) -> dict[str, float]:
    """Absolute trajectory error statistics (m) of associated (N, 3) ground-truth and aligned estimate positions."""
    return error_statistics(translation_errors(gt_positions, est_positions))


def rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """(N,) rotation angles (rad) of (N, 3, 3) rotation matrices.

    ``angle = atan2(||vee(R - R^T)|| / 2, (tr R - 1) / 2)``: sine and cosine of the angle, which keeps
    full precision near 0 and near pi (unlike ``arccos`` of the trace).
    """
    r = np.asarray(rotations, dtype=np.float64)
    skew = np.stack((r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]), axis=-1)
    sin = 0.5 * np.linalg.norm(skew, axis=-1)
    cos = 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0)
    return np.arctan2(sin, cos)


def rpe_pairs(gt_positions: np.ndarray, t_ns: np.ndarray, delta: float, unit: str,
              rel_tol: float = RPE_REL_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Pose pairs ``(i, j)`` about ``delta`` apart along the ground truth: evo's all-pairs rule.

    The coordinate ``d`` is the cumulative ground-truth path length (``unit="m"``) or the time (``unit="s"``).
    Every pose ``i`` but the last starts a candidate pair (overlapping pairs); ``j > i`` minimises
    ``|(d_j - d_i) - delta|`` (the first such pose on ties) and the pair is kept when that is at most
    ``rel_tol * delta``. With ``unit="m"`` these are the pairs of ``evo_rpe --delta_unit m --all_pairs
    --pairs_from_reference`` (evo's ``filter_pairs_by_path``, relative tolerance 0.1 by default); evo has no time
    unit, the same rule is applied to time.

    Args:
        gt_positions: (N, 3) associated ground-truth positions (m), in time order.
        t_ns: (N,) int64 their stamps (ns).
        delta: pair spacing (> 0), metres or seconds.
        unit: ``"m"`` or ``"s"``.
        rel_tol: accepted deviation from ``delta``, as a fraction of it.

    Returns:
        ``(i, j)``: (K,) index arrays with ``i < j``.
    """
    if unit not in RPE_UNITS:
        raise ValueError(f"rpe: unit must be one of {', '.join(RPE_UNITS)}, got '{unit}'")
    if not delta > 0:
        raise ValueError(f"rpe: delta must be > 0, got {delta}")
    if unit == "m":
        steps = np.linalg.norm(np.diff(np.asarray(gt_positions, dtype=np.float64), axis=0), axis=1)
        d = np.concatenate(([0.0], np.cumsum(steps)))
    else:
        t_ns = np.asarray(t_ns, dtype=np.int64)
        d = (t_ns - t_ns[0]).astype(np.float64) * 1e-9
    n = len(d)
    i = np.arange(n - 1)
    if n < 2:
        return i, i
    # d is non-decreasing, so the nearest pose is next to the first one at or past d_i + delta: the candidates
    # around it, each moved to the first pose of its value (an argmin takes the first minimum), ascending
    first = np.searchsorted(d, d[i] + delta, side="left")
    near = np.clip(first[:, None] + np.arange(-1, 2), i[:, None] + 1, n - 1)
    near = np.maximum(np.searchsorted(d, d[near], side="left"), i[:, None] + 1)
    miss = np.abs((d[near] - d[i, None]) - delta)   # evo's expression
    pick = np.argmin(miss, axis=1)
    j = near[i, pick]
    keep = miss[i, pick] <= rel_tol * delta
    return i[keep], j[keep]


def rpe(
    gt_poses: np.ndarray, est_poses: np.ndarray, t_ns: np.ndarray, delta: float, unit: str = "m"
) -> dict[str, float]:
    """Relative pose error over pose pairs ``delta`` metres or seconds apart (see :func:`rpe_pairs`).

    Args:
        gt_poses: (N, 4, 4) ground-truth poses ``T_WB``, associated with ``est_poses`` and in time order.
        est_poses: (N, 4, 4) aligned estimated poses (scale applied for monocular estimates).
        t_ns: (N,) int64 stamps (ns) of the pairs.
        delta: pair spacing (> 0).
        unit: ``"m"`` (ground-truth path length) or ``"s"`` (time).

    Returns:
        ``pairs`` (count) and ``trans_{rmse,mean,median,max}`` (m), ``rot_{rmse,mean,median,max}`` (deg).

    Raises:
        ValueError: no pair fits (the trajectory is shorter than ``delta``).
    """
    gt_poses = np.asarray(gt_poses, dtype=np.float64)
    est_poses = np.asarray(est_poses, dtype=np.float64)
    i, j = rpe_pairs(gt_poses[:, :3, 3], t_ns, delta, unit)
    if len(i) == 0:
        raise ValueError(f"rpe: the associated trajectory is shorter than delta = {delta} {unit}; no pose pairs")
    gt_rel = np.linalg.inv(gt_poses[i]) @ gt_poses[j]
    est_rel = np.linalg.inv(est_poses[i]) @ est_poses[j]
    error = np.linalg.inv(gt_rel) @ est_rel
    out: dict[str, float] = {"pairs": int(len(i))}
    for name, value in error_statistics(np.linalg.norm(error[:, :3, 3], axis=1)).items():
        out[f"trans_{name}"] = value
    for name, value in error_statistics(np.degrees(rotation_angle(error[:, :3, :3]))).items():
        out[f"rot_{name}"] = value
    return out


def recall(
    errors: np.ndarray, gt_index: np.ndarray, n_gt: int, thresholds: Sequence[float]
) -> dict[float, float]:
    """Fraction of ground-truth poses whose aligned translation error is below each threshold.

    Args:
        errors: (K,) translation errors (m) of the associated pairs.
        gt_index: (K,) index of each pair's ground-truth pose (a pose paired twice counts once, with
            its smaller error).
        n_gt: number of ground-truth poses; those without a pair count as misses.
        thresholds: error thresholds (m).

    Returns:
        ``{threshold: fraction in [0, 1]}``.
    """
    if n_gt <= 0:
        raise ValueError(f"recall: n_gt must be > 0, got {n_gt}")
    best = np.full(n_gt, np.inf)
    np.minimum.at(best, np.asarray(gt_index, dtype=np.int64), np.asarray(errors, dtype=np.float64))
    return {float(thr): float(np.count_nonzero(best < thr) / n_gt) for thr in thresholds}
