"""Differentiable Gaussian rasterizer: backend interface and the pure-PyTorch tile-based reference.

Design (3DGS, Kerbl et al. 2023, Sec. 4 and 6, written for CPU throughput in PyTorch):

1. **Projection** (plain autograd, O(N)). Camera-frame mean ``p = R_CW mu + t_CW``; pixel mean
   ``m = (fx x/z + cx, fy y/z + cy)``; 2D covariance ``Sigma' = J W Sigma W^T J^T + eps I`` with the
   projection Jacobian ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` (EWA splatting, Zwicker 2002)
   and a low-pass ``eps = 0.3`` px^2; conic ``Q = Sigma'^-1 = [[a, b], [b, c]]``.
2. **Binning** (no gradient). A Gaussian touches the pixels where ``o exp(-d^2/2) >= 1/255``
   (``d`` Mahalanobis), i.e. ``d^2 <= 2 ln(255 o)``: the exact bounding box of that ellipse selects
   candidate tiles, and of those only the tiles whose pixel-centre rectangle the ellipse meets are kept
   (exact ellipse-rectangle test, :func:`ellipse_meets_tile`: a box's corner tiles are often missed, and
   would only composite alpha = 0; about a sixth of the pairs in the mapping benchmark). (Gaussian, tile)
   pairs are sorted by tile then camera depth and each tile keeps its front-most ``K`` Gaussians
   (``K = min(max_per_tile, busiest tile)``), padded with a transparent dummy.
3. **Compositing** over (tiles T, pixels P, Gaussians K) in one custom autograd function
   (:class:`_RasterizeTiles`): the exponent ``power = -(1/2) (x - m)^T Q (x - m)`` is a quadratic form in
   the pixel, written as ``[x^2, xy, y^2, x, y, 1] . coef`` so a single batched matmul evaluates it for
   all pixels; ``alpha = min(o, 0.99) exp(power)`` (zero below 1/255; evaluated as ``exp(power + log o)``,
   folding the opacity into the constant coefficient), ``T_k = prod_{j<k} (1 - alpha_j)``,
   ``w_k = alpha_k T_k``, outputs ``sum_k w_k f_k`` for features ``f = (r, g, b, z)`` and accumulated
   opacity ``1 - prod_k (1 - alpha_k)``. The backward pass is analytic, which avoids autograd's slow
   cumprod backward and its zero-filled gradients of slices; tiles are processed busiest first in
   chunks, each gathering only its own ``K`` slots per tile.

The opacity is clamped to 0.99 before the Gaussian falloff (3DGS clamps ``o G`` instead): the two agree
wherever ``o <= 0.99`` and the clamp then has an exact, cheap gradient.

Pixel convention: pixel ``(i, j)`` (row, column) has its centre at ``(u, v) = (j, i)``, as
:class:`vigs_core.camera.CameraModel`. Rendered depth is the alpha-weighted sum ``sum_k w_k z_k``
(metres, "accumulated depth"); ``depth / alpha`` is the expected depth of the visible surface.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import torch

from vigs_core.compiled import numba_available
from vigs_core.geometry import quat_to_matrix

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99


@dataclass(frozen=True)
class RenderCamera:
    """Pinhole intrinsics of the rendered image (pixels; pixel-centre convention of ``CameraModel``).

    Build one from a :class:`vigs_core.camera.CameraModel` with :meth:`from_camera`.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @staticmethod
    def from_camera(camera, scale: float = 1.0) -> RenderCamera:
        """Intrinsics of ``camera`` (any object with width/height/fx/fy/cx/cy, e.g. ``CameraModel``)
        resampled by ``scale`` (the image size becomes ``round(width * scale) x round(height * scale)``,
        matching ``cv2.resize`` and ``CameraModel.scaled``)."""
        if not scale > 0:
            raise ValueError(f"render scale must be > 0, got {scale}")
        w = max(1, round(camera.width * scale))
        h = max(1, round(camera.height * scale))
        sx, sy = w / camera.width, h / camera.height
        return RenderCamera(
            w, h, camera.fx * sx, camera.fy * sy, (camera.cx + 0.5) * sx - 0.5, (camera.cy + 0.5) * sy - 0.5
        )


@dataclass(frozen=True)
class RenderSettings:
    """Settings of the reference rasterizer.

    Args:
        tile_size: tile edge in pixels (8 measured fastest on CPU: smaller tiles waste fewer (pixel,
            Gaussian) evaluations but cost more binning and smaller matrix products).
        max_per_tile: at most this many front-most Gaussians are composited per tile (``K``); high, since a cut
            darkens crowded tiles whose front Gaussians are not opaque (the reference's memory is bounded by
            ``chunk_pairs``, the compiled binning's by the pairs).
        near: Gaussians closer than this camera depth (metres) are culled.
        eps2d: low-pass variance added to every 2D covariance, px^2 (3DGS uses 0.3).
        chunk_pairs: (pixel, Gaussian) pairs composited at once (bounds the working set: about 20 bytes
            each; larger chunks mean fewer, larger tensor operations); tiles beyond it are processed in
            further chunks.
    """

    tile_size: int = 8
    max_per_tile: int = 2048
    near: float = 0.05
    eps2d: float = 0.3
    chunk_pairs: int = 1 << 20


@dataclass
class RenderOutput:
    """A rendered view: ``color`` (H, W, 3), ``depth`` (H, W) accumulated depth in metres, ``alpha`` (H, W)
    accumulated opacity, and ``visible`` (M,) int64 the input rows that reached at least one tile."""

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    visible: torch.Tensor


class Rasterizer(Protocol):
    """A rasterizer backend: activated Gaussian parameters in, one rendered view out.

    Args of ``__call__``: ``means`` (N, 3) world, ``quats`` (N, 4) ``(w, x, y, z)`` (normalised by the backend:
    any non-zero length), ``scales`` (N, 3) metres,
    ``opacities`` (N,) in [0, 1], ``colors`` (N, 3), ``T_CW`` (4, 4) camera-from-world, ``camera``
    :class:`RenderCamera`. Differentiable in the Gaussian parameters.
    """

    def __call__(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        T_CW: torch.Tensor,
        camera: RenderCamera,
    ) -> RenderOutput: ...


def ray_limits(camera: RenderCamera) -> tuple[float, float, float, float]:
    """``(lo_x, hi_x, lo_y, hi_y)``: the bounds of ``x/z``, ``y/z`` in the projection Jacobian, 1.3x the field of
    view (3DGS)."""
    lim_x = 1.3 * (0.5 * camera.width / camera.fx)
    lim_y = 1.3 * (0.5 * camera.height / camera.fy)
    return (-lim_x - camera.cx / camera.fx, lim_x + (camera.width - camera.cx) / camera.fx,
            -lim_y - camera.cy / camera.fy, lim_y + (camera.height - camera.cy) / camera.fy)


def _clamped_rays(tx: torch.Tensor, ty: torch.Tensor, camera: RenderCamera) -> tuple[torch.Tensor, torch.Tensor]:
    """``x/z``, ``y/z`` clamped to :func:`ray_limits`, as they enter the projection Jacobian (3DGS)."""
    lo_x, hi_x, lo_y, hi_y = ray_limits(camera)
    return tx.clamp(lo_x, hi_x), ty.clamp(lo_y, hi_y)


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    T_CW: torch.Tensor,
    camera: RenderCamera,
    eps2d: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection of 3D Gaussians (3DGS Eq. 5).

    Returns ``mean2d`` (N, 2) pixels, ``cov2d`` (N, 3) as ``(xx, xy, yy)`` px^2 (with ``eps2d`` added) and
    camera depth ``z`` (N,) metres. ``x/z`` and ``y/z`` inside the Jacobian are clamped to 1.3x the field
    of view (as 3DGS) so Gaussians near the image border do not explode.
    """
    R = T_CW[:3, :3].to(means.dtype)
    t = T_CW[:3, 3].to(means.dtype)
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    inv_z = 1.0 / z
    mean2d = torch.stack((camera.fx * x * inv_z + camera.cx, camera.fy * y * inv_z + camera.cy), -1)
    tx, ty = _clamped_rays(x * inv_z, y * inv_z, camera)
    zeros = torch.zeros_like(z)
    J = torch.stack(
        (
            torch.stack((camera.fx * inv_z, zeros, -camera.fx * tx * inv_z), -1),
            torch.stack((zeros, camera.fy * inv_z, -camera.fy * ty * inv_z), -1),
        ),
        -2,
    )  # (N, 2, 3)
    M = J @ R @ (quat_to_matrix(quats) * scales[:, None, :])  # (N, 2, 3): Sigma' = M M^T
    cov = M @ M.transpose(-1, -2)
    cov2d = torch.stack((cov[:, 0, 0] + eps2d, cov[:, 0, 1], cov[:, 1, 1] + eps2d), -1)
    return mean2d, cov2d, z


@torch.no_grad()
def frustum_rows(
    means: torch.Tensor, scales: torch.Tensor, T_CW: torch.Tensor, camera: RenderCamera, settings: RenderSettings,
    compiled: bool = False,
) -> torch.Tensor:
    """Rows (M,) int64 of the Gaussians (``means`` (N, 3), ``scales`` (N, 3) metres) that can reach a pixel:
    in front of the camera (depth above ``settings.near``) and with the projected centre ``m`` within
    ``r`` pixels of the image, where ``r`` bounds the binning's half extent ``sqrt(2 ln(255 o) Sigma'_ii)``
    (``o <= 1``). The projected standard deviation along any direction is at most
    ``||J R S||_2 + sqrt(eps) <= s_max ||J||_F + sqrt(eps)`` with ``||J||_F = sqrt(fx^2 (1 + t_x^2) +
    fy^2 (1 + t_y^2)) / z`` (``t`` the clamped rays of :func:`project_gaussians`), so
    ``r = sqrt(2 ln 255) (s_max ||J||_F + sqrt(eps))``: every row culled here would fail the rasterizer's
    own image test, and rendering only the returned rows gives the same image. No gradient. ``compiled`` (CPU
    tensors): the same test in one compiled pass (:func:`vigs_core.mapping.rasterizer_numba.frustum_rows`)."""
    if compiled and means.device.type == "cpu":
        from vigs_core.mapping import rasterizer_numba

        return rasterizer_numba.frustum_rows(means, scales, T_CW, camera, settings.near, settings.eps2d)
    dtype = means.dtype
    p_cam = means.detach() @ T_CW[:3, :3].to(dtype).T + T_CW[:3, 3].to(dtype)
    z = p_cam[:, 2].clamp_min(1e-9)
    tx, ty = p_cam[:, 0] / z, p_cam[:, 1] / z
    u = camera.fx * tx + camera.cx
    v = camera.fy * ty + camera.cy
    tx, ty = _clamped_rays(tx, ty, camera)
    jac = torch.sqrt(camera.fx**2 * (1.0 + tx * tx) + camera.fy**2 * (1.0 + ty * ty)) / z
    r = math.sqrt(2.0 * math.log(255.0)) * (scales.detach().amax(dim=1) * jac + math.sqrt(settings.eps2d))
    front = (
        (p_cam[:, 2] > settings.near)
        & (u + r >= -0.5)
        & (u - r <= camera.width - 0.5)
        & (v + r >= -0.5)
        & (v - r <= camera.height - 0.5)
    )
    return front.nonzero().squeeze(1)


def _pixel_monomials(tile_size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(P, 6) rows ``[x^2, xy, y^2, x, y, 1]`` of the tile-local pixel centres, row-major in the tile."""
    r = torch.arange(tile_size, dtype=dtype, device=device)
    y, x = torch.meshgrid(r, r, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack((x * x, x * y, y * y, x, y, torch.ones_like(x)), -1)


def _composite_chunk(coef, feat, mono, keep):
    """Forward of :class:`_RasterizeTiles` on one chunk of tiles: ``(out, acc, saved)``.

    ``alpha = exp(mono @ coef)`` (the opacity enters as ``log o`` in the constant coefficient, see
    :func:`_slot_coefficients`), cut below 1/255; ``T_{k+1} = cumprod(1 - alpha)``, ``w_k = T_k - T_{k+1}``.
    With ``keep`` the backward's inputs ``(w, alpha / (1 - alpha), T_end)`` are returned, else None."""
    alpha = torch.matmul(mono, coef).exp_()  # (T, P, K)
    torch.nn.functional.threshold_(alpha, ALPHA_MIN, 0.0)
    one_minus = torch.rsub(alpha, 1.0)
    t_incl = torch.cumprod(one_minus, dim=2)  # T_{k+1}
    w = torch.empty_like(alpha)
    torch.sub(1.0, t_incl[:, :, :1], out=w[:, :, :1])
    torch.sub(t_incl[:, :, :-1], t_incl[:, :, 1:], out=w[:, :, 1:])
    # (C, K) @ (K, P) per tile: far faster in BLAS than (P, K) @ (K, C) with C = 4
    out = torch.bmm(feat.transpose(1, 2), w.transpose(1, 2)).transpose(1, 2)
    t_end = t_incl[:, :, -1].clone()
    if not keep:
        return out, 1.0 - t_end, None
    ratio = torch.div(alpha, one_minus, out=one_minus)  # alpha / (1 - alpha), finite: alpha <= 0.99
    return out, 1.0 - t_end, (w, ratio, t_end)


@dataclass(frozen=True)
class _TileLayout:
    """Where the composited tiles go: ``tiles`` (T,) tile ids (row-major grid of ``n_ty x n_tx`` tiles of
    ``ts x ts`` px), ``index`` (T, K) the table rows of each tile's slots front to back (padded with the
    transparent dummy row), the image size, and the compositing ``chunks`` (see :func:`_tile_chunks`)."""

    tiles: torch.Tensor
    index: torch.Tensor
    n_tx: int
    n_ty: int
    ts: int
    width: int
    height: int
    chunks: list


def _slot_coefficients(slots: torch.Tensor, origin: torch.Tensor):
    """Coefficients (T, 6, K) of ``log alpha`` (before the 1/255 cut) of the tile slots, and the
    tile-local means ``mx, my`` with ``p = a mx + b my``, ``q = b mx + c my``.

    ``log o - (1/2) [dx, dy] Q [dx, dy]^T`` with ``dx = x - mx`` equals ``[x^2, xy, y^2, x, y, 1] . coef``,
    ``coef = (-a/2, -b, -c/2, p, q, log o - (mx p + my q)/2)``. The padding slots (``o = 0``) get
    ``log o = log 1e-30``: alpha underflows to zero, and gradients stay finite."""
    mx = slots[..., 0] - origin[:, None, 0]
    my = slots[..., 1] - origin[:, None, 1]
    a, b, c = slots[..., 2], slots[..., 3], slots[..., 4]
    p = a * mx + b * my
    q = b * mx + c * my
    log_o = slots[..., 5].clamp_min(1e-30).log()
    coef = torch.stack((-0.5 * a, -b, -0.5 * c, p, q, log_o - 0.5 * (mx * p + my * q)), 1)
    return coef, mx, my, p, q


class _RasterizeTiles(torch.autograd.Function):
    """Front-to-back alpha compositing of the K depth-sorted Gaussian slots of T tiles into an image.

    Input ``table`` (N + 1, 6 + F): per Gaussian ``[u, v, a, b, c, o, f_1..f_F]`` (pixel mean, conic,
    opacity, features, here RGB and camera depth), the last row the transparent dummy; tile ``t``'s slots are
    the rows ``layout.index[t]``. Per tile, with ``power = mono @ coef`` (P, K) (see
    :func:`_slot_coefficients`; ``power`` includes ``log o``), ``alpha = exp(power)`` kept where
    ``>= 1/255`` (``o <= 0.99`` is clamped by the caller, so ``alpha <= 0.99``), ``T_k = prod_{j<k}
    (1 - alpha_j)``, ``w_k = alpha_k T_k = T_k - T_{k+1}``: features ``out = w @ f`` (P, F) and accumulated
    opacity ``acc = 1 - prod_k (1 - alpha_k)``. Returns the image ``(features (H, W, F), alpha (H, W))``.

    Backward (``g = dL/dout``, ``h = dL/dacc``, ``gf_k = g . f_k``, ``S_k = sum_{j>k} w_j gf_j``,
    ``T_end = prod_k (1 - alpha_k)``): ``dL/dalpha_k = (T_{k+1} gf_k - S_k + h T_end) / (1 - alpha_k)``, so
    with ``T_{k+1} / (1 - alpha_k) = T_k``, ``r_k = alpha_k / (1 - alpha_k)`` and the inclusive prefix sum
    ``C_k = sum_{j<=k} w_j gf_j`` (``S_k = C_K - C_k``):

        dL/dpower_k = alpha_k dL/dalpha_k = w_k gf_k + r_k (C_k - (C_K - h T_end))

    (zero where alpha was cut, as ``w = r = 0`` there); ``dL/dcoef = mono^T dL/dpower``, whose constant
    row is ``dL/dlog o``, so ``dL/do = dL/dcoef_6 / o``; ``dL/df = w^T g``; then the chain rule through
    ``coef`` to ``(u, v, a, b, c)``, and the slot gradients are summed into the table rows. Doing all of
    this in one function keeps autograd from materialising a zero-filled gradient per slice and view,
    which dominated the run time; only ``w``, ``r`` and ``T_end`` are kept for the backward pass (nothing
    when no gradient is needed).

    The tiles are processed in chunks ``(start, end, k)`` (consecutive tiles, of which only the first
    ``k`` slots are gathered and used); tiles sorted by load (busiest first) waste little on padding.
    """

    @staticmethod
    def forward(ctx, table, origin, mono, layout):
        P, C = mono.shape[0], table.shape[1]
        F = C - 6
        keep = ctx.needs_input_grad[0]
        tile_out = table.new_zeros(layout.n_ty * layout.n_tx, P, F + 1)
        saved = []
        for a, b, k in layout.chunks:
            rows = layout.index[a:b, :k].reshape(-1)
            slots = table.index_select(0, rows).reshape(b - a, k, C)
            coef = _slot_coefficients(slots, origin[a:b])[0]
            out, acc, kept = _composite_chunk(coef, slots[..., 6:], mono, keep)
            tiles = layout.tiles[a:b]
            tile_out[tiles, :, :F] = out
            tile_out[tiles, :, F] = acc
            if keep:
                saved.append((rows, slots) + kept)
        if keep:
            ctx.save_for_backward(mono, origin)
            ctx.layout = layout
            ctx.saved_chunks = saved
            ctx.table_shape = table.shape
        ts, H, W = layout.ts, layout.height, layout.width
        img = tile_out.reshape(layout.n_ty, layout.n_tx, ts, ts, F + 1).permute(0, 2, 1, 3, 4)
        img = img.reshape(layout.n_ty * ts, layout.n_tx * ts, F + 1)[:H, :W]
        return img[..., :F].contiguous(), img[..., F].contiguous()

    @staticmethod
    def backward(ctx, g_feat_img, g_alpha_img):
        mono, origin = ctx.saved_tensors
        layout = ctx.layout
        ts, F = layout.ts, ctx.table_shape[1] - 6
        g_img = mono.new_zeros(layout.n_ty * ts, layout.n_tx * ts, F + 1)
        if g_feat_img is not None:
            g_img[: layout.height, : layout.width, :F] = g_feat_img
        if g_alpha_img is not None:
            g_img[: layout.height, : layout.width, F] = g_alpha_img
        g_tiles = g_img.reshape(layout.n_ty, ts, layout.n_tx, ts, F + 1).permute(0, 2, 1, 3, 4)
        g_tiles = g_tiles.reshape(layout.n_ty * layout.n_tx, ts * ts, F + 1)[layout.tiles]
        g_out, g_acc = g_tiles[..., :F].contiguous(), g_tiles[..., F].contiguous()
        d_table = mono.new_zeros(ctx.table_shape)
        for (a, b, k), (rows, slots, w, ratio, t_end) in zip(layout.chunks, ctx.saved_chunks):
            g = g_out[a:b]
            wg = torch.bmm(g, slots[..., 6:].transpose(1, 2)).mul_(w)  # w_k gf_k, (T, P, K)
            prefix = torch.cumsum(wg, 2)  # C_k
            prefix.sub_(prefix[:, :, -1:] - g_acc[a:b, :, None] * t_end[:, :, None])
            d_power = wg.addcmul_(ratio, prefix)
            d0, d1, d2, d3, d4, d5 = torch.matmul(mono.T, d_power).unbind(1)  # dL/dcoef, (T, K) each
            _, mx, my, p, q = _slot_coefficients(slots, origin[a:b])
            a_, b_, c_ = slots[..., 2], slots[..., 3], slots[..., 4]
            d_slots = torch.cat(
                (
                    torch.stack(
                        (
                            d3 * a_ + d4 * b_ - d5 * p,
                            d3 * b_ + d4 * c_ - d5 * q,
                            -0.5 * d0 + d3 * mx - 0.5 * d5 * mx * mx,
                            -d1 + d3 * my + d4 * mx - d5 * mx * my,
                            -0.5 * d2 + d4 * my - 0.5 * d5 * my * my,
                            d5 / slots[..., 5].clamp_min(1e-30),
                        ),
                        -1,
                    ),
                    torch.bmm(g.transpose(1, 2), w).transpose(1, 2),  # dL/df (T, K, F)
                ),
                -1,
            )
            d_table.index_add_(0, rows, d_slots.reshape(-1, F + 6))
        return d_table, None, None, None


def _tile_chunks(counts: list[int], pixels: int, budget: int) -> list[tuple[int, int, int]]:
    """Split tiles sorted by decreasing Gaussian count into chunks ``(start, end, k)`` of at most about
    ``budget`` (pixel, Gaussian) pairs, ``k`` being the chunk's largest count."""
    chunks, start = [], 0
    while start < len(counts):
        k = max(1, counts[start])
        end = min(len(counts), start + max(1, budget // (pixels * k)))
        chunks.append((start, end, k))
        start = end
    return chunks


@dataclass
class TileBins:
    """Result of binning: ``tiles`` (T,) ids of non-empty tiles (row-major over the tile grid), sorted by
    decreasing ``counts`` (T,) (Gaussians kept per tile), ``index`` the Gaussian rows of each tile, front to back,
    and ``binned`` (N,) bool, the Gaussians in at least one tile. ``index`` is (T, K) padded with ``N`` (the
    transparent dummy) when ``starts`` is None (the reference), else flat: tile ``i``'s rows are ``index[starts[i]
    : starts[i] + counts[i]]`` (the compiled binning, whose size then follows the pairs, not ``T K``)."""

    tiles: torch.Tensor
    index: torch.Tensor
    counts: torch.Tensor
    binned: torch.Tensor
    starts: torch.Tensor | None = None


def ellipse_meets_tile(ellipse: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Whether the ellipse ``(x - m)^T Q (x - m) <= r`` meets the rectangle ``[lo, hi]``, exactly, per row:
    ``ellipse`` (M, 6) ``(m_x, m_y, a, b, c, r)`` with ``Q = [[a, b], [b, c]]`` positive definite, corners
    ``lo``, ``hi`` (M, 2). Returns (M,) bool.

    The minimum of the convex quadratic ``f(d) = a dx^2 + 2 b dx dy + c dy^2`` (``d = x - m``) over the
    rectangle is 0 when ``m`` lies inside. Otherwise it lies on the boundary, on an edge beyond which ``m``
    lies: at a minimiser on the edge ``y = y1`` (not a corner) the gradient ``2 Q d`` is normal to it,
    ``d ~ Q^-1 (0, -1)``, whose y component is negative, so ``m_y > y1``; likewise for the other edges.
    The candidate x edge is ``x_e = clamp(m_x, x0, x1)`` (``dx = x_e - m_x``), on which ``f`` is smallest
    at ``dy = -b dx / c`` clamped to the edge; symmetrically for the y edge. When ``m_x`` lies within
    ``[x0, x1]`` the "x edge" point lies inside the rectangle, so it can only bound the minimum from above;
    the smaller of the two candidates is therefore the exact minimum."""
    mx, my, a, b, c, r = ellipse.unbind(-1)
    lx, ly = lo[:, 0] - mx, lo[:, 1] - my  # rectangle relative to the mean
    hx, hy = hi[:, 0] - mx, hi[:, 1] - my
    dx = lx.clamp_min(0.0).add_(hx.clamp_max(0.0))  # clamp(m_x, x0, x1) - m_x
    dy = ly.clamp_min(0.0).add_(hy.clamp_max(0.0))
    dy_x = torch.minimum(torch.maximum(-b * dx / c, ly), hy)  # best dy on the x edge
    dx_y = torch.minimum(torch.maximum(-b * dy / a, lx), hx)  # best dx on the y edge
    f_x = (a * dx + 2.0 * b * dy_x).mul_(dx).addcmul_(c * dy_x, dy_x)
    f_y = (a * dx_y + 2.0 * b * dy).mul_(dx_y).addcmul_(c * dy, dy)
    return torch.minimum(f_x, f_y) <= r


def bin_gaussians(
    mean2d: torch.Tensor,
    half_extent: torch.Tensor,
    depth: torch.Tensor,
    camera: RenderCamera,
    settings: RenderSettings,
    conic: torch.Tensor | None = None,
    reach: torch.Tensor | None = None,
) -> TileBins:
    """Assign Gaussians to the tiles they touch and keep the front-most ``max_per_tile`` per tile, ordered
    by ``depth`` (N,). No gradient.

    ``mean2d`` (N, 2) are pixel means (pixel ``(i, j)``'s centre at ``(j, i)``); the candidate tiles are
    those the bounding box ``mean2d +- half_extent`` (N, 2) overlaps. With ``conic`` (N, 3) ``(a, b, c)``
    and ``reach`` (N,), a candidate tile is kept only where the ellipse ``d^2 <= reach`` (``d``
    Mahalanobis) meets the rectangle spanned by the tile's pixel centres (:func:`ellipse_meets_tile`): the
    bounding box's corner tiles that the ellipse misses would only composite alpha = 0."""
    ts = settings.tile_size
    n_tx = math.ceil(camera.width / ts)
    n_ty = math.ceil(camera.height / ts)
    n = mean2d.shape[0]
    device = mean2d.device
    # tile (tx, ty) holds the pixel centres u in [tx ts, tx ts + ts - 1]: u + 1/2 in [tx ts, (tx + 1) ts)
    lo = torch.floor((mean2d - half_extent + 0.5) / ts).long()
    hi = torch.floor((mean2d + half_extent + 0.5) / ts).long()
    lo[:, 0].clamp_(0, n_tx - 1)
    lo[:, 1].clamp_(0, n_ty - 1)
    hi[:, 0].clamp_(0, n_tx - 1)
    hi[:, 1].clamp_(0, n_ty - 1)
    span = hi - lo + 1
    counts = span[:, 0] * span[:, 1]
    gid = torch.repeat_interleave(torch.arange(n, device=device), counts)
    # per pair: (start of its Gaussian's run, span in x, lowest tile x, lowest tile y), one gather
    per_g = torch.stack((torch.cumsum(counts, 0) - counts, span[:, 0], lo[:, 0], lo[:, 1]), -1)
    per_g = per_g.index_select(0, gid)
    start, sx, lo_x, lo_y = per_g.unbind(-1)
    local = torch.arange(gid.numel(), device=device) - start
    tx, ty = lo_x + local % sx, lo_y + local // sx
    if conic is not None and reach is not None and gid.numel() > 0:
        ellipse = torch.cat((mean2d, conic, reach[:, None]), -1).index_select(0, gid)
        corner = torch.stack((tx, ty), -1).to(mean2d.dtype).mul_(ts)
        last = torch.tensor([camera.width - 1, camera.height - 1], dtype=mean2d.dtype, device=device)
        meets = ellipse_meets_tile(ellipse, corner, torch.minimum(corner + (ts - 1), last)).nonzero().squeeze(1)
        gid, tx, ty = gid.index_select(0, meets), tx.index_select(0, meets), ty.index_select(0, meets)
    if gid.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return TileBins(empty, empty.reshape(0, 1), empty, torch.zeros(n, dtype=torch.bool, device=device))
    tile = ty * n_tx + tx
    binned = torch.zeros(n, dtype=torch.bool, device=device)
    binned[gid] = True
    rank = torch.empty(n, dtype=torch.int64, device=device)
    rank[torch.argsort(depth)] = torch.arange(n, device=device)
    order = torch.argsort(tile * n + rank.index_select(0, gid))
    tile, gid = tile.index_select(0, order), gid.index_select(0, order)
    tiles, per_tile = torch.unique_consecutive(tile, return_counts=True)
    n_tiles = tiles.numel()
    k = int(min(settings.max_per_tile, int(per_tile.max())))
    counts = per_tile.clamp_max(k)
    by_load = torch.argsort(counts, descending=True, stable=True)
    dest = torch.empty_like(by_load)  # output row of each tile
    dest[by_load] = torch.arange(n_tiles, device=device)
    tile_start = torch.cumsum(per_tile, 0) - per_tile
    row = torch.repeat_interleave(torch.arange(n_tiles, device=device), per_tile)
    pos = torch.arange(tile.numel(), device=device) - tile_start.index_select(0, row)
    # flat slot of each pair; pairs beyond the k front-most of their tile all go to a sink slot at the end
    slot = torch.where(pos < k, dest.index_select(0, row) * k + pos, n_tiles * k)
    index = torch.full((n_tiles * k + 1,), n, dtype=torch.int64, device=device)
    index[slot] = gid
    return TileBins(tiles[by_load], index[:-1].view(n_tiles, k), counts[by_load], binned)


def _append_zero_row(v: torch.Tensor) -> torch.Tensor:
    """``v`` (N, ...) with a zero row appended: the transparent dummy that pads the tile lists."""
    return torch.cat((v, v.new_zeros((1,) + v.shape[1:])))


class TorchRasterizer:
    """Tile-based rasterizer on PyTorch tensors (CPU or GPU); see the module docstring. With ``compiled`` (used
    for CPU tensors) projection, binning and compositing run in the numba kernels of
    :mod:`vigs_core.mapping.rasterizer_numba` instead of the torch reference: the same model and tiles, with 3DGS's
    early stop per pixel."""

    def __init__(self, settings: RenderSettings | None = None, compiled: bool = False) -> None:
        self.settings = settings or RenderSettings()
        self.compiled = compiled

    def __call__(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        T_CW: torch.Tensor,
        camera: RenderCamera,
    ) -> RenderOutput:
        compiled = self.compiled and means.device.type == "cpu"  # the kernels take CPU arrays; elsewhere torch
        if compiled:
            from vigs_core.mapping import rasterizer_numba
        s = self.settings
        dtype, device = means.dtype, means.device
        ts = s.tile_size
        n_tx = math.ceil(camera.width / ts)
        n_ty = math.ceil(camera.height / ts)
        P = ts * ts

        front = frustum_rows(means, scales, T_CW, camera, s, compiled)
        every = front.shape[0] == means.shape[0]  # culled already (the mapper's views): no gather to differentiate
        rows = (means, quats, scales) if every else tuple(x.index_select(0, front) for x in (means, quats, scales))
        if compiled:  # the projection fused with the conic, in one compiled loop each way
            mean2d, conic, z, cov2d = rasterizer_numba.ProjectGaussians.apply(*rows, T_CW, camera, s.eps2d)
        else:
            mean2d, cov2d, z = project_gaussians(*rows, T_CW, camera, s.eps2d)
            det = (cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2).clamp_min(1e-12)
            conic = torch.stack((cov2d[:, 2], -cov2d[:, 1], cov2d[:, 0]), -1) / det[:, None]
        opac = (opacities if every else opacities.index_select(0, front)).clamp(max=ALPHA_MAX)
        with torch.no_grad():
            reach = 2.0 * torch.log((255.0 * opac.detach()).clamp_min(1.0))  # d^2 where alpha hits 1/255
            half = torch.sqrt(reach[:, None] * cov2d[:, [0, 2]].detach())
            inside = (
                (reach > 0)
                & (mean2d[:, 0] + half[:, 0] >= -0.5)
                & (mean2d[:, 0] - half[:, 0] <= camera.width - 0.5)
                & (mean2d[:, 1] + half[:, 1] >= -0.5)
                & (mean2d[:, 1] - half[:, 1] <= camera.height - 0.5)
            )
            sel = inside.nonzero().squeeze(1)
        with torch.no_grad():
            if compiled:
                bins = rasterizer_numba.bin_gaussians(
                    *(x.index_select(0, sel) for x in (mean2d, half, z, conic, reach)), n_tx, n_ty, ts,
                    camera.width, camera.height, s.max_per_tile,
                )  # fmt: skip
            else:
                bins = bin_gaussians(
                    mean2d.detach()[sel], half[sel], z.detach()[sel], camera, s, conic.detach()[sel], reach[sel]
                )
        # one (N, 10) table [mean2d, conic, opacity, colour, z]; the compositing gathers its tile slots
        colors = colors if every else colors.index_select(0, front)
        table = torch.cat((mean2d, conic, opac[:, None], colors, z[:, None]), -1).index_select(0, sel)
        visible = front.index_select(0, sel[bins.binned])
        if compiled:   # flat tile lists: no padding slot
            color, depth, alpha = rasterizer_numba.CompositeTiles.apply(table, bins, n_tx, ts, camera.width,
                                                                        camera.height)
            return RenderOutput(color, depth, alpha, visible)
        table = _append_zero_row(table)   # the slot that pads the tile table's rows
        origin = torch.stack(((bins.tiles % n_tx) * ts, (bins.tiles // n_tx) * ts), -1).to(dtype)
        chunks = _tile_chunks(bins.counts.tolist(), P, s.chunk_pairs)
        layout = _TileLayout(bins.tiles, bins.index, n_tx, n_ty, ts, camera.width, camera.height, chunks)
        feats, alpha = _RasterizeTiles.apply(table, origin, _pixel_monomials(ts, dtype, device), layout)
        return RenderOutput(feats[..., :-1], feats[..., -1], alpha, visible)


def make_rasterizer(backend: str = "auto", settings: RenderSettings | None = None) -> Rasterizer:
    """The rasterizer named ``backend``: ``"torch"`` (reference), ``"numba"`` (the reference's model with compiled
    CPU kernels; tensors on another device take the reference's path), ``"gsplat"`` (CUDA only) or ``"auto"``
    (gsplat when CUDA and the gsplat package are available, else numba when installed, else the reference)."""
    if backend not in ("auto", "torch", "numba", "gsplat"):
        raise ValueError(f"rasterizer backend must be 'auto', 'torch', 'numba' or 'gsplat', got {backend!r}")
    if backend in ("auto", "gsplat"):
        from vigs_core.mapping.gsplat_backend import GsplatRasterizer, gsplat_available

        if gsplat_available():
            return GsplatRasterizer(settings)
        if backend == "gsplat":
            raise RuntimeError("rasterizer backend 'gsplat' needs CUDA and the gsplat package; neither is usable here")
    compiled = backend in ("auto", "numba") and numba_available()
    if backend == "numba" and not compiled:
        raise RuntimeError("rasterizer backend 'numba' needs the numba package (requirements/runtime.txt)")
    return TorchRasterizer(settings, compiled=compiled)
