"""Compiled CPU Adam step over selected rows (numba) for :class:`~vigs_core.mapping.optimizer.RowAdam`: the same
update, fused per row, where the torch version gathers and scatters each moment and parameter (about ten tensor
operations per parameter, whose per-call overhead dominated at the mapper's tens of thousands of rows)."""
from __future__ import annotations

import math

from numba import njit


@njit(cache=True, nogil=True)
def adam_rows(p, m, v, t, rows, g, lr, b1, b2, eps):
    """Adam (Kingma and Ba 2015, Alg. 1) on rows ``rows`` (M,) of ``p``, ``m``, ``v`` (N, C), in place, with the
    gradients ``g`` (M, C) and the rows' step counts ``t`` (N,) (already incremented)."""
    for i in range(rows.shape[0]):
        r = rows[i]
        c1 = 1.0 - b1 ** t[r]
        c2 = 1.0 - b2 ** t[r]
        for c in range(p.shape[1]):
            gi = g[i, c]
            mi = b1 * m[r, c] + (1.0 - b1) * gi
            vi = b2 * v[r, c] + (1.0 - b2) * gi * gi
            m[r, c] = mi
            v[r, c] = vi
            p[r, c] -= lr * (mi / c1) / (math.sqrt(vi / c2) + eps)
