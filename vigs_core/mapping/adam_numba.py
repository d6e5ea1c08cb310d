"""Compiled CPU Adam step over selected rows (numba) for :class:`~vigs_core.mapping.optimizer.RowAdam`: the same
update, fused per row over all parameter tensors, where the torch version gathers and scatters each moment and
parameter (about ten tensor operations per parameter, whose per-call overhead dominated at the mapper's tens of
thousands of rows)."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, fastmath=True)
def adam_rows(ps, ms, vs, gs, lrs, t, rows, b1, b2, eps):
    """Adam (Kingma and Ba 2015, Alg. 1) on rows ``rows`` (M,) of each parameter ``ps[j]`` and its moments
    ``ms[j]``, ``vs[j]`` (N, C_j), in place, with the gradients ``gs[j]`` (M, C_j), learning rates ``lrs`` and the
    rows' step counts ``t`` (N,) (already incremented, so at least 1). The bias corrections ``1 / (1 - b^k)`` are
    tabulated once for the step counts present (not two powers per row and tensor); float64 arithmetic."""
    t_max = 1
    for i in range(rows.shape[0]):
        t_max = max(t_max, t[rows[i]])
    inv_c1, inv_c2 = np.empty(t_max + 1), np.empty(t_max + 1)
    for k in range(1, t_max + 1):
        inv_c1[k] = 1.0 / (1.0 - b1**k)
        inv_c2[k] = 1.0 / (1.0 - b2**k)
    for i in range(rows.shape[0]):
        r = rows[i]
        k1, k2 = inv_c1[t[r]], inv_c2[t[r]]
        for j in range(len(ps)):
            p, m, v, g, lr = ps[j], ms[j], vs[j], gs[j], lrs[j]
            for c in range(p.shape[1]):
                gi = g[i, c]
                mi = b1 * m[r, c] + (1.0 - b1) * gi
                vi = b2 * v[r, c] + (1.0 - b2) * gi * gi
                m[r, c] = mi
                v[r, c] = vi
                p[r, c] -= lr * (mi * k1) / (math.sqrt(vi * k2) + eps)
