"""Relative Sim(3) between two keyframes from dense correspondences with depth, its information matrix, and the
geometric verification of a loop candidate (VIGS-SLAM Sec. 3.1: loop edges measured from dense two-view
correspondences; DROID-SLAM's global BA uses the same reprojection residuals).

Keyframe ``a`` has grid pixels ``p`` (P, 2) with depths ``z_a`` (P,) in its own map units, keyframe ``b`` the same
grid with depths ``z_b``. The relative similarity ``Z = S_a^{-1} S_b = [s R, t]`` maps camera ``b`` points (in
``b``'s units) to camera ``a`` (in ``a``'s units). Correspondences ``a -> b`` (targets ``u_ab``, confidences
``w_ab``) and ``b -> a`` give the residuals

    r_ab(p) = u_ab(p) - pi(Z^{-1} X_a(p)),     X_a(p) = z_a(p) K^{-1} p~      (a's points seen by b)
    r_ba(p) = u_ba(p) - pi(Z X_b(p)),          X_b(p) = z_b(p) K^{-1} p~      (b's points seen by a)

``r_ab`` does not depend on ``s`` (a similarity's scale cancels in the projection), ``r_ba`` does: using both
directions with the depths fixed measures the relative scale, which is what loop closure needs to correct
monocular scale drift. With the left perturbation ``Z <- Exp(delta) Z`` (``delta = (rho, phi, sigma)``, the
tangent order of :mod:`vigs_core.geometry.sim3`) and ``Exp(delta) X ~ X + [I, -[X]x, X] delta``:

    d(Z X_b)/d delta = [I, -[Y]x, Y],                       Y = Z X_b
    d(Z^{-1} X_a)/d delta = (R^T / s) [-I, [X_a]x, -X_a]

times ``d pi / dP = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]``. At a true revisit ``t ~ 0`` and the
reprojection hardly sees the scale, so each direction also has a log-depth residual against the other
keyframe's depth map ``z_b`` at the matched pixel (bilinear in inverse depth on the grid):

    r_d,ab(p) = log z(Z^{-1} X_a(p)) - log z_b(u_ab(p)),    d r_d / d delta = e_3^T (d Y / d delta) / z

with standard deviation ``depth_sigma``. Gauss-Newton with Huber weights times the confidences refines ``Z``
(initialised by PnP-RANSAC on ``a``'s points and the targets in ``b``, scale from the median depth ratio), and
``J^T W J`` at the solution is the information of the measurement (pixel residuals of unit variance), scaled
down by ``information_scale`` because dense residuals are correlated.

Verification accepts the pair when enough of the grid has confident correspondences in both directions and,
after the refinement, most of those reproject within a few pixels AND agree with the other keyframe's depth
(``|log(z_predicted / z_measured)| < tau``): a view that only looks alike (textures that repeat on a different
structure) does not reproduce the other keyframe's geometry.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from vigs_core.frontend.correspondence import Correspondences, PixelGrid
from vigs_core.geometry import hat, sim3_exp, sim3_from_srt
from vigs_core.loop.config import LoopVerificationConfig
from vigs_core.solver import Intrinsics, huber_weight, pixel_rays

F64 = torch.float64


@dataclass
class TwoViewCorrespondences:
    """Dense correspondences of one ordered keyframe pair on the source's grid: targets (P, 2) in input pixels
    of the target image, confidences (P,) in [0, 1] and optionally the target keyframe's depth at the targets
    (P,) (its own units; 0 = unknown), which adds the depth residuals."""

    target: torch.Tensor
    weight: torch.Tensor
    target_depth: torch.Tensor | None = None

    @staticmethod
    def of(corr: Correspondences) -> "TwoViewCorrespondences":
        """The float64 tensors of a correspondence estimator's output (targets and confidences, no depth)."""
        return TwoViewCorrespondences(torch.from_numpy(np.asarray(corr.target, dtype=np.float64)),
                                      torch.from_numpy(np.asarray(corr.weight, dtype=np.float64)))


@dataclass
class TwoViewResult:
    """Outcome of :func:`estimate_relative_sim3`.

    Attributes:
        accepted: the geometric verification passed.
        reason: why it was rejected ("" when accepted).
        relative: (4, 4) ``Z = S_a^{-1} S_b`` (camera b in camera a, with b's depth-unit scale), or None.
        information: (7, 7) information of ``Z`` in the tangent ``(rho, phi, sigma)`` of a left perturbation.
        confident_fraction: min over both directions of the fraction of grid pixels with confident matches.
        inlier_fraction: min over both directions of the fraction of confident matches that reproject and
            agree in depth.
        rms_px: RMS reprojection error of the inliers, pixels.
    """

    accepted: bool
    reason: str
    relative: torch.Tensor | None = None
    information: torch.Tensor | None = None
    confident_fraction: float = 0.0
    inlier_fraction: float = 0.0
    rms_px: float = float("inf")


def _project(P: torch.Tensor, intr: Intrinsics) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixels (N, 2), projection Jacobians (N, 2, 3) and validity (N,) of camera points (N, 3)."""
    X, Y, Z = P.unbind(-1)
    valid = Z > 1e-6
    inv_z = 1.0 / torch.where(valid, Z, torch.ones_like(Z))
    uv = torch.stack((intr.fx * X * inv_z + intr.cx, intr.fy * Y * inv_z + intr.cy), -1)
    zero = torch.zeros_like(X)
    J = torch.stack((torch.stack((intr.fx * inv_z, zero, -intr.fx * X * inv_z**2), -1),
                     torch.stack((zero, intr.fy * inv_z, -intr.fy * Y * inv_z**2), -1)), -2)
    return uv, J, valid


@dataclass
class DirectionResiduals:
    """Residuals of one direction: reprojection ``r`` (P, 2) pixels with Jacobian ``J`` (P, 2, 7), the
    predicted depth ``z`` (P,) of the source points in the target camera (target units), the log-depth residual
    ``r_depth = log z - log z_measured`` (P,) with Jacobian ``J_depth`` (P, 7) (zero without a measured depth),
    and ``valid`` (P,): in front of the target camera."""

    r: torch.Tensor
    J: torch.Tensor | None
    z: torch.Tensor
    r_depth: torch.Tensor
    J_depth: torch.Tensor | None
    valid: torch.Tensor


def _direction(Y: torch.Tensor, dY: torch.Tensor | None, c: TwoViewCorrespondences,
               intr: Intrinsics) -> DirectionResiduals:
    uv, Jpi, valid = _project(Y, intr)
    z = Y[:, 2]
    has = c.target_depth is not None
    z_meas = c.target_depth.to(F64) if has else torch.zeros_like(z)
    ok = valid & (z_meas > 0)
    r_depth = torch.where(ok, torch.log(z.clamp_min(1e-12)) - torch.log(z_meas.clamp_min(1e-12)), 0.0)
    J = J_depth = None
    if dY is not None:
        J = Jpi @ dY
        J_depth = torch.where(ok[:, None], dY[:, 2, :] / z.clamp_min(1e-12)[:, None], 0.0)
    return DirectionResiduals(c.target - uv, J, z, r_depth, J_depth, valid)


def two_view_residuals(Z: torch.Tensor, points_a: torch.Tensor, points_b: torch.Tensor,
                       ab: TwoViewCorrespondences, ba: TwoViewCorrespondences | None, intr: Intrinsics,
                       jacobians: bool = True) -> list[DirectionResiduals]:
    """Residuals of both directions (module docstring): a's points seen by b, then (if ``ba``) b's points seen
    by a.

    Args:
        Z: (4, 4) relative similarity ``S_a^{-1} S_b``.
        points_a, points_b: (P, 3) grid points of a and b in their own camera frames and units.
        ab, ba: correspondences a -> b and b -> a (``ba`` may be None: one direction only).
    """
    s = torch.linalg.det(Z[:3, :3]).clamp_min(1e-300) ** (1.0 / 3.0)
    R, t = Z[:3, :3] / s, Z[:3, 3]
    eye = torch.eye(3, dtype=F64).expand(points_a.shape[0], 3, 3)
    # a's points seen by b: Y = Z^{-1} X_a = R^T (X_a - t) / s
    Y = ((points_a - t) @ R) / s
    dY = (R.T / s) @ torch.cat((-eye, hat(points_a), -points_a[..., None]), -1) if jacobians else None
    out = [_direction(Y, dY, ab, intr)]
    if ba is not None:
        Y = points_b @ Z[:3, :3].T + t
        dY = torch.cat((eye, -hat(Y), Y[..., None]), -1) if jacobians else None
        out.append(_direction(Y, dY, ba, intr))
    return out


def grid_points(depth: torch.Tensor, coords: torch.Tensor, intr: Intrinsics) -> torch.Tensor:
    """Camera-frame points (P, 3) ``z K^{-1} (u, v, 1)`` of grid pixels ``coords`` (P, 2) with depths (P,)."""
    return pixel_rays(coords.to(F64), intr) * depth.to(F64)[:, None]


def relative_information(Z: torch.Tensor, points_a: torch.Tensor, points_b: torch.Tensor,
                         ab: TwoViewCorrespondences, ba: TwoViewCorrespondences | None, intr: Intrinsics,
                         huber_px: float, min_confidence: float, depth_sigma: float) -> torch.Tensor:
    """Gauss-Newton information (7, 7) of the relative similarity ``Z``: ``sum_p w_p J_p^T J_p`` over the
    confident correspondences of both directions, pixel residuals of unit variance and log-depth residuals of
    standard deviation ``depth_sigma``, Huber-reweighted."""
    H, _ = _normal_equations(two_view_residuals(Z, points_a, points_b, ab, ba, intr), (ab, ba), huber_px,
                             min_confidence, depth_sigma)
    return H


def _normal_equations(dirs: list[DirectionResiduals], corrs, huber_px: float, min_confidence: float,
                      depth_sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(H (7, 7), g (7,))`` of the weighted least squares over all directions (``H delta = g`` steps)."""
    H = torch.zeros(7, 7, dtype=F64)
    g = torch.zeros(7, dtype=F64)
    for d, c in zip(dirs, corrs):
        conf = torch.where(c.weight >= min_confidence, c.weight.to(F64), 0.0) * d.valid
        w = conf * huber_weight(d.r.norm(dim=-1), huber_px)
        H += torch.einsum("p,pki,pkj->ij", w, d.J, d.J)
        g += torch.einsum("p,pki,pk->i", w, d.J, d.r)
        e = d.r_depth / depth_sigma
        wd = conf * huber_weight(e.abs(), 2.0) / depth_sigma**2
        H += torch.einsum("p,pi,pj->ij", wd, d.J_depth, d.J_depth)
        g -= torch.einsum("p,pi,p->i", wd, d.J_depth, d.r_depth)
    return H, g


def depth_at(depth: torch.Tensor, grid: PixelGrid, uv: torch.Tensor) -> torch.Tensor:
    """Depth (N,) of a grid depth map (P,) at pixels (N, 2): bilinear in inverse depth between the four
    surrounding cell centres, 0 outside the grid or where a neighbour is unknown (depth <= 0)."""
    s = grid.stride
    x = (uv[:, 0].to(F64) - (s - 1) / 2.0) / s
    y = (uv[:, 1].to(F64) - (s - 1) / 2.0) / s
    inside = (x >= 0) & (x <= grid.cols - 1) & (y >= 0) & (y <= grid.rows - 1)
    x = x.clamp(0, grid.cols - 1)
    y = y.clamp(0, grid.rows - 1)
    x0 = x.floor().long().clamp_max(grid.cols - 2)
    y0 = y.floor().long().clamp_max(grid.rows - 2)
    fx, fy = x - x0, y - y0
    z = depth.to(F64).reshape(grid.rows, grid.cols)
    corners = torch.stack((z[y0, x0], z[y0, x0 + 1], z[y0 + 1, x0], z[y0 + 1, x0 + 1]), -1)
    known = (corners > 0).all(-1)
    inv = 1.0 / corners.clamp_min(1e-12)
    w = torch.stack(((1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy), -1)
    d = (w * inv).sum(-1)
    return torch.where(inside & known, 1.0 / d, 0.0)


def with_target_depth(c: TwoViewCorrespondences, depth_src: torch.Tensor, depth_dst: torch.Tensor,
                      grid: PixelGrid) -> TwoViewCorrespondences:
    """Float64 copy of ``c`` with the target keyframe's depth at the targets; confidences are zeroed where the
    source or the target depth is unknown."""
    target = c.target.to(F64)
    z_t = depth_at(depth_dst, grid, target)
    weight = torch.where((depth_src.to(F64) > 0) & (z_t > 0), c.weight.to(F64), 0.0)
    return TwoViewCorrespondences(target, weight, z_t)


def edge_information(Z: torch.Tensor, depth_a: torch.Tensor, depth_b: torch.Tensor, ab: TwoViewCorrespondences,
                     ba: TwoViewCorrespondences | None, grid: PixelGrid, intr: Intrinsics,
                     config: LoopVerificationConfig | None = None) -> torch.Tensor:
    """Information (7, 7) of a keyframe pair's relative similarity ``Z = S_a^{-1} S_b`` from its dense
    correspondences (one or both directions) and depths (P,), scaled by ``information_scale``: the covariance
    of an odometry edge of the relative-pose graph, computed like a loop edge's."""
    cfg = config or LoopVerificationConfig()
    coords = torch.from_numpy(grid.coords())
    pa, pb = grid_points(depth_a, coords, intr), grid_points(depth_b, coords, intr)
    ab = with_target_depth(ab, depth_a, depth_b, grid)
    ba = with_target_depth(ba, depth_b, depth_a, grid) if ba is not None else None
    return cfg.information_scale * relative_information(Z.to(F64), pa, pb, ab, ba, intr, cfg.inlier_px,
                                                        cfg.min_confidence, cfg.depth_sigma)


def _pnp_initial(points_a: torch.Tensor, ab: TwoViewCorrespondences, intr: Intrinsics,
                 config: LoopVerificationConfig) -> torch.Tensor | None:
    """``Z`` from PnP-RANSAC on a's points and their targets in b; scale = median of (depth in b predicted in
    a's units) / (b's own depth at the target)."""
    conf = (ab.weight >= config.min_confidence).numpy()
    if conf.sum() < 12:
        return None
    obj = points_a.numpy()[conf]
    img = ab.target.numpy()[conf]
    K = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]], dtype=np.float64)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, reprojectionError=config.pnp_reprojection_px,
                                                 iterationsCount=200, confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:  # degenerate point sets (e.g. all points on a line) make OpenCV raise
        return None
    if not ok or inl is None or len(inl) < 12:
        return None
    R_ba = torch.from_numpy(cv2.Rodrigues(rvec)[0])                # X_b' = R_ba X_a + t_ba (a's units)
    t_ba = torch.from_numpy(tvec[:, 0])
    idx = torch.from_numpy(np.flatnonzero(conf)[inl[:, 0]])
    z_pred = (points_a[idx] @ R_ba.T + t_ba)[:, 2]
    z_meas = ab.target_depth[idx]
    good = (z_meas > 0) & (z_pred > 0)
    if int(good.sum()) < 12:
        return None
    s = float((z_pred[good] / z_meas[good]).median())
    # X_a = R_ba^T (X_b' - t_ba) with X_b' = s X_b
    return sim3_from_srt(torch.tensor(s, dtype=F64), R_ba.T, -(R_ba.T @ t_ba))


def estimate_relative_sim3(depth_a: torch.Tensor, depth_b: torch.Tensor, ab: TwoViewCorrespondences,
                           ba: TwoViewCorrespondences, grid: PixelGrid, intr: Intrinsics,
                           config: LoopVerificationConfig | None = None) -> TwoViewResult:
    """Verify a keyframe pair and measure ``Z = S_a^{-1} S_b`` (module docstring).

    Args:
        depth_a, depth_b: (P,) grid depths of a and b, each in its own map units (> 0; 0 = unknown).
        ab, ba: dense correspondences a -> b and b -> a on the grid ``grid`` (their ``target_depth`` is filled
            here from the depths).
        intr: pinhole intrinsics of the input images.
    """
    cfg = config or LoopVerificationConfig()
    coords = torch.from_numpy(grid.coords())
    P = coords.shape[0]
    for name, t in (("depth_a", depth_a), ("depth_b", depth_b), ("ab.weight", ab.weight), ("ba.weight", ba.weight)):
        if tuple(t.shape) != (P,):
            raise ValueError(f"estimate_relative_sim3: {name} has shape {tuple(t.shape)}, expected ({P},) for the "
                             f"{grid.cols}x{grid.rows} grid")
    depth_a, depth_b = depth_a.to(F64), depth_b.to(F64)
    corrs = [with_target_depth(ab, depth_a, depth_b, grid), with_target_depth(ba, depth_b, depth_a, grid)]
    ab, ba = corrs
    confident = min(float((c.weight >= cfg.min_confidence).double().mean()) for c in corrs)
    if confident < cfg.min_confident_fraction:
        return TwoViewResult(False, f"confident correspondences {confident:.2f} < {cfg.min_confident_fraction}",
                             confident_fraction=confident)
    pa, pb = grid_points(depth_a, coords, intr), grid_points(depth_b, coords, intr)
    Z = _pnp_initial(pa, ab, intr, cfg)
    if Z is None:
        return TwoViewResult(False, "PnP found no consistent pose", confident_fraction=confident)
    for _ in range(cfg.refine_iterations):
        H, g = _normal_equations(two_view_residuals(Z, pa, pb, ab, ba, intr), corrs, cfg.inlier_px,
                                 cfg.min_confidence, cfg.depth_sigma)
        H += torch.eye(7, dtype=F64) * (1e-6 * float(H.diagonal().mean()) + 1e-12)
        delta = torch.linalg.solve(H, g)
        Z = sim3_exp(delta) @ Z
        if float(delta.norm()) < 1e-10:
            break
    inlier_fractions, sq_errors = [], []
    for d, c in zip(two_view_residuals(Z, pa, pb, ab, ba, intr, jacobians=False), corrs):
        conf = c.weight >= cfg.min_confidence
        e = d.r.norm(dim=-1)
        inl = conf & d.valid & (e < cfg.inlier_px) & (d.r_depth.abs() < cfg.max_log_depth_ratio)
        inlier_fractions.append(float(inl.sum()) / max(int(conf.sum()), 1))
        sq_errors.append(e[inl] ** 2)
    inlier = min(inlier_fractions)
    errors = torch.cat(sq_errors)
    rms = float(errors.mean().sqrt()) if errors.numel() else float("inf")
    info = cfg.information_scale * relative_information(Z, pa, pb, ab, ba, intr, cfg.inlier_px, cfg.min_confidence,
                                                        cfg.depth_sigma)
    if inlier < cfg.min_inlier_fraction:
        return TwoViewResult(False, f"inlier fraction {inlier:.2f} < {cfg.min_inlier_fraction} (reprojection "
                             f"within {cfg.inlier_px} px and depth agreement)", Z, info, confident, inlier, rms)
    return TwoViewResult(True, "", Z, info, confident, inlier, rms)
