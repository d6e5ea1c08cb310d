"""Vectorised ray caster: images and exact depth of a :class:`~vigs_core.sim.scene.Scene` seen by a
:class:`~vigs_core.camera.CameraModel` (distortion included).

For pixel ``(u, v)`` the camera-frame ray is ``d_C = unproject(u, v)`` (z = 1, through the lens model),
so a hit at ray parameter ``t`` lies at depth ``Z = t`` exactly: the depth map is the ray parameter of
the centre ray of every pixel. World rays are ``o = t_WC``, ``d = R_WC d_C``; all pixels and all boxes
that can be seen (bounding-sphere culling against the field-of-view cone) are intersected at once,
the nearest hit wins (:meth:`Scene.intersect`). An object is only tested against the rays inside the
bounding rectangle of its projected corners on the normalised image plane (exact culling: the
perspective image of a convex box in front of the camera is the convex hull of its projected corners).

Shading is Lambertian with one fixed directional light, ``I = albedo * (a + (1 - a) max(0, n . l))``,
so a surface point keeps its brightness from every viewpoint (brightness constancy, as optical flow
assumes). Anti-aliasing: textures are box-prefiltered analytically with the pixel footprint
(:mod:`vigs_core.sim.texture`); ``supersample = s`` additionally averages ``s x s`` stratified rays per
pixel, which also smooths geometric edges.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from vigs_core.camera import CameraModel
from vigs_core.sim.scene import Scene
from vigs_core.sim.texture import SurfaceTextures


@dataclass(frozen=True)
class RenderConfig:
    """Renderer settings.

    Args:
        supersample: ``s x s`` rays per pixel (1 = centre ray only, textures still prefiltered).
        rgb: render colour (H, W, 3) instead of grey (H, W).
        ambient: share ``a`` of the light that does not depend on the surface orientation.
        light_dir: direction towards the light in the world (normalised internally), z up.
        chunk_rays: rays intersected at once (bounds memory: about 200 bytes per ray and visible box).
        device: torch device of the computation ("cpu" or "cuda").
    """

    supersample: int = 1
    rgb: bool = False
    ambient: float = 0.55
    light_dir: tuple[float, float, float] = (0.35, 0.25, 0.9)
    chunk_rays: int = 131072
    device: str = "cpu"


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        image: (H, W) or (H, W, 3) float32 intensities in [0, 1].
        depth: (H, W) float32 depth Z (m) of the pixel-centre ray in the camera frame ((0, 0) when not
            requested).
    """

    image: np.ndarray
    depth: np.ndarray


class Renderer:
    """Renders a scene through a camera model at given camera poses.

    Args:
        scene: the scene (moved to the configured device, float32).
        camera: camera model; images are ``camera.height x camera.width``.
        config: rendering settings.
        photos: optional grey photographs (H, W) used as textures on some surfaces (see
            :class:`~vigs_core.sim.texture.SurfaceTextures`).
    """

    def __init__(
        self,
        scene: Scene,
        camera: CameraModel,
        config: RenderConfig = RenderConfig(),
        photos: list[np.ndarray] | tuple[np.ndarray, ...] = (),
    ) -> None:
        if config.supersample < 1:
            raise ValueError(f"RenderConfig.supersample must be >= 1, got {config.supersample}")
        self.camera = camera
        self.config = config
        self.device = torch.device(config.device)
        self.dtype = torch.float32
        self.scene = scene.to(self.device, self.dtype)
        light = torch.tensor(config.light_dir, dtype=self.dtype, device=self.device)
        self.light = light / light.norm()
        grid = camera.pixel_grid(dtype=torch.float64).reshape(-1, 2)  # (H*W, 2) pixel centres
        self.centre_rays = camera.unproject(grid).to(self.device, self.dtype)  # (H*W, 3), z = 1
        # angular pixel size along each ray: |d(u + 1) - d(u)| (rays with z = 1)
        step = camera.unproject(grid + torch.tensor([1.0, 0.0], dtype=torch.float64)) - camera.unproject(grid)
        self.pixel_spread = step.norm(dim=1).to(self.device, self.dtype)  # (H*W,)
        s = config.supersample
        if s == 1:
            self.sample_rays = self.centre_rays[None]
        else:
            offsets = (torch.arange(s, dtype=torch.float64) + 0.5) / s - 0.5
            oy, ox = torch.meshgrid(offsets, offsets, indexing="ij")
            shifts = torch.stack((ox.reshape(-1), oy.reshape(-1)), dim=1)  # (s*s, 2)
            self.sample_rays = torch.stack([camera.unproject(grid + sh) for sh in shifts]).to(self.device, self.dtype)
        self.corners = self.scene.box_corners()  # (B, 8, 3) world
        self.textures = SurfaceTextures(scene.seed, 6 * scene.num_boxes, self.device, photos)

    def trace(
        self, T_WC: torch.Tensor | np.ndarray, rays_cam: torch.Tensor, spread: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Shade arbitrary camera rays.

        Args:
            T_WC: (4, 4) camera pose in the world.
            rays_cam: (N, 3) camera-frame rays (z = 1 for pixel rays; depth is the ray parameter).
            spread: (N,) footprint growth per unit ray parameter (texture prefilter width / distance).

        Returns:
            ``(values (N,) or (N, 3) float32 in [0, 1], t (N,) ray parameters)``.
        """
        T = torch.as_tensor(T_WC, dtype=torch.float64).to(self.device)
        rot = T[:3, :3].to(self.dtype)
        origin = T[:3, 3].to(self.dtype)
        values, depths = [], []
        for start in range(0, rays_cam.shape[0], self.config.chunk_rays):
            d_cam = rays_cam[start : start + self.config.chunk_rays]
            dirs = d_cam @ rot.T
            hit = self.scene.intersect(origin, dirs, self._candidates(rot, origin, d_cam))
            norm = dirs.norm(dim=1)
            cos = (hit.normal * dirs).sum(dim=1).abs() / norm
            footprint = hit.t * spread[start : start + d_cam.shape[0]] / cos.clamp_min(0.2)
            albedo = self.textures.evaluate(hit.uv, hit.surface, footprint, self.config.rgb)
            lambert = (hit.normal @ self.light).clamp_min(0.0)
            shade = self.config.ambient + (1.0 - self.config.ambient) * lambert
            values.append(albedo * (shade[:, None] if self.config.rgb else shade))
            depths.append(hit.t)
        return torch.cat(values), torch.cat(depths)

    def _candidates(self, rot: torch.Tensor, origin: torch.Tensor, d_cam: torch.Tensor) -> list[torch.Tensor | None]:
        """Per box, the rays (indices into ``d_cam`` (N, 3), z > 0) that can hit it; None = all rays."""
        corners = (self.corners - origin) @ rot  # (B, 8, 3) camera frame: R_WC^T (p - t_WC)
        z = corners[..., 2]
        in_front = z > 1e-6
        rx = d_cam[:, 0] / d_cam[:, 2]
        ry = d_cam[:, 1] / d_cam[:, 2]
        empty = torch.zeros(0, dtype=torch.long, device=d_cam.device)
        out: list[torch.Tensor | None] = [None]
        for b in range(1, corners.shape[0]):
            if not bool(in_front[b].any()):
                out.append(empty)
            elif not bool(in_front[b].all()):
                out.append(None)
            else:
                x = corners[b, :, 0] / z[b]
                y = corners[b, :, 1] / z[b]
                mask = (rx >= x.min()) & (rx <= x.max()) & (ry >= y.min()) & (ry <= y.max())
                out.append(torch.nonzero(mask)[:, 0])
        return out

    def depth(self, T_WC: torch.Tensor | np.ndarray) -> np.ndarray:
        """(H, W) float32 depth map (m) of the pixel-centre rays (geometry only, no shading)."""
        T = torch.as_tensor(T_WC, dtype=torch.float64).to(self.device)
        rot = T[:3, :3].to(self.dtype)
        origin = T[:3, 3].to(self.dtype)
        t = []
        for s in range(0, self.centre_rays.shape[0], self.config.chunk_rays):
            d_cam = self.centre_rays[s : s + self.config.chunk_rays]
            t.append(self.scene.intersect(origin, d_cam @ rot.T, self._candidates(rot, origin, d_cam)).t)
        return torch.cat(t).reshape(self.camera.height, self.camera.width).cpu().numpy()

    def render(self, T_WC: torch.Tensor | np.ndarray, with_depth: bool = True) -> RenderOutput:
        """Render the view from camera pose ``T_WC`` (4, 4) (camera frame: x right, y down, z forward)."""
        s2 = self.sample_rays.shape[0]
        spread = self.pixel_spread / self.config.supersample
        acc = None
        depth = None
        for k in range(s2):
            values, t = self.trace(T_WC, self.sample_rays[k], spread)
            acc = values if acc is None else acc + values
            if s2 == 1:
                depth = t
        image = (acc / s2).reshape(self.camera.height, self.camera.width, *((3,) if self.config.rgb else ()))
        if with_depth:
            if depth is not None:
                depth_map = depth.reshape(self.camera.height, self.camera.width).cpu().numpy()
            else:
                depth_map = self.depth(T_WC)
        else:
            depth_map = np.zeros((0, 0), dtype=np.float32)
        return RenderOutput(image=image.cpu().numpy().astype(np.float32), depth=depth_map.astype(np.float32))
