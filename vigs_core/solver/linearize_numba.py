"""Compiled CPU linearisation (numba) of the dense visual terms, for :func:`vigs_core.solver.normal_equations.
linearize_visual`.

One loop over each edge's source pixels does what the tensor version spreads over about a hundred whole-array
operations: the projection of :func:`vigs_core.solver.projective.reproject` (``P = R (x, y, 1) + t d``, valid where
``Z > MIN_DEPTH_RATIO``, else projected with ``Z = 1`` and weight 0), the residual ``r = u* - pi``, the IRLS Huber
weight ``min(1, delta / |r|)`` times the pixel's confidences, the target-pose Jacobian ``J_j`` (2, 6, whose entries
(0, 1) and (1, 0) are zero) and the disparity Jacobian ``J_d`` (2,) in closed form. From them it sums the edge's
target block ``H_jj = sum J_j^T W J_j`` and gradient ``v_j = sum J_j^T W r`` (float64 scalars, reassociated), adds
each pixel's ``J_d^T W J_d`` and ``J_d^T W r`` to its source keyframe's ``C`` and ``w``, writes the coupling row
``E_j = J_j^T W J_d`` (6,) to the edge's E block and adds ``E_i = -E_j Ad`` to the source's own block, and sums the
robust cost ``conf rho(|r|)``. Per-pixel arithmetic is float64; the per-pixel outputs take the disparities' dtype.
The cost alone (the LM trial steps) has a loop of its own. The interpreter lock is released while they run
(``nogil``).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit

from vigs_core.solver.projective import MIN_DEPTH_RATIO, Intrinsics, pixel_rays


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _edge_terms(T_ji, Ad, disp, rays, target, conf, fx, fy, cx, cy, delta, src_row, slot, rank,
                H_jj, v_j, C, w, block_E, residual, valid, cost):
    n_edges, n_pix = disp.shape
    for e in range(n_edges):
        i, E_i, E_j = src_row[e], block_E[slot[e], 0], block_E[slot[e], rank[e] + 1]
        A = Ad[e]
        R00, R01, R02, t0 = T_ji[e, 0, 0], T_ji[e, 0, 1], T_ji[e, 0, 2], T_ji[e, 0, 3]
        R10, R11, R12, t1 = T_ji[e, 1, 0], T_ji[e, 1, 1], T_ji[e, 1, 2], T_ji[e, 1, 3]
        R20, R21, R22, t2 = T_ji[e, 2, 0], T_ji[e, 2, 1], T_ji[e, 2, 2], T_ji[e, 2, 3]
        h00 = h02 = h03 = h04 = h05 = h11 = h12 = h13 = h14 = h15 = 0.0
        h22 = h23 = h24 = h25 = h33 = h34 = h35 = h44 = h45 = h55 = 0.0
        g0 = g1 = g2 = g3 = g4 = g5 = 0.0
        c_sum = 0.0
        for p in range(n_pix):
            x, y, d = rays[p, 0], rays[p, 1], float(disp[e, p])
            X = R00 * x + R01 * y + R02 + t0 * d
            Y = R10 * x + R11 * y + R12 + t1 * d
            Z = R20 * x + R21 * y + R22 + t2 * d
            ok = Z > MIN_DEPTH_RATIO
            iz = 1.0 / (Z if ok else 1.0)
            xn, yn = X * iz, Y * iz
            r0 = target[e, p, 0] - (fx * xn + cx)
            r1 = target[e, p, 1] - (fy * yn + cy)
            residual[e, p, 0], residual[e, p, 1] = r0, r1
            valid[e, p] = ok
            rn = math.sqrt(r0 * r0 + r1 * r1)
            huber = min(1.0, delta / max(rn, 1e-12))
            c0, c1 = conf[e, p, 0], conf[e, p, 1]
            m = 1.0 if ok else 0.0
            W0, W1 = c0 * huber * m, c1 * huber * m
            rho = 0.5 * rn * rn if rn <= delta else delta * (rn - 0.5 * delta)
            c_sum += m * 0.5 * (c0 + c1) * rho
            fdz, gdz, xy = fx * d * iz, fy * d * iz, xn * yn
            a0, a2, a3, a4, a5 = fdz, -fdz * xn, -fx * xy, fx * (1 + xn * xn), -fx * yn
            b1, b2, b3, b4, b5 = gdz, -gdz * yn, -fy * (1 + yn * yn), fy * xy, fy * xn
            d0 = fx * iz * (t0 - xn * t2)
            d1 = fy * iz * (t1 - yn * t2)
            C[i, p] += W0 * d0 * d0 + W1 * d1 * d1
            w[i, p] += W0 * d0 * r0 + W1 * d1 * r1
            u0, u1 = W0 * a0, W1 * b1
            p2, q2 = W0 * a2, W1 * b2
            p3, q3 = W0 * a3, W1 * b3
            p4, q4 = W0 * a4, W1 * b4
            p5, q5 = W0 * a5, W1 * b5
            e0, e1, e2 = u0 * d0, u1 * d1, p2 * d0 + q2 * d1
            e3, e4, e5 = p3 * d0 + q3 * d1, p4 * d0 + q4 * d1, p5 * d0 + q5 * d1
            E_j[0, p], E_j[1, p], E_j[2, p], E_j[3, p], E_j[4, p], E_j[5, p] = e0, e1, e2, e3, e4, e5
            for k in range(6):
                E_i[k, p] -= (e0 * A[0, k] + e1 * A[1, k] + e2 * A[2, k] + e3 * A[3, k] + e4 * A[4, k]
                              + e5 * A[5, k])
            g0 += u0 * r0
            g1 += u1 * r1
            g2 += p2 * r0 + q2 * r1
            g3 += p3 * r0 + q3 * r1
            g4 += p4 * r0 + q4 * r1
            g5 += p5 * r0 + q5 * r1
            h00 += u0 * a0
            h02 += u0 * a2
            h03 += u0 * a3
            h04 += u0 * a4
            h05 += u0 * a5
            h11 += u1 * b1
            h12 += u1 * b2
            h13 += u1 * b3
            h14 += u1 * b4
            h15 += u1 * b5
            h22 += p2 * a2 + q2 * b2
            h23 += p2 * a3 + q2 * b3
            h24 += p2 * a4 + q2 * b4
            h25 += p2 * a5 + q2 * b5
            h33 += p3 * a3 + q3 * b3
            h34 += p3 * a4 + q3 * b4
            h35 += p3 * a5 + q3 * b5
            h44 += p4 * a4 + q4 * b4
            h45 += p4 * a5 + q4 * b5
            h55 += p5 * a5 + q5 * b5
        H = H_jj[e]
        H[0, 0], H[0, 1], H[0, 2], H[0, 3], H[0, 4], H[0, 5] = h00, 0.0, h02, h03, h04, h05
        H[1, 1], H[1, 2], H[1, 3], H[1, 4], H[1, 5] = h11, h12, h13, h14, h15
        H[2, 2], H[2, 3], H[2, 4], H[2, 5] = h22, h23, h24, h25
        H[3, 3], H[3, 4], H[3, 5] = h33, h34, h35
        H[4, 4], H[4, 5] = h44, h45
        H[5, 5] = h55
        for a in range(6):
            for b in range(a):
                H[a, b] = H[b, a]
        v_j[e, 0], v_j[e, 1], v_j[e, 2], v_j[e, 3], v_j[e, 4], v_j[e, 5] = g0, g1, g2, g3, g4, g5
        cost[e] = c_sum


@njit(cache=True, nogil=True, error_model="numpy", fastmath={"reassoc", "contract"})
def _edge_cost(T_ji, disp, rays, target, conf, fx, fy, cx, cy, delta):
    n_edges, n_pix = disp.shape
    total = 0.0
    for e in range(n_edges):
        R00, R01, R02, t0 = T_ji[e, 0, 0], T_ji[e, 0, 1], T_ji[e, 0, 2], T_ji[e, 0, 3]
        R10, R11, R12, t1 = T_ji[e, 1, 0], T_ji[e, 1, 1], T_ji[e, 1, 2], T_ji[e, 1, 3]
        R20, R21, R22, t2 = T_ji[e, 2, 0], T_ji[e, 2, 1], T_ji[e, 2, 2], T_ji[e, 2, 3]
        for p in range(n_pix):
            x, y, d = rays[p, 0], rays[p, 1], float(disp[e, p])
            Z = R20 * x + R21 * y + R22 + t2 * d
            if not Z > MIN_DEPTH_RATIO:
                continue
            iz = 1.0 / Z
            r0 = target[e, p, 0] - (fx * (R00 * x + R01 * y + R02 + t0 * d) * iz + cx)
            r1 = target[e, p, 1] - (fy * (R10 * x + R11 * y + R12 + t1 * d) * iz + cy)
            rn = math.sqrt(r0 * r0 + r1 * r1)
            rho = 0.5 * rn * rn if rn <= delta else delta * (rn - 0.5 * delta)
            total += 0.5 * (conf[e, p, 0] + conf[e, p, 1]) * rho
    return total


def _rays(coords: torch.Tensor, intr: Intrinsics) -> np.ndarray:
    """(P, 2) float64 ``(x, y)`` of the pixels' normalised rays (:func:`~vigs_core.solver.projective.pixel_rays`)."""
    return pixel_rays(coords.double(), intr)[:, :2].contiguous().numpy()


def edge_cost(T_ji: torch.Tensor, disp: torch.Tensor, coords: torch.Tensor, target: torch.Tensor, conf: torch.Tensor,
              intr: Intrinsics, huber_delta: float) -> torch.Tensor:
    """The robust cost ``sum conf rho(|r|)`` (scalar, ``disp``'s dtype) of the edges of :func:`linearize_edges`."""
    total = _edge_cost(T_ji.double().contiguous().numpy(), disp.contiguous().numpy(), _rays(coords, intr),
                       target.contiguous().numpy(), conf.contiguous().numpy(), float(intr.fx), float(intr.fy),
                       float(intr.cx), float(intr.cy), float(huber_delta))
    return torch.tensor(total, dtype=disp.dtype)


def linearize_edges(T_ji: torch.Tensor, Ad: torch.Tensor, disp: torch.Tensor, coords: torch.Tensor,
                    target: torch.Tensor, conf: torch.Tensor, intr: Intrinsics, huber_delta: float, src: torch.Tensor,
                    slot: torch.Tensor, rank: torch.Tensor, n: int, n_slots: int, K: int) -> tuple:
    """The visual terms (module docstring) of E edges: relative poses ``T_ji`` (E, 4, 4) and their adjoints ``Ad``
    (E, 6, 6), source disparities ``disp`` (E, P), shared pixel coordinates ``coords`` (P, 2), targets and per-axis
    confidences (E, P, 2); edge ``e`` leaves keyframe ``src[e]`` (of ``n``) whose E blocks are slot ``slot[e]`` (of
    ``n_slots``, ``K`` blocks each), its own block 0 and the edge's ``rank[e] + 1``. CPU tensors. Returns ``H_jj``
    (E, 6, 6), ``v_j`` (E, 6), ``C`` and ``w`` (n, P), the E blocks (n_slots, K, 6, P), residual (E, P, 2), valid
    (E, P) and the cost (scalar), in ``disp``'s dtype (valid: bool)."""
    E, P = disp.shape
    d = disp.contiguous().numpy()
    H_jj, v_j, cost = np.empty((E, 6, 6)), np.empty((E, 6)), np.empty(E)
    C, w = np.zeros((n, P), d.dtype), np.zeros((n, P), d.dtype)
    block_E = np.zeros((n_slots, K, 6, P), d.dtype)
    residual, valid = np.empty((E, P, 2), d.dtype), np.empty((E, P), np.bool_)
    _edge_terms(T_ji.double().contiguous().numpy(), Ad.double().contiguous().numpy(), d, _rays(coords, intr),
                target.contiguous().numpy(), conf.contiguous().numpy(), float(intr.fx), float(intr.fy),
                float(intr.cx), float(intr.cy), float(huber_delta), src.numpy(), slot.numpy(), rank.numpy(),
                H_jj, v_j, C, w, block_E, residual, valid, cost)
    dt = disp.dtype
    return (torch.from_numpy(H_jj).to(dt), torch.from_numpy(v_j).to(dt), torch.from_numpy(C),
            torch.from_numpy(w), torch.from_numpy(block_E), torch.from_numpy(residual), torch.from_numpy(valid),
            torch.tensor(float(cost.sum()), dtype=dt))
