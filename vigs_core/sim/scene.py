"""Analytic indoor scenes for the simulator: a room box seen from inside plus oriented boxes inside it.

Every surface is a face of a box, so a ray-scene intersection is the slab test (Kay & Kajiya,
"Ray tracing complex scenes", SIGGRAPH 1986) evaluated for all rays and all boxes at once:
for a box with centre ``c``, rotation ``R_WO`` and half extents ``h``, a world ray ``o + t d`` becomes
``o_l + t d_l`` with ``o_l = R_WO^T (o - c)``, ``d_l = R_WO^T d``; per axis the ray is inside the slab for
``t`` between ``(-h - o_l) / d_l`` and ``(h - o_l) / d_l``; the ray enters the box at the largest of the
per-axis entry values and leaves it at the smallest exit value. The camera is inside the room, so the
room is hit at its exit value; objects are hit at their entry value when it is positive and not past
the exit. The nearest hit over all boxes is the visible surface (a z-buffer over boxes).

Surfaces are numbered ``6 * box + 2 * axis + (1 if the face is at +h else 0)``; the texture of a surface
is a function of this id and the scene seed (see :mod:`vigs_core.sim.texture`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class SceneConfig:
    """How :func:`build_room_scene` lays out a room around a trajectory.

    Args:
        margin_xy: room walls lie this far (m) outside the trajectory's bounding box horizontally.
        margin_below: floor this far (m) below the lowest trajectory point.
        margin_above: ceiling this far (m) above the highest trajectory point.
        n_objects: number of boxes placed inside the room (fewer if no free space is found); None =
            ``object_density`` times the floor area, at least ``min_objects``.
        object_density: objects per square metre of floor when ``n_objects`` is None.
        min_objects: fewest objects when ``n_objects`` is None.
        clearance: minimum distance (m) between any trajectory point and any object.
        min_size: smallest object edge length (m).
        max_size: largest object edge length (m) (capped by the room size).
        pillar_fraction: share of the objects that are floor-to-ceiling pillars.
        max_tilt: largest roll/pitch (rad) of floating objects; floor objects and pillars only yaw.
    """

    margin_xy: float = 1.5
    margin_below: float = 1.0
    margin_above: float = 1.2
    n_objects: int | None = None
    object_density: float = 0.2
    min_objects: int = 10
    clearance: float = 0.5
    min_size: float = 0.3
    max_size: float = 1.6
    pillar_fraction: float = 0.2
    max_tilt: float = 0.4


@dataclass
class Scene:
    """A set of oriented boxes; box 0 is the room (seen from inside).

    Attributes:
        centers: (B, 3) box centres in the world (m).
        half_sizes: (B, 3) half edge lengths (m).
        rotations: (B, 3, 3) ``R_WO``, box axes in the world.
        seed: texture seed of the scene.
    """

    centers: torch.Tensor
    half_sizes: torch.Tensor
    rotations: torch.Tensor
    seed: int

    def __post_init__(self) -> None:
        b = self.centers.shape[0]
        if self.centers.shape != (b, 3) or self.half_sizes.shape != (b, 3) or self.rotations.shape != (b, 3, 3):
            raise ValueError(
                f"Scene: expected centers (B,3), half_sizes (B,3), rotations (B,3,3); got "
                f"{tuple(self.centers.shape)}, {tuple(self.half_sizes.shape)}, {tuple(self.rotations.shape)}"
            )
        if b < 1:
            raise ValueError("Scene: needs at least the room box")

    @property
    def num_boxes(self) -> int:
        return self.centers.shape[0]

    def to(self, device: torch.device | str, dtype: torch.dtype) -> "Scene":
        return Scene(
            self.centers.to(device, dtype),
            self.half_sizes.to(device, dtype),
            self.rotations.to(device, dtype),
            self.seed,
        )

    def intersect(
        self, origin: torch.Tensor, dirs: torch.Tensor, candidates: list[torch.Tensor | None] | None = None
    ) -> "Hit":
        """Nearest surface along rays from one origin.

        Args:
            origin: (3,) ray origin in the world (m), inside the room.
            dirs: (N, 3) world ray directions (any length; ``t`` is measured in units of ``|d|``).
            candidates: optional per-box ray selection, one entry per box (entry 0, the room, is ignored):
                ``None`` tests all rays against that box, a (M,) long tensor tests only those rays, an
                empty tensor skips the box. Rays left out must not be able to hit the box (culling).

        Returns:
            :class:`Hit` with ``t`` (N,) such that the hit point is ``origin + t * dirs``.
        """
        n = dirs.shape[0]
        o_l = torch.einsum("bji,bj->bi", self.rotations, origin[None, :] - self.centers)  # (B, 3) = R^T (o - c)
        t_best = self._slab(o_l[0], dirs @ self.rotations[0], self.half_sizes[0])[1]  # room: exit
        box_best = torch.zeros(n, dtype=torch.long, device=dirs.device)
        for b in range(1, self.num_boxes):
            sel = None if candidates is None else candidates[b]
            if sel is not None and sel.numel() == 0:
                continue
            d_sub = dirs if sel is None else dirs[sel]
            t_enter, t_exit = self._slab(o_l[b], d_sub @ self.rotations[b], self.half_sizes[b])
            t_obj = torch.where((t_enter > 0) & (t_enter <= t_exit), t_enter, torch.full_like(t_enter, math.inf))
            if sel is None:
                closer = t_obj < t_best
                t_best = torch.where(closer, t_obj, t_best)
                box_best = torch.where(closer, b, box_best)
            else:
                closer = t_obj < t_best[sel]
                idx = sel[closer]
                t_best[idx] = t_obj[closer]
                box_best[idx] = b
        rot = self.rotations[box_best]  # (N, 3, 3)
        half = self.half_sizes[box_best]
        d_l = torch.einsum("nji,nj->ni", rot, dirs)
        p_l = o_l[box_best] + t_best[:, None] * d_l  # (N, 3) hit point in the box frame
        axis = (p_l.abs() / half).argmax(dim=1)
        coord = p_l.gather(1, axis[:, None])[:, 0]
        positive = coord > 0
        surface = 6 * box_best + 2 * axis + positive.long()
        sign = torch.where(positive, 1.0, -1.0).to(p_l.dtype)
        sign = torch.where(box_best == 0, -sign, sign)  # the room's faces point inwards
        normal = rot.gather(2, axis[:, None, None].expand(n, 3, 1))[:, :, 0] * sign[:, None]
        # face coordinates (m): the two box-frame coordinates other than the face axis, in a fixed order
        u_axis = torch.where(axis == 0, 1, 0)
        v_axis = torch.where(axis == 2, 1, 2)
        uv = torch.stack([p_l.gather(1, u_axis[:, None])[:, 0], p_l.gather(1, v_axis[:, None])[:, 0]], dim=1)
        return Hit(t=t_best, surface=surface, normal=normal, uv=uv)

    @staticmethod
    def _slab(o_l: torch.Tensor, d_l: torch.Tensor, half: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Entry and exit ray parameters (N,), (N,) of rays ``o_l + t d_l`` (box frame) through a box."""
        tiny = torch.finfo(d_l.dtype).tiny
        d_safe = torch.where(d_l.abs() < tiny, torch.full_like(d_l, tiny), d_l)
        t_a = (-half - o_l) / d_safe
        t_b = (half - o_l) / d_safe
        return torch.minimum(t_a, t_b).amax(dim=1), torch.maximum(t_a, t_b).amin(dim=1)

    def box_corners(self) -> torch.Tensor:
        """(B, 8, 3) world coordinates of the box corners."""
        signs = torch.tensor(
            [[sx, sy, sz] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for sz in (-1.0, 1.0)],
            dtype=self.centers.dtype,
            device=self.centers.device,
        )
        local = signs[None] * self.half_sizes[:, None, :]  # (B, 8, 3)
        return self.centers[:, None, :] + torch.einsum("bij,bkj->bki", self.rotations, local)


@dataclass
class Hit:
    """Ray-scene intersection results, one row per ray.

    Attributes:
        t: (N,) ray parameter of the hit (hit point = origin + t * dir).
        surface: (N,) long surface id ``6 * box + 2 * axis + (face at +h)``.
        normal: (N, 3) unit surface normal in the world, facing the inside of the room / out of objects.
        uv: (N, 2) metric face coordinates (m) in the box frame.
    """

    t: torch.Tensor
    surface: torch.Tensor
    normal: torch.Tensor
    uv: torch.Tensor


def _rotation_zyx(yaw: float, pitch: float, roll: float) -> np.ndarray:
    cy, sy = math.cos(yaw), math.sin(yaw)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def _box_distance(points: np.ndarray, center: np.ndarray, half: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """(N,) Euclidean distance (m) from points (N, 3) to a solid oriented box (0 inside)."""
    local = (points - center) @ rot
    outside = np.maximum(np.abs(local) - half, 0.0)
    return np.linalg.norm(outside, axis=1)


def build_room_scene(positions: np.ndarray, seed: int = 0, config: SceneConfig = SceneConfig()) -> Scene:
    """A room enclosing a trajectory, with objects placed off the trajectory.

    The room is the trajectory's axis-aligned bounding box grown by the margins. Objects are drawn
    (deterministically from ``seed``) as floor-standing boxes, floor-to-ceiling pillars and floating tilted
    boxes; a candidate is rejected when it comes closer than ``clearance`` to any trajectory point.

    Args:
        positions: (N, 3) camera (or body) positions in the world (m), z up.
        seed: scene seed (layout and textures).
        config: layout settings.

    Returns:
        The :class:`Scene` (float64, CPU).
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if len(positions) == 0:
        raise ValueError("build_room_scene: needs at least one trajectory position")
    lo = positions.min(axis=0) - np.array([config.margin_xy, config.margin_xy, config.margin_below])
    hi = positions.max(axis=0) + np.array([config.margin_xy, config.margin_xy, config.margin_above])
    centers = [(lo + hi) / 2]
    halves = [(hi - lo) / 2]
    rots = [np.eye(3)]
    rng = np.random.default_rng([seed, 1])
    # keep candidate tests cheap on long trajectories
    probe = positions[:: max(1, len(positions) // 2000)]
    room_size = hi - lo
    max_size = min(config.max_size, 0.5 * float(room_size[:2].min()))
    n_objects = config.n_objects
    if n_objects is None:
        n_objects = max(config.min_objects, int(round(config.object_density * float(room_size[0] * room_size[1]))))
    n_pillars = int(round(config.pillar_fraction * n_objects))
    placed, attempts = 0, 0
    while placed < n_objects and attempts < 400 * max(1, n_objects):
        attempts += 1
        kind = "pillar" if placed < n_pillars else ("floor" if rng.random() < 0.6 else "floating")
        size = rng.uniform(config.min_size, max(config.min_size, max_size), size=3)
        yaw = rng.uniform(-math.pi, math.pi)
        pitch = roll = 0.0
        xy = rng.uniform(lo[:2], hi[:2])
        if kind == "pillar":
            size[:2] = rng.uniform(config.min_size, max(config.min_size, 0.6 * max_size), size=2)
            size[2] = room_size[2]
            z = lo[2] + size[2] / 2
        elif kind == "floor":
            z = lo[2] + size[2] / 2
        else:
            z = rng.uniform(lo[2] + size[2] / 2, hi[2] - size[2] / 2)
            pitch, roll = rng.uniform(-config.max_tilt, config.max_tilt, size=2)
        center = np.array([xy[0], xy[1], z])
        rot = _rotation_zyx(yaw, pitch, roll)
        if _box_distance(probe, center, size / 2, rot).min() < config.clearance:
            continue
        centers.append(center)
        halves.append(size / 2)
        rots.append(rot)
        placed += 1
    return Scene(
        torch.tensor(np.array(centers)), torch.tensor(np.array(halves)), torch.tensor(np.array(rots)), int(seed)
    )
