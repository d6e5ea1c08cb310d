"""Compiled CPU projection, binning and tile compositing (numba) of :class:`~vigs_core.mapping.rasterizer.
TorchRasterizer`, the compositing with 3DGS's early stop (Kerbl et al. 2023, Sec. 6).

Projection (:class:`ProjectGaussians`): :func:`~vigs_core.mapping.rasterizer.project_gaussians` and the conic in one
loop over the Gaussians, its backward the chain rule written out (float64 arithmetic: a few dozen operations per
Gaussian, where the tensor version paid the per-call overhead of about a hundred operations and their autograd).

Binning (:func:`bin_gaussians`) gives the reference's :class:`~vigs_core.mapping.rasterizer.TileBins` without its
sort of (tile, depth) pairs: the Gaussians are visited in depth order, so each tile's list fills front to back; a
candidate tile of a Gaussian's bounding box is kept where its 1/255 ellipse meets the rectangle of the tile's pixel
centres (the exact test of :func:`~vigs_core.mapping.rasterizer.ellipse_meets_tile`). The lists are flat, one after
the other (``TileBins.starts``), not a (tiles, busiest tile) table: a whole sequence's map has tiles with thousands.

Same model as the torch reference (:class:`~vigs_core.mapping.rasterizer._RasterizeTiles`): ``alpha = o
exp(power)``, ``power = -(1/2) d^T Q d``, cut below 1/255, ``w_k = alpha_k T_k``, features ``sum_k w_k f_k``
(RGB and depth), accumulated opacity ``1 - T_end``. A tile is composited slot by slot, front to back, each slot
over all the tile's pixels in one branch-free loop that LLVM vectorises (selects instead of branches, a polynomial
``exp``: a library call or a combined test stops the vectoriser). A pixel whose transmittance fell below
``T_STOP`` takes no further slot (the slot that takes it there is still composited, so its remaining weights sum
to less than ``T_STOP``: the images differ from the reference's by at most ``T_STOP`` times the largest feature);
a tile stops when all its pixels have.

Backward, back to front from the saved ``T_end`` and slot count per pixel (3DGS's order): ``T_k = T_{k+1} / (1 -
alpha_k)``, ``S_k = sum_{j>k} w_j g.f_j`` and ``dL/dpower_k = w_k g.f_k - r_k (S_k - h T_end)`` with ``r_k =
alpha_k / (1 - alpha_k)`` (the reference's formula); then ``dL/du = dL/dpower (a dx + b dy)``, ``dL/dv = dL/dpower
(b dx + c dy)``, ``dL/d(a, b, c) = -dL/dpower (dx^2/2, dx dy, dy^2/2)``, ``dL/do = dL/dpower / o`` and ``dL/df_k =
w_k g``, summed over the tile's pixels into the table rows. One thread; the interpreter lock is released while a
kernel runs (``nogil``), so a tracking thread beside the mapper keeps running.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from vigs_core.mapping.rasterizer import ALPHA_MIN, TileBins, ray_limits

T_STOP = 1e-4
EXP_FLOOR = 20.0
# the kernels compute in float32 (the map's dtype): twice the lanes of float64 in the vectorised pixel loops.
# Their constants are float32 scalars, as a Python float literal would promote the arithmetic to float64.
_F = np.float32
_0, _1, _HALF, _INV64 = _F(0.0), _F(1.0), _F(0.5), _F(1.0 / 64.0)
_C2, _C3, _C4, _C5 = _F(1.0 / 2.0), _F(1.0 / 6.0), _F(1.0 / 24.0), _F(1.0 / 120.0)
_ALPHA_MIN, _T_STOP, _EXP_FLOOR = _F(ALPHA_MIN), _F(T_STOP), _F(-EXP_FLOOR)


@njit(cache=True, fastmath=True, inline="always")
def _exp_neg(x):
    """``exp(x)`` for ``x <= 0`` without a library call, so the pixel loops vectorise: a degree-5 Taylor
    polynomial of ``exp(x / 64)`` squared six times (relative error within float32 rounding for ``x >= -6``,
    which covers every ``alpha`` the 1/255 cut keeps, ``o <= 0.99``); ``x`` is clamped at ``-EXP_FLOOR``."""
    y = max(x, _EXP_FLOOR) * _INV64
    e = _1 + y * (_1 + y * (_C2 + y * (_C3 + y * (_C4 + y * _C5))))
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _forward(table, index, starts, counts, tiles, n_tx, ts, width, height, color, depth, t_end, n_used):
    P = ts * ts
    gx, gy = np.empty(P, _F), np.empty(P, _F)  # tile-local pixel centres
    T, used = np.empty(P, _F), np.empty(P, _F)
    acc0, acc1, acc2, acc3 = np.empty(P, _F), np.empty(P, _F), np.empty(P, _F), np.empty(P, _F)
    for p in range(P):
        gx[p], gy[p] = p % ts, p // ts
    for t in range(tiles.shape[0]):
        ox, oy = (tiles[t] % n_tx) * ts, (tiles[t] // n_tx) * ts
        for p in range(P):  # pixels beyond the image start done (T = 0)
            T[p] = _1 if ox + p % ts < width and oy + p // ts < height else _0
            used[p] = acc0[p] = acc1[p] = acc2[p] = acc3[p] = _0
        for k in range(counts[t]):
            row = index[starts[t] + k]
            u, v = table[row, 0] - _F(ox), table[row, 1] - _F(oy)
            a, b, c, o = table[row, 2], table[row, 3], table[row, 4], table[row, 5]
            f0, f1, f2, f3 = table[row, 6], table[row, 7], table[row, 8], table[row, 9]
            slot = _F(k + 1)
            live = _0
            for p in range(P):  # branch-free: vectorised over the tile's pixels
                dx, dy = gx[p] - u, gy[p] - v
                alpha = o * _exp_neg(-_HALF * (a * dx * dx + c * dy * dy) - b * dx * dy)
                alpha = alpha if alpha >= _ALPHA_MIN else _0  # two selects: a combined test stops vectorisation
                alpha = alpha if T[p] >= _T_STOP else _0
                w = alpha * T[p]
                acc0[p] += w * f0
                acc1[p] += w * f1
                acc2[p] += w * f2
                acc3[p] += w * f3
                used[p] = slot if alpha > _0 else used[p]
                T[p] *= _1 - alpha
                live += T[p]
            if live < _T_STOP:  # every pixel of the tile is done
                break
        for p in range(P):
            px, py = ox + p % ts, oy + p // ts
            if px < width and py < height:
                color[py, px, 0], color[py, px, 1], color[py, px, 2] = acc0[p], acc1[p], acc2[p]
                depth[py, px] = acc3[p]
                t_end[py, px] = T[p]
                n_used[py, px] = int(used[p])


@njit(cache=True, fastmath=True, nogil=True, error_model="numpy")
def _backward(table, index, starts, counts, tiles, n_tx, ts, width, height, t_end, n_used, g_color, g_depth, g_alpha,
              d_table):
    P = ts * ts
    gx, gy = np.empty(P, _F), np.empty(P, _F)
    T, S, used, h = np.empty(P, _F), np.empty(P, _F), np.empty(P, _F), np.empty(P, _F)  # T_{k+1}, sum_{j>k} w g.f
    g0, g1, g2, g3 = np.empty(P, _F), np.empty(P, _F), np.empty(P, _F), np.empty(P, _F)  # dL/dfeatures
    for p in range(P):
        gx[p], gy[p] = p % ts, p // ts
    for t in range(tiles.shape[0]):
        ox, oy = (tiles[t] % n_tx) * ts, (tiles[t] // n_tx) * ts
        last = 0
        for p in range(P):
            px, py = ox + p % ts, oy + p // ts
            inside = px < width and py < height
            T[p] = t_end[py, px] if inside else _1
            used[p] = n_used[py, px] if inside else _0
            h[p] = g_alpha[py, px] * t_end[py, px] if inside else _0
            S[p] = _0
            g0[p] = g_color[py, px, 0] if inside else _0
            g1[p] = g_color[py, px, 1] if inside else _0
            g2[p] = g_color[py, px, 2] if inside else _0
            g3[p] = g_depth[py, px] if inside else _0
            last = max(last, int(used[p]))
        for k in range(last - 1, -1, -1):
            row = index[starts[t] + k]
            u, v = table[row, 0] - _F(ox), table[row, 1] - _F(oy)
            a, b, c, o = table[row, 2], table[row, 3], table[row, 4], table[row, 5]
            f0, f1, f2, f3 = table[row, 6], table[row, 7], table[row, 8], table[row, 9]
            slot = _F(k)
            du = dv = da = db = dc = do = d0 = d1 = d2 = d3 = _0
            for p in range(P):
                dx, dy = gx[p] - u, gy[p] - v
                alpha = o * _exp_neg(-_HALF * (a * dx * dx + c * dy * dy) - b * dx * dy)
                alpha = alpha if alpha >= _ALPHA_MIN else _0
                alpha = alpha if slot < used[p] else _0
                inv = _1 / (_1 - alpha)
                Tk = T[p] * inv
                w = alpha * Tk
                gf = g0[p] * f0 + g1[p] * f1 + g2[p] * f2 + g3[p] * f3
                d_power = w * gf - alpha * inv * (S[p] - h[p])
                S[p] += w * gf
                T[p] = Tk
                d0 += w * g0[p]
                d1 += w * g1[p]
                d2 += w * g2[p]
                d3 += w * g3[p]
                du += d_power * (a * dx + b * dy)
                dv += d_power * (b * dx + c * dy)
                da += d_power * dx * dx
                db += d_power * dx * dy
                dc += d_power * dy * dy
                do += d_power
            d_table[row, 0] += du
            d_table[row, 1] += dv
            d_table[row, 2] -= _HALF * da
            d_table[row, 3] -= db
            d_table[row, 4] -= _HALF * dc
            d_table[row, 5] += do / o
            d_table[row, 6] += d0
            d_table[row, 7] += d1
            d_table[row, 8] += d2
            d_table[row, 9] += d3


@njit(cache=True, nogil=True, inline="always")
def _meets(mx, my, a, b, c, r, x0, y0, x1, y1):
    """Scalar :func:`~vigs_core.mapping.rasterizer.ellipse_meets_tile`: the minimum of ``d^T Q d`` over the
    rectangle ``[x0, x1] x [y0, y1]`` (``d`` from the mean) is at most ``r``."""
    lx, ly, hx, hy = x0 - mx, y0 - my, x1 - mx, y1 - my
    dx = max(lx, 0.0) + min(hx, 0.0)
    dy = max(ly, 0.0) + min(hy, 0.0)
    dy_x = min(max(-b * dx / c, ly), hy)
    dx_y = min(max(-b * dy / a, lx), hx)
    f_x = (a * dx + 2.0 * b * dy_x) * dx + c * dy_x * dy_x
    f_y = (a * dx_y + 2.0 * b * dy) * dx_y + c * dy * dy
    return min(f_x, f_y) <= r


@njit(cache=True, nogil=True)
def _bin(mean2d, half, conic, reach, order, ts, n_tx, n_ty, width, height, max_per_tile):
    """Per tile the rows of the Gaussians that meet it, front to back (``order``), the first ``max_per_tile``, in
    one flat list (tile by tile): ``(counts (n_tx n_ty,), starts (n_tx n_ty,), index (sum of counts,), binned
    (N,))``, tile ``t``'s rows ``index[starts[t] : starts[t] + counts[t]]``. The pairs are collected in depth
    order, then placed by a counting sort on the tile, which keeps that order within each tile."""
    n = mean2d.shape[0]
    box = np.empty((n, 4), np.int64)
    bound = 0
    for g in range(n):
        mx, my = mean2d[g, 0], mean2d[g, 1]
        box[g, 0] = min(max(int(np.floor((mx - half[g, 0] + 0.5) / ts)), 0), n_tx - 1)
        box[g, 1] = min(max(int(np.floor((mx + half[g, 0] + 0.5) / ts)), 0), n_tx - 1)
        box[g, 2] = min(max(int(np.floor((my - half[g, 1] + 0.5) / ts)), 0), n_ty - 1)
        box[g, 3] = min(max(int(np.floor((my + half[g, 1] + 0.5) / ts)), 0), n_ty - 1)
        bound += (box[g, 1] - box[g, 0] + 1) * (box[g, 3] - box[g, 2] + 1)
    pair_tile, pair_row = np.empty(bound, np.int64), np.empty(bound, np.int64)
    counts = np.zeros(n_tx * n_ty, np.int64)
    binned = np.zeros(n, np.bool_)
    m = 0
    for g in order:
        mx, my = mean2d[g, 0], mean2d[g, 1]
        for ty in range(box[g, 2], box[g, 3] + 1):
            for tx in range(box[g, 0], box[g, 1] + 1):
                x0, y0 = tx * ts, ty * ts
                if not _meets(mx, my, conic[g, 0], conic[g, 1], conic[g, 2], reach[g], x0, y0,
                              min(x0 + ts - 1, width - 1), min(y0 + ts - 1, height - 1)):
                    continue
                tile = ty * n_tx + tx
                binned[g] = True
                if counts[tile] < max_per_tile:
                    pair_tile[m], pair_row[m] = tile, g
                    counts[tile] += 1
                    m += 1
    starts = np.zeros(n_tx * n_ty, np.int64)
    starts[1:] = np.cumsum(counts)[:-1]
    fill = starts.copy()
    index = np.empty(m, np.int64)
    for i in range(m):
        index[fill[pair_tile[i]]] = pair_row[i]
        fill[pair_tile[i]] += 1
    return counts, starts, index, binned


def bin_gaussians(mean2d, half_extent, depth, conic, reach, n_tx: int, n_ty: int, ts: int, width: int, height: int,
                  max_per_tile: int) -> TileBins:
    """:func:`~vigs_core.mapping.rasterizer.bin_gaussians` with the ellipse test, compiled (CPU tensors, no
    gradient): the same tiles, each's front-most ``max_per_tile`` Gaussians ordered by ``depth`` (rounded to
    float32, the kernels' precision; equal depths by row), in the flat layout (``TileBins.starts``): its size
    follows the tile-Gaussian pairs, not the busiest tile times the tiles, so a high ``max_per_tile`` costs only
    the Gaussians composited."""
    arrays = [t.detach().contiguous().numpy() for t in (mean2d, half_extent, conic, reach)]
    order = depth_order(depth.detach().to(torch.float32).numpy())
    counts, starts, index, binned = _bin(*arrays, order, ts, n_tx, n_ty, width, height, max_per_tile)
    tiles = np.flatnonzero(counts)
    tiles = tiles[np.argsort(-counts[tiles], kind="stable")]
    return TileBins(torch.from_numpy(tiles), torch.from_numpy(index), torch.from_numpy(counts[tiles]),
                    torch.from_numpy(binned), torch.from_numpy(starts[tiles]))


def depth_order(depth: np.ndarray) -> np.ndarray:
    """``np.argsort(depth, kind="stable")`` of a float32 array without NaN (ties in index order) as one sort of
    64-bit keys: the depth's bits made order-preserving as unsigned integers (the sign bit flipped, all bits of a
    negative number; ``-0.0`` made ``0.0`` first) above the index. numpy sorts such keys with SIMD, several times
    faster than a stable argsort of the floats (a mapping step sorts its visible Gaussians once)."""
    bits = (depth + np.float32(0.0)).view(np.uint32)
    flip = np.where(bits >> np.uint32(31), np.uint32(0xFFFFFFFF), np.uint32(0x80000000))
    keys = ((bits ^ flip).astype(np.uint64) << np.uint64(32)) | np.arange(depth.shape[0], dtype=np.uint64)
    return (np.sort(keys) & np.uint64(0xFFFFFFFF)).astype(np.int64)


@njit(cache=True, nogil=True)
def _in_frustum(means, scales, R, t, intr, lim, near, reach, sqrt_eps, width, height, keep):
    """:func:`~vigs_core.mapping.rasterizer.frustum_rows`'s test, one pass per Gaussian into ``keep`` (N,)."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    for i in range(means.shape[0]):
        x, y, z_cam = _camera_point(R, t, means[i])
        z = max(z_cam, 1e-9)
        tx, ty = x / z, y / z
        u, v = fx * tx + cx, fy * ty + cy
        tx, ty = min(max(tx, lim[0]), lim[1]), min(max(ty, lim[2]), lim[3])
        jac = math.sqrt(fx * fx * (1.0 + tx * tx) + fy * fy * (1.0 + ty * ty)) / z
        r = reach * (max(scales[i, 0], scales[i, 1], scales[i, 2]) * jac + sqrt_eps)
        keep[i] = (z_cam > near and u + r >= -0.5 and u - r <= width - 0.5
                   and v + r >= -0.5 and v - r <= height - 0.5)


def frustum_rows(means, scales, T_CW, camera, near: float, eps2d: float) -> torch.Tensor:
    """:func:`~vigs_core.mapping.rasterizer.frustum_rows` compiled (CPU tensors): one pass in float64 instead of a
    dozen whole-map tensor operations, which cost a mapping step about 2-3 ms on a whole sequence's map."""
    T = T_CW.detach().to(torch.float64).numpy()
    keep = np.empty(means.shape[0], np.bool_)
    _in_frustum(means.detach().contiguous().numpy(), scales.detach().contiguous().numpy(), T[:3, :3].copy(),
                T[:3, 3].copy(), np.array([camera.fx, camera.fy, camera.cx, camera.cy]),
                np.array(ray_limits(camera)), near, math.sqrt(2.0 * math.log(255.0)), math.sqrt(eps2d),
                camera.width, camera.height, keep)
    return torch.from_numpy(np.flatnonzero(keep))


@njit(cache=True, nogil=True, inline="always")
def _rays(x, y, z, lim):
    """``x/z``, ``y/z`` clamped to ``lim`` (4,) (:func:`~vigs_core.mapping.rasterizer.ray_limits`) and
    whether each lies inside its bounds (its derivative passes)."""
    tx, ty = x / z, y / z
    in_x, in_y = lim[0] <= tx <= lim[1], lim[2] <= ty <= lim[3]
    return min(max(tx, lim[0]), lim[1]), min(max(ty, lim[2]), lim[3]), in_x, in_y


@njit(cache=True, nogil=True, inline="always")
def _camera_point(R, t, mu):
    """``R mu + t``: the camera-frame point."""
    return (R[0, 0] * mu[0] + R[0, 1] * mu[1] + R[0, 2] * mu[2] + t[0],
            R[1, 0] * mu[0] + R[1, 1] * mu[1] + R[1, 2] * mu[2] + t[1],
            R[2, 0] * mu[0] + R[2, 1] * mu[1] + R[2, 2] * mu[2] + t[2])


@njit(cache=True, nogil=True, inline="always")
def _quat_matrix(q, Q):
    """:func:`~vigs_core.geometry.quat_to_matrix` of one quaternion ``(w, x, y, z)`` (normalised here too) into
    ``Q`` (3, 3)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    Q[0, 0], Q[0, 1], Q[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    Q[1, 0], Q[1, 1], Q[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    Q[2, 0], Q[2, 1], Q[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)


@njit(cache=True, nogil=True, inline="always")
def _footprint_rows(R, Q, s, fx, fy, iz, tx, ty, RQ, m0, m1):
    """``RQ = R Q`` and the rows ``m0``, ``m1`` of ``M = J R Q diag(s)`` (``Sigma' = M M^T``), into the arrays."""
    for r in range(3):
        for c in range(3):
            RQ[r, c] = R[r, 0] * Q[0, c] + R[r, 1] * Q[1, c] + R[r, 2] * Q[2, c]
    for c in range(3):
        m0[c] = fx * iz * (RQ[0, c] - tx * RQ[2, c]) * s[c]
        m1[c] = fy * iz * (RQ[1, c] - ty * RQ[2, c]) * s[c]


@njit(cache=True, nogil=True)
def _project(means, quats, scales, R, t, intr, lim, eps2d, mean2d, conic, depth, cov2d):
    """Forward of :class:`ProjectGaussians` (float64 arithmetic), into the output arrays."""
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    Q, RQ, m0, m1 = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(3)
    for i in range(means.shape[0]):
        x, y, z = _camera_point(R, t, means[i])
        iz = 1.0 / z
        mean2d[i, 0], mean2d[i, 1], depth[i] = fx * x * iz + cx, fy * y * iz + cy, z
        tx, ty, _, _ = _rays(x, y, z, lim)
        _quat_matrix(quats[i], Q)
        _footprint_rows(R, Q, scales[i], fx, fy, iz, tx, ty, RQ, m0, m1)
        c00 = m0[0] * m0[0] + m0[1] * m0[1] + m0[2] * m0[2] + eps2d
        c01 = m0[0] * m1[0] + m0[1] * m1[1] + m0[2] * m1[2]
        c11 = m1[0] * m1[0] + m1[1] * m1[1] + m1[2] * m1[2] + eps2d
        det = max(c00 * c11 - c01 * c01, 1e-12)
        conic[i, 0], conic[i, 1], conic[i, 2] = c11 / det, -c01 / det, c00 / det
        cov2d[i, 0], cov2d[i, 1], cov2d[i, 2] = c00, c01, c11


@njit(cache=True, nogil=True)
def _project_backward(means, quats, scales, R, t, intr, lim, cov2d, g_mean2d, g_conic, g_depth,
                      d_means, d_quats, d_scales):
    """Backward of :class:`ProjectGaussians`: the chain rule of :func:`_project` in reverse (float64)."""
    fx, fy = intr[0], intr[1]
    Q, RQ, m0, m1 = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(3)
    dW, dQ, dm0, dm1 = np.empty((3, 3)), np.empty((3, 3)), np.empty(3), np.empty(3)
    for i in range(means.shape[0]):
        x, y, z = _camera_point(R, t, means[i])
        iz = 1.0 / z
        tx, ty, in_x, in_y = _rays(x, y, z, lim)
        _quat_matrix(quats[i], Q)
        s = scales[i]
        _footprint_rows(R, Q, s, fx, fy, iz, tx, ty, RQ, m0, m1)
        c00, c01, c11 = cov2d[i, 0], cov2d[i, 1], cov2d[i, 2]
        D = max(c00 * c11 - c01 * c01, 1e-12)
        D2 = D * D
        ga, gb, gc = g_conic[i, 0], g_conic[i, 1], g_conic[i, 2]
        # conic = (c11, -c01, c00) / D  ->  gradients of the covariance entries
        g00 = -ga * c11 * c11 / D2 + gb * c01 * c11 / D2 + gc * (1.0 / D - c00 * c11 / D2)
        g11 = ga * (1.0 / D - c11 * c00 / D2) + gb * c01 * c00 / D2 - gc * c00 * c00 / D2
        g01 = 2.0 * ga * c01 * c11 / D2 + gb * (-1.0 / D - 2.0 * c01 * c01 / D2) + 2.0 * gc * c01 * c00 / D2
        for c in range(3):
            dm0[c] = 2.0 * g00 * m0[c] + g01 * m1[c]
            dm1[c] = 2.0 * g11 * m1[c] + g01 * m0[c]
        # M = J W with W = R Q diag(s): dJ = dM W^T (entries J00, J02, J11, J12), dW = J^T dM
        dJ00 = dJ02 = dJ11 = dJ12 = 0.0
        for c in range(3):
            dJ00 += dm0[c] * RQ[0, c] * s[c]
            dJ02 += dm0[c] * RQ[2, c] * s[c]
            dJ11 += dm1[c] * RQ[1, c] * s[c]
            dJ12 += dm1[c] * RQ[2, c] * s[c]
            dW[0, c] = fx * iz * dm0[c]
            dW[1, c] = fy * iz * dm1[c]
            dW[2, c] = -fx * tx * iz * dm0[c] - fy * ty * iz * dm1[c]
        for c in range(3):
            d_scales[i, c] = dW[0, c] * RQ[0, c] + dW[1, c] * RQ[1, c] + dW[2, c] * RQ[2, c]
            for r in range(3):
                dQ[r, c] = (R[0, r] * dW[0, c] + R[1, r] * dW[1, c] + R[2, r] * dW[2, c]) * s[c]
        _quat_matrix_backward(quats[i], dQ, d_quats[i])
        # the camera-frame point: mean2d, depth and J (through 1/z and the clamped rays)
        dtx_dx, dtx_dz = (iz, -x * iz * iz) if in_x else (0.0, 0.0)
        dty_dy, dty_dz = (iz, -y * iz * iz) if in_y else (0.0, 0.0)
        dp0 = g_mean2d[i, 0] * fx * iz - dJ02 * fx * iz * dtx_dx
        dp1 = g_mean2d[i, 1] * fy * iz - dJ12 * fy * iz * dty_dy
        dp2 = (-g_mean2d[i, 0] * fx * x * iz * iz - g_mean2d[i, 1] * fy * y * iz * iz + g_depth[i]
               - dJ00 * fx * iz * iz - dJ11 * fy * iz * iz
               - dJ02 * fx * (dtx_dz * iz - tx * iz * iz) - dJ12 * fy * (dty_dz * iz - ty * iz * iz))
        for c in range(3):
            d_means[i, c] = R[0, c] * dp0 + R[1, c] * dp1 + R[2, c] * dp2


@njit(cache=True, nogil=True, inline="always")
def _quat_matrix_backward(q, G, out):
    """Gradient ``out`` (4,) of ``sum(G * quat_to_matrix(q))`` with respect to ``q`` (through the normalisation)."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    w, x, y, z = q[0] / n, q[1] / n, q[2] / n, q[3] / n
    dw = 2.0 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
    dx = 2.0 * (y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2 * x * G[1, 1] - w * G[1, 2] + z * G[2, 0]
                + w * G[2, 1] - 2 * x * G[2, 2])
    dy = 2.0 * (-2 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2] - w * G[2, 0]
                + z * G[2, 1] - 2 * y * G[2, 2])
    dz = 2.0 * (-2 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2 * z * G[1, 1] + y * G[1, 2]
                + x * G[2, 0] + y * G[2, 1])
    dot = w * dw + x * dx + y * dy + z * dz  # d(q / |q|) / dq = (I - u u^T) / |q|
    out[0], out[1], out[2], out[3] = (dw - w * dot) / n, (dx - x * dot) / n, (dy - y * dot) / n, (dz - z * dot) / n


class ProjectGaussians(torch.autograd.Function):
    """:func:`~vigs_core.mapping.rasterizer.project_gaussians` fused with the conic: ``(mean2d (N, 2), conic (N, 3)
    (a, b, c) of ``cov2d^-1``, depth (N,), cov2d (N, 3) without gradient)`` of ``means``, ``quats`` (normalised
    here), ``scales`` (N, 3) seen by ``T_CW`` (4, 4) through ``camera`` (a ``RenderCamera``), ``eps2d`` px^2 added.
    One compiled loop per Gaussian forward and backward (float64 arithmetic) in place of about a hundred tensor
    operations; the backward is the chain rule of EWA splatting (3DGS Eq. 5) through the clamped rays."""

    @staticmethod
    def forward(ctx, means, quats, scales, T_CW, camera, eps2d):
        f64 = [x.detach().to(torch.float64).contiguous().numpy() for x in (means, quats, scales)]
        T = T_CW.detach().to(torch.float64).numpy()
        R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
        intr = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
        lim = np.array(ray_limits(camera))
        n = means.shape[0]
        mean2d, conic, depth, cov2d = np.empty((n, 2)), np.empty((n, 3)), np.empty(n), np.empty((n, 3))
        _project(*f64, R, t, intr, lim, float(eps2d), mean2d, conic, depth, cov2d)
        ctx.kernel_args = (*f64, R, t, intr, lim, cov2d)
        ctx.dtype = means.dtype
        out = [torch.from_numpy(a).to(means.dtype) for a in (mean2d, conic, depth, cov2d)]
        ctx.mark_non_differentiable(out[3])
        return tuple(out)

    @staticmethod
    def backward(ctx, g_mean2d, g_conic, g_depth, _g_cov2d):
        means = ctx.kernel_args[0]
        n = means.shape[0]
        grads = [np.zeros((n, 2)) if g_mean2d is None else g_mean2d.to(torch.float64).contiguous().numpy(),
                 np.zeros((n, 3)) if g_conic is None else g_conic.to(torch.float64).contiguous().numpy(),
                 np.zeros(n) if g_depth is None else g_depth.to(torch.float64).contiguous().numpy()]
        d_means, d_quats, d_scales = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
        _project_backward(*ctx.kernel_args, *grads, d_means, d_quats, d_scales)
        out = [torch.from_numpy(a).to(ctx.dtype) for a in (d_means, d_quats, d_scales)]
        return (*out, None, None, None)


class CompositeTiles(torch.autograd.Function):
    """``(color (H, W, 3), depth (H, W), alpha (H, W))`` of the table ``(N, 10)`` rows ``[u, v, a, b, c, o, red,
    green, blue, z]`` (mean, conic, opacity, colour, depth) composited over the tiles of a
    :class:`~vigs_core.mapping.rasterizer.TileBins` (``tiles``, ``index``, ``counts``, ``starts``:
    :func:`bin_gaussians`'s flat lists); ``n_tx`` tiles of ``ts`` pixels per row, a ``width x height`` image. CPU
    tensors; computed in float32, returned in the table's dtype. Colour and depth come as separate tensors, so
    their gradients reach the kernel without a slice's backward."""

    @staticmethod
    def forward(ctx, table, bins, n_tx, ts, width, height):
        if table.shape[1] != 10:
            raise ValueError(f"compiled compositing takes 4 features per Gaussian, got {table.shape[1] - 6}")
        tab = table.detach().to(torch.float32).contiguous().numpy()
        index, starts, counts, tiles = (v.contiguous().numpy() for v in (bins.index, bins.starts, bins.counts,
                                                                         bins.tiles))
        color = np.zeros((height, width, 3), np.float32)
        depth = np.zeros((height, width), np.float32)
        t_end = np.ones((height, width), np.float32)
        n_used = np.zeros((height, width), np.int64)
        _forward(tab, index, starts, counts, tiles, n_tx, ts, width, height, color, depth, t_end, n_used)
        if ctx.needs_input_grad[0]:
            ctx.kernel_args = (tab, index, starts, counts, tiles, n_tx, ts, width, height, t_end, n_used)
        ctx.dtype, ctx.size = table.dtype, (height, width)
        return tuple(torch.from_numpy(a).to(table.dtype) for a in (color, depth, 1.0 - t_end))

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        height, width = ctx.size
        grads = [np.zeros(shape, np.float32) if g is None else g.detach().to(torch.float32).contiguous().numpy()
                 for g, shape in ((g_color, (height, width, 3)), (g_depth, (height, width)),
                                  (g_alpha, (height, width)))]
        d_table = np.zeros_like(ctx.kernel_args[0])
        _backward(*ctx.kernel_args, *grads, d_table)
        return torch.from_numpy(d_table).to(ctx.dtype), None, None, None, None, None
