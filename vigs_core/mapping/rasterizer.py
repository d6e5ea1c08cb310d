"""Differentiable Gaussian rasterizer: backend interface and the pure-PyTorch tile-based reference.

Design (3DGS, Kerbl et al. 2023, Sec. 4 and 6, written for CPU throughput in PyTorch):

1. **Projection** (plain autograd, O(N)). Camera-frame mean ``p = R_CW mu + t_CW``; pixel mean
   ``m = (fx x/z + cx, fy y/z + cy)``; 2D covariance ``Sigma' = J W Sigma W^T J^T + eps I`` with the
   projection Jacobian ``J = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]`` (EWA splatting, Zwicker 2002)
   and a low-pass ``eps = 0.3`` px^2; conic ``Q = Sigma'^-1 = [[a, b], [b, c]]``.
2. **Binning** (no gradient). A Gaussian touches the pixels where ``o exp(-d^2/2) >= 1/255``
   (``d`` Mahalanobis), i.e. ``d^2 <= 2 ln(255 o)``: the exact bounding box of that ellipse selects the
   tiles. (Gaussian, tile) pairs are sorted by tile then camera depth and each tile keeps its front-most
   ``K`` Gaussians (``K = min(max_per_tile, busiest tile)``), padded with a transparent dummy.
3. **Compositing** over (tiles T, pixels P, Gaussians K) in one custom autograd function
   (:class:`_RasterizeTiles`): the exponent ``power = -(1/2) (x - m)^T Q (x - m)`` is a quadratic form in
   the pixel, written as ``[x^2, xy, y^2, x, y, 1] . coef`` so a single batched matmul evaluates it for
   all pixels; ``alpha = min(o, 0.99) exp(power)`` (zero below 1/255), ``T_k = prod_{j<k} (1 - alpha_j)``,
   ``w_k = alpha_k T_k``, outputs ``sum_k w_k f_k`` for features ``f = (r, g, b, z)`` and accumulated
   opacity ``1 - prod_k (1 - alpha_k)``. The backward pass is analytic, which avoids autograd's slow
   cumprod backward and its zero-filled gradients of slices; tiles are processed busiest first in
   cache-sized chunks, each with its own ``K``.

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
        max_per_tile: at most this many front-most Gaussians are composited per tile (``K``).
        near: Gaussians closer than this camera depth (metres) are culled.
        eps2d: low-pass variance added to every 2D covariance, px^2 (3DGS uses 0.3).
        chunk_pairs: (pixel, Gaussian) pairs composited at once (bounds the working set: about 20 bytes
            each); tiles beyond it are processed in further chunks.
    """

    tile_size: int = 8
    max_per_tile: int = 96
    near: float = 0.05
    eps2d: float = 0.3
    chunk_pairs: int = 1 << 18


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

    Args of ``__call__``: ``means`` (N, 3) world, ``quats`` (N, 4) ``(w, x, y, z)``, ``scales`` (N, 3) metres,
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
    lim_x = 1.3 * (0.5 * camera.width / camera.fx)
    lim_y = 1.3 * (0.5 * camera.height / camera.fy)
    tx = (x * inv_z).clamp(-lim_x - camera.cx / camera.fx, lim_x + (camera.width - camera.cx) / camera.fx)
    ty = (y * inv_z).clamp(-lim_y - camera.cy / camera.fy, lim_y + (camera.height - camera.cy) / camera.fy)
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


def _pixel_monomials(tile_size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(P, 6) rows ``[x^2, xy, y^2, x, y, 1]`` of the tile-local pixel centres, row-major in the tile."""
    r = torch.arange(tile_size, dtype=dtype, device=device)
    y, x = torch.meshgrid(r, r, indexing="ij")
    x, y = x.reshape(-1), y.reshape(-1)
    return torch.stack((x * x, x * y, y * y, x, y, torch.ones_like(x)), -1)


def _composite_chunk(coef, opac, feat, mono):
    """Forward of :class:`_CompositeTiles` on one chunk of tiles: ``(out, acc, saved)``."""
    alpha = torch.matmul(mono, coef).exp_().mul_(opac[:, None, :])  # (T, P, K)
    torch.nn.functional.threshold_(alpha, ALPHA_MIN, 0.0)
    one_minus = 1.0 - alpha
    t_incl = torch.cumprod(one_minus, dim=2)  # T_{k+1}
    w = torch.empty_like(alpha)
    torch.sub(1.0, t_incl[:, :, :1], out=w[:, :, :1])
    torch.sub(t_incl[:, :, :-1], t_incl[:, :, 1:], out=w[:, :, 1:])
    # (C, K) @ (K, P) per tile: far faster in BLAS than (P, K) @ (K, C) with C = 4
    out = torch.bmm(feat.transpose(1, 2), w.transpose(1, 2)).transpose(1, 2)
    return out, 1.0 - t_incl[:, :, -1], (alpha, one_minus, t_incl, w)


@dataclass(frozen=True)
class _TileLayout:
    """Where the composited tiles go: ``tiles`` (T,) tile ids (row-major grid of ``n_ty x n_tx`` tiles of
    ``ts x ts`` px), the image size, and the compositing ``chunks`` (see :func:`_tile_chunks`)."""

    tiles: torch.Tensor
    n_tx: int
    n_ty: int
    ts: int
    width: int
    height: int
    chunks: list


def _slot_coefficients(slots: torch.Tensor, origin: torch.Tensor):
    """Quadratic-form coefficients (T, 6, K) of the tile slots and the tile-local means ``mx, my``.

    ``power = -(1/2) [dx, dy] Q [dx, dy]^T`` with ``dx = x - mx`` equals ``[x^2, xy, y^2, x, y, 1] . coef``,
    ``coef = (-a/2, -b, -c/2, a mx + b my, b mx + c my, -(a mx^2 + 2 b mx my + c my^2)/2)``."""
    mx = slots[..., 0] - origin[:, None, 0]
    my = slots[..., 1] - origin[:, None, 1]
    a, b, c = slots[..., 2], slots[..., 3], slots[..., 4]
    p = a * mx + b * my
    q = b * mx + c * my
    coef = torch.stack((-0.5 * a, -b, -0.5 * c, p, q, -0.5 * (mx * p + my * q)), 1)
    return coef, mx, my, p, q


class _RasterizeTiles(torch.autograd.Function):
    """Front-to-back alpha compositing of the K depth-sorted Gaussian slots of T tiles into an image.

    Input ``slots`` (T, K, 6 + F): per slot ``[u, v, a, b, c, o, f_1..f_F]`` (pixel mean, conic, opacity,
    features, here RGB and camera depth). Per tile, with ``power = mono @ coef`` (P, K) (see
    :func:`_slot_coefficients`), ``alpha = o exp(power)`` kept where ``>= 1/255`` (``o <= 0.99`` is clamped
    by the caller, so ``alpha <= 0.99``), ``T_k = prod_{j<k} (1 - alpha_j)``, ``w_k = alpha_k T_k =
    T_k - T_{k+1}``: features ``out = w @ f`` (P, F) and accumulated opacity ``acc = 1 - prod_k (1 - alpha_k)``.
    Returns the image ``(features (H, W, F), alpha (H, W))``.

    Backward (``g = dL/dout``, ``h = dL/dacc``, ``gf_k = g . f_k``, ``S_k = sum_{j>k} w_j gf_j``,
    ``T_end = prod_k (1 - alpha_k)``): ``dL/dalpha_k = (T_{k+1} gf_k - S_k + h T_end) / (1 - alpha_k)``;
    ``dL/dpower = alpha dL/dalpha`` (zero where alpha was cut), ``dL/do = sum_p dL/dpower / o``,
    ``dL/dcoef = mono^T dL/dpower``, ``dL/df = w^T g``, then the chain rule through ``coef`` to
    ``(u, v, a, b, c)``. Doing all of this in one function keeps autograd from materialising a
    zero-filled gradient per slice and view, which dominated the run time.

    The tiles are processed in chunks ``(start, end, k)`` (consecutive tiles, of which only the first
    ``k`` slots are used): chunks of about a megabyte stay in cache and in the allocator's heap, and
    tiles sorted by load (busiest first) waste little on padding.
    """

    @staticmethod
    def forward(ctx, slots, origin, mono, layout):
        T, P, F = slots.shape[0], mono.shape[0], slots.shape[2] - 6
        coef, mx, my, p, q = _slot_coefficients(slots, origin)
        opac, feat = slots[..., 5].contiguous(), slots[..., 6:].contiguous()
        tile_out = slots.new_zeros(layout.n_ty * layout.n_tx, P, F + 1)
        saved = []
        for a, b, k in layout.chunks:
            out, acc, kept = _composite_chunk(coef[a:b, :, :k], opac[a:b, :k], feat[a:b, :k], mono)
            rows = layout.tiles[a:b]
            tile_out[rows, :, :F] = out
            tile_out[rows, :, F] = acc
            saved.append(kept)
        ctx.save_for_backward(mono, opac, feat, mx, my, p, q, slots[..., 2:5])
        ctx.layout = layout
        ctx.saved_chunks = saved
        ts, H, W = layout.ts, layout.height, layout.width
        img = tile_out.reshape(layout.n_ty, layout.n_tx, ts, ts, F + 1).permute(0, 2, 1, 3, 4)
        img = img.reshape(layout.n_ty * ts, layout.n_tx * ts, F + 1)[:H, :W]
        return img[..., :F].contiguous(), img[..., F].contiguous()

    @staticmethod
    def backward(ctx, g_feat_img, g_alpha_img):
        mono, opac, feat, mx, my, p, q, conic = ctx.saved_tensors
        layout = ctx.layout
        ts, F = layout.ts, feat.shape[2]
        g_img = opac.new_zeros(layout.n_ty * ts, layout.n_tx * ts, F + 1)
        if g_feat_img is not None:
            g_img[: layout.height, : layout.width, :F] = g_feat_img
        if g_alpha_img is not None:
            g_img[: layout.height, : layout.width, F] = g_alpha_img
        g_tiles = g_img.reshape(layout.n_ty, ts, layout.n_tx, ts, F + 1).permute(0, 2, 1, 3, 4)
        g_tiles = g_tiles.reshape(layout.n_ty * layout.n_tx, ts * ts, F + 1)[layout.tiles]
        g_out, g_acc = g_tiles[..., :F].contiguous(), g_tiles[..., F].contiguous()
        d_coef = opac.new_zeros(opac.shape[0], 6, opac.shape[1])
        d_slots = opac.new_zeros(opac.shape[0], opac.shape[1], 6 + F)
        for (a, b, k), (alpha, one_minus, t_incl, w) in zip(layout.chunks, ctx.saved_chunks):
            g, f = g_out[a:b], feat[a:b, :k]
            gf = torch.bmm(g, f.transpose(1, 2))  # (T, P, K)
            wg = w * gf
            total = wg.sum(2, keepdim=True) - g_acc[a:b, :, None] * t_incl[:, :, -1:]
            suffix = wg.cumsum_(2)
            torch.sub(total, suffix, out=suffix)
            d_power = gf.mul_(t_incl).sub_(suffix).div_(one_minus).mul_(alpha)
            d_slots[a:b, :k, 5] = d_power.sum(1) / opac[a:b, :k].clamp_min(ALPHA_MIN)
            d_coef[a:b, :, :k] = torch.matmul(mono.T, d_power)  # (T, 6, K)
            d_slots[a:b, :k, 6:] = torch.bmm(g.transpose(1, 2), w).transpose(1, 2)
        d0, d1, d2, d3, d4, d5 = d_coef.unbind(1)
        a_, b_, c_ = conic.unbind(-1)
        d_slots[..., 0] = d3 * a_ + d4 * b_ - d5 * p
        d_slots[..., 1] = d3 * b_ + d4 * c_ - d5 * q
        d_slots[..., 2] = -0.5 * d0 + d3 * mx - 0.5 * d5 * mx * mx
        d_slots[..., 3] = -d1 + d3 * my + d4 * mx - d5 * mx * my
        d_slots[..., 4] = -0.5 * d2 + d4 * my - 0.5 * d5 * my * my
        return d_slots, None, None, None


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
    decreasing ``counts`` (T,) (Gaussians kept per tile), and ``index`` (T, K) Gaussian rows, front to back,
    padded with ``N`` (the transparent dummy)."""

    tiles: torch.Tensor
    index: torch.Tensor
    counts: torch.Tensor


def bin_gaussians(
    mean2d: torch.Tensor,
    half_extent: torch.Tensor,
    depth: torch.Tensor,
    camera: RenderCamera,
    settings: RenderSettings,
) -> TileBins:
    """Assign Gaussians to the tiles their bounding boxes ``mean2d +- half_extent`` (N, 2) touch and keep
    the front-most ``max_per_tile`` per tile, ordered by ``depth`` (N,). No gradient."""
    ts = settings.tile_size
    n_tx = math.ceil(camera.width / ts)
    n_ty = math.ceil(camera.height / ts)
    n = mean2d.shape[0]
    device = mean2d.device
    lo = torch.floor((mean2d - half_extent) / ts).long()
    hi = torch.floor((mean2d + half_extent) / ts).long()
    lo[:, 0].clamp_(0, n_tx - 1)
    lo[:, 1].clamp_(0, n_ty - 1)
    hi[:, 0].clamp_(0, n_tx - 1)
    hi[:, 1].clamp_(0, n_ty - 1)
    span = hi - lo + 1
    counts = span[:, 0] * span[:, 1]
    gid = torch.repeat_interleave(torch.arange(n, device=device), counts)
    if gid.numel() == 0:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return TileBins(empty, empty.reshape(0, 1), empty)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.numel(), device=device) - starts[gid]
    sx = span[gid, 0]
    tile = (lo[gid, 1] + local // sx) * n_tx + lo[gid, 0] + local % sx
    rank = torch.empty(n, dtype=torch.int64, device=device)
    rank[torch.argsort(depth)] = torch.arange(n, device=device)
    order = torch.argsort(tile * n + rank[gid])
    tile, gid = tile[order], gid[order]
    tiles, per_tile = torch.unique_consecutive(tile, return_counts=True)
    k = int(min(settings.max_per_tile, int(per_tile.max())))
    tile_start = torch.cumsum(per_tile, 0) - per_tile
    row = torch.repeat_interleave(torch.arange(tiles.numel(), device=device), per_tile)
    pos = torch.arange(tile.numel(), device=device) - tile_start[row]
    keep = pos < k
    index = torch.full((tiles.numel(), k), n, dtype=torch.int64, device=device)
    index[row[keep], pos[keep]] = gid[keep]
    counts = per_tile.clamp_max(k)
    by_load = torch.argsort(counts, descending=True, stable=True)
    return TileBins(tiles[by_load], index[by_load], counts[by_load])


def _append_zero_row(v: torch.Tensor) -> torch.Tensor:
    """``v`` (N, ...) with a zero row appended: the transparent dummy that pads the tile lists."""
    return torch.cat((v, v.new_zeros((1,) + v.shape[1:])))


class TorchRasterizer:
    """Pure-PyTorch tile-based reference rasterizer (CPU or GPU); see the module docstring."""

    def __init__(self, settings: RenderSettings | None = None) -> None:
        self.settings = settings or RenderSettings()

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
        s = self.settings
        dtype, device = means.dtype, means.device
        ts = s.tile_size
        n_tx = math.ceil(camera.width / ts)
        n_ty = math.ceil(camera.height / ts)
        P = ts * ts

        # Cheap pre-cull on the centres (no gradient): in front of the camera and projecting within
        # half an image of the image borders (the 3DGS frustum test with a margin).
        with torch.no_grad():
            p_cam = means.detach() @ T_CW[:3, :3].to(dtype).T + T_CW[:3, 3].to(dtype)
            z_all = p_cam[:, 2].clamp_min(1e-9)
            u = camera.fx * p_cam[:, 0] / z_all + camera.cx
            v = camera.fy * p_cam[:, 1] / z_all + camera.cy
            front = (
                (p_cam[:, 2] > s.near)
                & (u > -0.5 * camera.width)
                & (u < 1.5 * camera.width)
                & (v > -0.5 * camera.height)
                & (v < 1.5 * camera.height)
            )
            front = front.nonzero().squeeze(1)
        mean2d, cov2d, z = project_gaussians(
            means[front], quats[front], scales[front], T_CW, camera, s.eps2d
        )
        opac = opacities[front].clamp(max=ALPHA_MAX)
        det = (cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2).clamp_min(1e-12)
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
            # Tile pixel (i_t, j_t) of tile (ty, tx) is image pixel (ty*ts + i_t, tx*ts + j_t); its centre
            # is at u = tx*ts + j_t, so bin on the pixel-centre coordinate shifted by half a pixel.
            bins = bin_gaussians(mean2d.detach()[sel] + 0.5, half[sel], z.detach()[sel], camera, s)
        conic = torch.stack((cov2d[:, 2], -cov2d[:, 1], cov2d[:, 0]), -1) / det[:, None]
        # one (N + 1, 10) table [mean2d, conic, opacity, colour, z] gathered per tile slot in one go
        table = torch.cat((mean2d, conic, opac[:, None], colors[front], z[:, None]), -1)
        table = _append_zero_row(table.index_select(0, sel))

        T = bins.tiles.numel()
        slots = table.index_select(0, bins.index.reshape(-1)).reshape(T, bins.index.shape[1], table.shape[1])
        origin = torch.stack(((bins.tiles % n_tx) * ts, (bins.tiles // n_tx) * ts), -1).to(dtype)
        chunks = _tile_chunks(bins.counts.tolist(), P, s.chunk_pairs)
        layout = _TileLayout(bins.tiles, n_tx, n_ty, ts, camera.width, camera.height, chunks)
        feats, alpha = _RasterizeTiles.apply(slots, origin, _pixel_monomials(ts, dtype, device), layout)
        return RenderOutput(feats[..., :-1], feats[..., -1], alpha, front[sel])


def make_rasterizer(backend: str = "auto", settings: RenderSettings | None = None) -> Rasterizer:
    """The rasterizer named ``backend``: ``"torch"`` (reference), ``"gsplat"`` (CUDA only) or ``"auto"``
    (gsplat when CUDA and the gsplat package are available, else the reference)."""
    if backend not in ("auto", "torch", "gsplat"):
        raise ValueError(f"rasterizer backend must be 'auto', 'torch' or 'gsplat', got {backend!r}")
    if backend in ("auto", "gsplat"):
        from vigs_core.mapping.gsplat_backend import GsplatRasterizer, gsplat_available

        if gsplat_available():
            return GsplatRasterizer(settings)
        if backend == "gsplat":
            raise RuntimeError("rasterizer backend 'gsplat' needs CUDA and the gsplat package; neither is usable here")
    return TorchRasterizer(settings)
