"""Procedural, anti-aliased surface textures evaluated at ray hit points.

Every surface carries a sum of layers defined on its metric face coordinates ``(u, v)`` (m):

* *mosaic* layers: a grid of cells of size ``s`` with an independent random grey value per cell, so
  there are high-contrast corners at every cell corner;
* *value-noise* layers (Perlin, "An image synthesizer", SIGGRAPH 1985, value variant): random values at
  the lattice points blended with the smoothstep ``3f^2 - 2f^3``, from 2 m down to 7 mm cells (fBm).

Each layer's grid is rotated by its own per-surface angle, its cell size is a per-surface multiple of a
per-surface base size, and its lattice values are read from a 1024 x 1024 table of random values at a
per-surface, per-layer offset. A single layer therefore repeats only after 1024 cells, and as the layers
have incommensurate sizes and orientations their sum does not repeat at any scale the camera sees.

Anti-aliasing is analytic (box prefiltering, cf. Heckbert, "Fundamentals of texture mapping", 1989):
with the pixel footprint ``w`` (in cells), the box-filtered step between neighbouring mosaic cells is
the linear ramp ``clamp((x + w/2 - x_edge) / w, 0, 1)``, which replaces the hard step; a layer whose
cells approach the pixel size fades to its mean (0.5) before it could alias. The colour of a surface
(``rgb=True``) is a per-surface tint modulated by the grey pattern and a low-frequency hue layer.

Optional photographs (e.g. real camera frames) cover a share of the surfaces: a photo spans
``photo_size_m`` on the face, tiled with mirroring (no seams), sampled bilinearly from the mip level
whose texel is at least the pixel footprint (Williams, "Pyramidal parametrics", SIGGRAPH 1983), and
blended with the procedural pattern, which keeps detail finer than the photo's texels.
"""
from __future__ import annotations

import math

import numpy as np
import torch

TABLE_SIZE = 1024

# layer table: (kind, cell size as a multiple of the surface's base cell size s0, amplitude)
# kind 0 = mosaic (sharp cells), 1 = value noise (smooth)
LAYERS = (
    (0, 1.0, 0.50),
    (0, 0.30, 0.32),
    (0, 0.09, 0.20),
    (1, 4.0, 0.30),
    (1, 0.15, 0.18),
    (1, 0.03, 0.12),
)
_HUE_LAYER_SCALE = 2.0  # cell of the colour variation layer, in units of s0


class SurfaceTextures:
    """Texture parameters of all surfaces of a scene (deterministic in ``seed``).

    Args:
        seed: scene seed.
        num_surfaces: number of surface ids (6 per box).
        device: torch device of the tables.
        photos: optional grey photographs, each (H, W) uint8 or float in [0, 1], all the same size.
        photo_fraction: share of the surfaces covered by a photo (when photos are given).
        photo_size_m: width (m) a photo spans on a surface.
    """

    def __init__(
        self,
        seed: int,
        num_surfaces: int,
        device: torch.device | str = "cpu",
        photos: list[np.ndarray] | tuple[np.ndarray, ...] = (),
        photo_fraction: float = 0.5,
        photo_size_m: float = 2.5,
    ) -> None:
        rng = np.random.default_rng([seed, 2])
        n_layers = len(LAYERS) + 3  # the grey layers plus one hue layer per colour channel
        table = rng.random((TABLE_SIZE, TABLE_SIZE), dtype=np.float32)  # lattice values [row j, column i]
        # the four corners of every lattice cell side by side, so a cell is one (4,) row: one gather per layer
        corners = [np.roll(table, shift, axis=(0, 1)) for shift in ((0, 0), (0, -1), (-1, 0), (-1, -1))]
        self.cells = torch.from_numpy(np.stack([c.reshape(-1) for c in corners], axis=1)).to(device)  # (T*T, 4)
        self.base_cell = torch.from_numpy(rng.uniform(0.22, 0.57, num_surfaces).astype(np.float32)).to(device)
        angles = rng.uniform(0.0, 2 * math.pi, (num_surfaces, n_layers))
        self.cos = torch.from_numpy(np.cos(angles).astype(np.float32)).to(device)  # (S, L)
        self.sin = torch.from_numpy(np.sin(angles).astype(np.float32)).to(device)
        self.offset = torch.from_numpy(rng.integers(0, TABLE_SIZE, (num_surfaces, n_layers, 2))).to(device)
        self.tint = torch.from_numpy(rng.uniform(0.55, 1.0, (num_surfaces, 3)).astype(np.float32)).to(device)
        self.photo_index = torch.full((num_surfaces,), -1, dtype=torch.long, device=device)
        self.mips: list[torch.Tensor] = []
        if len(photos):
            sizes = {np.asarray(p).shape for p in photos}
            if len(sizes) != 1 or len(next(iter(sizes))) != 2:
                raise ValueError(
                    f"SurfaceTextures: photos must be grey (H, W) images of one size, got shapes {sorted(sizes)}"
                )
            stack = np.stack([np.asarray(p, dtype=np.float32) for p in photos])
            if stack.max() > 1.0:
                stack = stack / 255.0
            covered = rng.random(num_surfaces) < photo_fraction
            choice = rng.integers(0, len(photos), num_surfaces)
            self.photo_index = torch.from_numpy(np.where(covered, choice, -1)).to(device)
            level = torch.from_numpy(stack).to(device)
            while True:
                self.mips.append(level)
                if min(level.shape[1:]) < 8:
                    break
                level = torch.nn.functional.avg_pool2d(level[:, None], 2, ceil_mode=True)[:, 0]
            self.photo_texel_m = photo_size_m / stack.shape[2]

    def _photo(self, uv: torch.Tensor, photo: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """Mip-mapped, mirrored-tiled bilinear photo lookup: (N,) values for rays with photo ids (N,)."""
        level = torch.log2((footprint / self.photo_texel_m).clamp_min(1.0)).ceil().long().clamp(max=len(self.mips) - 1)
        out = torch.empty(uv.shape[0], dtype=uv.dtype, device=uv.device)
        for lv in torch.unique(level).tolist():
            sel = torch.nonzero(level == lv)[:, 0]
            mip = self.mips[lv]
            n_img, h, w = mip.shape
            texel = self.photo_texel_m * (self.mips[0].shape[2] / w)
            x = uv[sel, 0] / texel - 0.5
            y = -uv[sel, 1] / texel - 0.5  # v up on the face, image rows down
            x0, y0 = torch.floor(x), torch.floor(y)
            fx, fy = x - x0, y - y0
            x0, y0 = x0.long(), y0.long()

            def mirror(i: torch.Tensor, n: int) -> torch.Tensor:
                m = torch.remainder(i, 2 * n)
                return torch.where(m < n, m, 2 * n - 1 - m)

            flat = mip.reshape(-1)
            base = photo[sel] * (h * w)
            xa, xb = mirror(x0, w), mirror(x0 + 1, w)
            ya, yb = mirror(y0, h) * w, mirror(y0 + 1, h) * w
            top = flat[base + ya + xa] * (1 - fx) + flat[base + ya + xb] * fx
            bottom = flat[base + yb + xa] * (1 - fx) + flat[base + yb + xb] * fx
            out[sel] = top * (1 - fy) + bottom * fy
        return out

    def _layer(
        self,
        uv: torch.Tensor,
        rows: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        layer: int,
        cell: torch.Tensor,
        footprint: torch.Tensor,
        sharp: bool,
    ) -> torch.Tensor:
        """One anti-aliased lattice layer: (N,) values in [0, 1], faded to 0.5 where it would alias.

        Args:
            uv: (N, 2) face coordinates (m); rows: the per-ray (cos (N, L), sin (N, L), offset (N, L, 2))
            of the ray's surface; layer: layer index; cell: (N,) cell size (m); footprint: (N,) pixel
            footprint (m); sharp: mosaic or value noise.
        """
        ca = rows[0][:, layer]
        sa = rows[1][:, layer]
        x = (ca * uv[:, 0] - sa * uv[:, 1]) / cell
        y = (sa * uv[:, 0] + ca * uv[:, 1]) / cell
        w = footprint / cell
        if sharp:
            wc = w.clamp_min(1e-6)
            x0 = torch.floor(x - wc / 2)
            y0 = torch.floor(y - wc / 2)
            fx = ((x + wc / 2 - (x0 + 1)) / wc).clamp(0.0, 1.0)
            fy = ((y + wc / 2 - (y0 + 1)) / wc).clamp(0.0, 1.0)
            fade = (1.5 - w).clamp(0.0, 1.0)
        else:
            x0 = torch.floor(x)
            y0 = torch.floor(y)
            fx = x - x0
            fy = y - y0
            fx = fx * fx * (3 - 2 * fx)
            fy = fy * fy * (3 - 2 * fy)
            fade = (1.5 - 2.0 * w).clamp(0.0, 1.0)
        off = rows[2][:, layer]  # (N, 2)
        mask = TABLE_SIZE - 1
        i0 = (x0.to(torch.int64) + off[:, 0]) & mask
        j0 = (y0.to(torch.int64) + off[:, 1]) & mask
        # (N, 4): values at (i, j), (i+1, j), (i, j+1), (i+1, j+1)
        corners = self.cells.index_select(0, j0 * TABLE_SIZE + i0)
        h00, h10, h01, h11 = corners.unbind(dim=1)
        top = h00 + fx * (h10 - h00)
        bottom = h01 + fx * (h11 - h01)
        value = top + fy * (bottom - top)
        return 0.5 + fade * (value - 0.5)

    def evaluate(
        self, uv: torch.Tensor, surface: torch.Tensor, footprint: torch.Tensor, rgb: bool = False
    ) -> torch.Tensor:
        """Texture values of surfaces at hit points.

        Args:
            uv: (N, 2) float32 metric face coordinates (m).
            surface: (N,) long surface ids (see :mod:`vigs_core.sim.scene`).
            footprint: (N,) float32 pixel footprint on the surface (m per pixel).
            rgb: return colour (N, 3) instead of grey (N,).

        Returns:
            (N,) or (N, 3) float32 albedo in [0, 1].
        """
        s0 = self.base_cell[surface]
        rows = (self.cos[surface], self.sin[surface], self.offset[surface])
        total = torch.zeros(uv.shape[0], dtype=uv.dtype, device=uv.device)
        amp_sum = 0.0
        for layer, (kind, scale, amp) in enumerate(LAYERS):
            amp_sum += amp
            # a layer entirely below the pixel size contributes its mean (0 around 0.5)
            if float((footprint / (s0 * scale)).min()) >= (1.5 if kind == 0 else 0.75):
                continue
            total += amp * (self._layer(uv, rows, layer, s0 * scale, footprint, kind == 0) - 0.5)
        grey = (0.5 + 1.6 * total / amp_sum).clamp(0.02, 0.98)
        if self.mips:
            photo = self.photo_index[surface]
            on_photo = torch.nonzero(photo >= 0)[:, 0]
            if on_photo.numel():
                values = self._photo(uv[on_photo], photo[on_photo], footprint[on_photo])
                grey[on_photo] = (0.75 * values + 0.25 * grey[on_photo]).clamp(0.02, 0.98)
        if not rgb:
            return grey
        cell = s0 * _HUE_LAYER_SCALE
        hue = torch.stack(
            [self._layer(uv, rows, len(LAYERS) + c, cell, footprint, False) for c in range(3)], dim=1
        )
        return (grey[:, None] * self.tint[surface] * (0.7 + 0.6 * hue)).clamp(0.0, 1.0)
