"""Pairing poses of two trajectories by time stamp."""
from __future__ import annotations

import numpy as np


def associate(
    t_ref_ns: np.ndarray, t_est_ns: np.ndarray, max_diff_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """Pair stamps of two sequences by nearest time, within ``max_diff_ns``.

    Every stamp of the sequence with fewer stamps (the estimate when both have as many) looks up the
    nearest stamp of the other sequence (ties go to the earlier stamp) and is paired with it if
    ``|dt| <= max_diff_ns``; this keeps every pose of the sparser trajectory that has a partner (the
    rule evo's ``associate_trajectories`` uses). Stamps are compared as exact integers.

    Args:
        t_ref_ns: (N,) int64 reference stamps (ns), in any order.
        t_est_ns: (M,) int64 estimate stamps (ns), in any order.
        max_diff_ns: largest accepted ``|t_ref - t_est|`` (ns), >= 0.

    Returns:
        ``(i_ref, i_est)``: (K,) int64 index arrays into the inputs, ordered by the sparser sequence's
        stamps; ``t_ref_ns[i_ref[k]]`` and ``t_est_ns[i_est[k]]`` are the k-th pair.
    """
    t_ref_ns = np.asarray(t_ref_ns, dtype=np.int64)
    t_est_ns = np.asarray(t_est_ns, dtype=np.int64)
    if max_diff_ns < 0:
        raise ValueError(f"associate: max_diff_ns must be >= 0, got {max_diff_ns}")
    if len(t_ref_ns) == 0 or len(t_est_ns) == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    ref_is_dense = len(t_ref_ns) >= len(t_est_ns)
    sparse, dense = (t_est_ns, t_ref_ns) if ref_is_dense else (t_ref_ns, t_est_ns)

    sparse_order = np.argsort(sparse, kind="stable")
    dense_order = np.argsort(dense, kind="stable")
    dense_sorted = dense[dense_order]
    query = sparse[sparse_order]
    # Candidates: the last dense stamp <= query and the first one > query.
    after = np.searchsorted(dense_sorted, query, side="right")
    before = np.clip(after - 1, 0, len(dense_sorted) - 1)
    after = np.clip(after, 0, len(dense_sorted) - 1)
    diff_before = np.abs(query - dense_sorted[before])
    diff_after = np.abs(dense_sorted[after] - query)
    nearest = np.where(diff_after < diff_before, after, before)
    diff = np.minimum(diff_before, diff_after)
    keep = diff <= max_diff_ns

    i_sparse = sparse_order[keep]
    i_dense = dense_order[nearest[keep]]
    return (i_dense, i_sparse) if ref_is_dense else (i_sparse, i_dense)
