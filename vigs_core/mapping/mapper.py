"""Online Gaussian-splatting mapper (VIGS-SLAM Sec. 3.3).

For every new keyframe (image, depth, pose ``T_WC``):

1. **Expansion / densification where the map is thin**: the current map is rendered at the keyframe; pixels
   whose accumulated opacity is below ``densify_alpha`` or whose measured depth lies clearly in front of
   the rendered surface (``d < (1 - densify_depth_ratio) depth/alpha``) are unprojected into new Gaussians
   anchored to the keyframe (:func:`vigs_core.mapping.init.gaussians_from_depth`; all pixels for the
   first keyframe).
2. **Optimisation**: ``iterations`` (N = 10) Adam steps, each rendering one keyframe of the schedule
   ``[new] + shuffle(local window + global_keyframes random older ones)`` (cycled), with the loss

       L = lambda_c |C - C_gt|_1 + lambda_d |D - D_gt|_1 (valid depth only) + lambda_iso |s - mean(s)|_1

   (means over pixels; the isotropic term over the visible Gaussians' scales ``s`` (metres) penalises
   needle-like Gaussians). Poses are fixed: the tracker owns them. Each step renders and differentiates
   only the Gaussians that can reach the view (:func:`vigs_core.mapping.rasterizer.frustum_rows`, the
   same image as rendering all), so its cost follows the Gaussians in view, not the size of the map.
3. **Pruning**: Gaussians with opacity below ``prune_min_opacity`` or whose largest standard deviation
   exceeds ``prune_max_angular`` times their distance to their anchor keyframe (oversized) are removed.
4. **Keyframe culling** (ours, for long missions): a keyframe whose view the map already covered (new Gaussians
   at no more than ``cull_max_new_fraction`` of its pixels in step 1) and that lies near a kept keyframe (within
   ``cull_baseline`` times its median depth and ``cull_rotation_deg``) is released once it leaves the local
   window: its Gaussians are re-anchored to that keyframe and its pixels dropped. A kept keyframe is never
   released, so on a revisited scene the keyframes, the spilled pixels and the schedule's draws stay bounded
   by the places seen, not by the time spent (as ORB-SLAM culls keyframes that others already cover).

Keyframe pose/scale corrections move anchored Gaussians in one batch (:mod:`vigs_core.mapping.anchor`).
The mapper is fed through an inbox (:mod:`vigs_core.mapping.inbox`): :meth:`GaussianMapper.add_keyframe` and
:meth:`GaussianMapper.update_keyframe_poses` only enqueue, so tracking never waits for mapping; pose corrections
are folded into one batch, applied before the next keyframe; keyframes are inserted in order by
:meth:`GaussianMapper.step` (synchronous use) or by the worker thread of :meth:`GaussianMapper.run_async`. A live
mapper that falls behind (``max_backlog``) keeps up with the newest keyframes: older ones are deferred to when
nothing else waits, and a keyframe's steps stop while the queue is full; with ``refine_when_idle`` it spends the
time when nothing waits on further optimisation steps. Rendering and saving take the map lock between
optimisation steps.
"""
from __future__ import annotations

import contextlib
import math
import random
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from vigs_core.geometry import relative_rotation_cosines, se3_inverse
from vigs_core.heap import retain_freed_heap
from vigs_core.mapping.anchor import anchored_update
from vigs_core.mapping.gaussians import PARAMETER_FIELDS, GaussianMap
from vigs_core.mapping.inbox import MapperInbox
from vigs_core.mapping.init import gaussians_from_depth
from vigs_core.mapping.metrics import psnr, ssim
from vigs_core.mapping.optimizer import RowAdam
from vigs_core.mapping.ply import save_map
from vigs_core.mapping.rasterizer import RenderCamera, RenderOutput, RenderSettings, frustum_rows, make_rasterizer
from vigs_core.ranges import bounded
from vigs_core.spill import SpillConfig, SpillStore


@dataclass
class MapperConfig:
    """Settings of :class:`GaussianMapper` (defaults: VIGS-SLAM's 10 iterations per keyframe, spread more widely
    over older keyframes than its local window; CPU-sized resolution).

    Args:
        iterations: optimisation steps per new keyframe (N).
        window: size of the local window of most recent keyframes (including the new one).
        global_keyframes: random keyframes from outside the window added to each schedule. Over a whole
            sequence a map optimised mostly on its newest keyframes forgets the older views; a short window and
            more random keyframes at the same ``iterations`` keep them (docs/benchmarks.md, issue 23).
        render_scale: rendering/optimisation resolution relative to the keyframe images (1: the frontend's processing
            resolution, 376x240 for EuRoC, at which both ``vigs run`` and the mapper node map and evaluate).
        init_stride: pixel stride (at render resolution) when unprojecting depth into Gaussians.
        init_scale: initial standard deviation in pixel spacings (see ``gaussians_from_depth``).
        lambda_color: weight of the L1 colour term.
        lambda_depth: weight of the L1 depth term (metres) on the steps of a new keyframe's local window.
        lambda_depth_revisit: weight of the depth term on the steps that revisit older keyframes (the random
            ones from outside the window, the idle steps). Their depth was imposed while they were in the window;
            colour alone then keeps their views without pulling the surfaces back to the frontend's coarse depth
            grid, as the final refinement does (docs/benchmarks.md, issue 23).
        lambda_iso: weight of the isotropic regulariser.
        lr_means: Adam step for means, metres.
        lr_log_scales: Adam step for log scales.
        lr_quats: Adam step for quaternions.
        lr_opacity: Adam step for opacity logits.
        lr_colors: Adam step for RGB colours.
        densify_alpha: pixels of a new keyframe rendering less opaque than this get new Gaussians.
        densify_depth_ratio: pixels whose measured depth is this fraction in front of the map get new Gaussians.
        prune_min_opacity: Gaussians less opaque than this are removed.
        prune_max_angular: Gaussians larger than this (std / distance to the anchor keyframe, rad) are removed.
        backend: rasterizer backend (:func:`~vigs_core.mapping.rasterizer.make_rasterizer`): "auto" (gsplat on CUDA,
            else the compiled CPU kernels), "torch" (the pure-PyTorch reference), "numba" or "gsplat". The numba
            backend also takes Adam's compiled step (:class:`~vigs_core.mapping.optimizer.RowAdam` ``compiled``).
        tile_size: tile edge of the reference rasterizer, pixels.
        max_per_tile: Gaussians composited per tile at most, the front-most (the torch and numba backends; gsplat
            has no cap). A whole sequence's map puts hundreds of Gaussians on many tiles, and a cap that cuts the
            far ones of a tile whose front ones are not yet opaque leaves it dark, in the renders and in the
            gradients (96 cost 2.5-4 dB on whole sequences; docs/benchmarks.md, issue 23).
        seed: seed of the keyframe sampler.
        retain_heap: keep freed heap memory in the process (see :func:`vigs_core.heap.retain_freed_heap`; glibc
            only, process-wide) instead of returning it to the kernel after every step.
        max_backlog: keyframes queued at most (:class:`vigs_core.mapping.inbox.MapperInbox`): older ones are
            deferred, mapped when nothing else waits (idle, or the shutdown drain); while the queue is full the
            keyframe being inserted gets no further optimisation steps. A live mapper that cannot keep up stays
            this far behind the newest keyframe. 0: every keyframe in order with its ``iterations`` however
            long the queue (offline runs).
        keyframe_store: where the keyframes' pixels live: the most recent in memory, older ones on disk
            (:class:`vigs_core.spill.SpillStore`); read back when the schedule or a refinement picks them.
        cull_keyframes: release covered keyframes near a kept one (step 4 of the module docstring; off: every
            keyframe is kept for the whole run).
        cull_max_new_fraction: a keyframe that got new Gaussians at more than this fraction of its pixels is kept.
        cull_baseline: distance to the nearest kept keyframe, in the keyframe's median depths, within which it
            may be released.
        cull_rotation_deg: rotation to that kept keyframe within which it may be released, degrees.
        refine_when_idle: the worker thread (:meth:`GaussianMapper.run_async`), when nothing is queued, keeps
            optimising, one step at a time on a keyframe drawn uniformly from the mapped ones, so CPU left
            over improves the map (a live mapper at low priority); off: it waits.
    """

    iterations: int = bounded(10, 0)
    window: int = bounded(3, 1)
    global_keyframes: int = bounded(6, 0)
    render_scale: float = bounded(1.0, 0, 1, lo_open=True)
    init_stride: int = bounded(3, 1)
    init_scale: float = bounded(0.5, 0, lo_open=True)
    lambda_color: float = bounded(0.9, 0)
    lambda_depth: float = bounded(0.1, 0)
    lambda_depth_revisit: float = bounded(0.0, 0)
    lambda_iso: float = bounded(10.0, 0)
    lr_means: float = bounded(1e-3, 0)
    lr_log_scales: float = bounded(5e-3, 0)
    lr_quats: float = bounded(2e-3, 0)
    lr_opacity: float = bounded(5e-2, 0)
    lr_colors: float = bounded(5e-3, 0)
    densify_alpha: float = bounded(0.6, 0, 1)
    densify_depth_ratio: float = bounded(0.1, 0)
    prune_min_opacity: float = bounded(0.01, 0, 1)
    prune_max_angular: float = bounded(0.1, 0)
    backend: str = "auto"
    tile_size: int = bounded(8, 1)
    max_per_tile: int = bounded(2048, 1)
    seed: int = 0
    retain_heap: bool = True
    max_backlog: int = bounded(0, 0)
    refine_when_idle: bool = False
    cull_keyframes: bool = True
    cull_max_new_fraction: float = bounded(0.05, 0, 1)
    cull_baseline: float = bounded(0.1, 0)
    cull_rotation_deg: float = bounded(10.0, 0, 180)
    keyframe_store: SpillConfig = field(default_factory=SpillConfig)

    def __post_init__(self) -> None:
        if self.iterations < 0 or self.window < 1 or self.global_keyframes < 0 or self.max_backlog < 0:
            raise ValueError(
                f"need iterations >= 0, window >= 1, global_keyframes >= 0, max_backlog >= 0; got "
                f"{self.iterations}, {self.window}, {self.global_keyframes}, {self.max_backlog}"
            )
        if not 0 < self.render_scale <= 1:
            raise ValueError(f"render_scale must be in (0, 1], got {self.render_scale}")


_IDLE_PAUSE_S = 0.01   # between idle steps (GaussianMapper._work)
_READER_POLL_S = 2e-4  # the worker's poll while a reader waits for the map lock (GaussianMapper._let_readers_in)


@dataclass
class Keyframe:
    """A keyframe as the mapper keeps it: pose (4, 4) float64 and its pixels in the mapper's :class:`SpillStore`
    under its id, at render resolution: RGB (h, w, 3) uint8 and depth (h, w) float32 metres (0 where invalid),
    the stored depth times ``depth_scale`` (loop corrections rescale it without rewriting the pixels). The store
    keeps the most recent keyframes in memory and the rest on disk, so long runs stay small."""

    id: int
    T_WC: torch.Tensor
    pixels: SpillStore
    device: torch.device
    timestamp_ns: int | None = None
    depth_scale: float = 1.0

    def image(self) -> torch.Tensor:
        """(h, w, 3) float32 RGB in [0, 1]."""
        return torch.from_numpy(self.pixels.get(self.id)[0]).to(self.device, torch.float32) / 255.0

    @property
    def depth(self) -> torch.Tensor:
        """(h, w) float32 metres (a new tensor)."""
        return torch.from_numpy(self.pixels.get(self.id)[1]).to(self.device) * self.depth_scale


@dataclass
class MapDelta:
    """Changes since the previous :meth:`GaussianMapper.pop_delta`: Gaussians ``added`` and ``changed``
    (full current rows) and the persistent ids of those ``removed``."""

    added: GaussianMap
    changed: GaussianMap
    removed_ids: torch.Tensor


@dataclass
class MapperStats:
    """Counters of a mapper: keyframes integrated (``cut_short`` of them with fewer than ``iterations``
    optimisation steps: behind, or at shutdown), their optimisation ``steps``, seconds spent on them, steps taken
    while idle, Gaussians added/pruned, keyframes ``released`` (culled)."""

    keyframes: int = 0
    cut_short: int = 0
    steps: int = 0
    idle_steps: int = 0
    mapping_seconds: float = 0.0
    added: int = 0
    pruned: int = 0
    pose_updates: int = 0
    released: int = 0
    ignored_pose_ids: list[int] = field(default_factory=list)


@dataclass
class MapperSummary:
    """What a run reports of its mapper (:meth:`GaussianMapper.summary`, also across a process boundary):
    counters, Gaussians, the render size ``(w, h)`` and the keyframe store's entries on disk and reads back."""

    stats: MapperStats
    gaussians: int
    render_size: tuple[int, int]
    keyframes_on_disk: int
    keyframe_disk_reads: int


def _prepare_image(image, size: tuple[int, int]) -> torch.Tensor:
    """(H, W) / (H, W, 1) / (H, W, 3) uint8 or float [0, 1] -> (h, w, 3) float32 at ``size = (w, h)``."""
    img = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    if img.dtype == np.uint8:
        img = img.astype(np.float32) / 255.0
    img = img.astype(np.float32)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"keyframe image must be (H, W), (H, W, 1) or (H, W, 3), got shape {img.shape}")
    if (img.shape[1], img.shape[0]) != size:
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(img))


def _prepare_depth(depth, size: tuple[int, int]) -> torch.Tensor:
    """(H, W) metres -> (h, w) float32 at ``size = (w, h)`` (nearest neighbour; invalid -> 0)."""
    d = depth.detach().cpu().numpy() if isinstance(depth, torch.Tensor) else np.asarray(depth)
    d = np.squeeze(d).astype(np.float32)
    if d.ndim != 2:
        raise ValueError(f"keyframe depth must be (H, W), got shape {np.shape(depth)}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    if (d.shape[1], d.shape[0]) != size:
        d = cv2.resize(d, size, interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy(np.ascontiguousarray(d))


class GaussianMapper:
    """The online mapper (see the module docstring).

    Args:
        config: :class:`MapperConfig`.
        camera: undistorted pinhole intrinsics of the keyframe images (``vigs_core.camera.CameraModel``
            with ``distortion == "none"``, or any object with width/height/fx/fy/cx/cy).
        device: torch device of the map.
    """

    def __init__(self, config: MapperConfig | None, camera, device: torch.device | str = "cpu") -> None:
        if getattr(camera, "distortion", "none") != "none":
            raise ValueError(
                f"GaussianMapper needs undistorted images and a pinhole camera, got distortion="
                f"{camera.distortion!r}; undistort the images and pass camera.pinhole()"
            )
        self.config = config or MapperConfig()
        if self.config.retain_heap:
            retain_freed_heap()
        self.camera = camera
        self.device = torch.device(device)
        self.render_camera = RenderCamera.from_camera(camera, self.config.render_scale)
        self.rasterizer = make_rasterizer(
            self.config.backend, RenderSettings(self.config.tile_size, self.config.max_per_tile)
        )
        c = self.config
        self.optimizer = RowAdam(
            {
                "means": c.lr_means,
                "log_scales": c.lr_log_scales,
                "quats": c.lr_quats,
                "opacity_logits": c.lr_opacity,
                "colors": c.lr_colors,
            },
            compiled=getattr(self.rasterizer, "compiled", False),  # the numba backend's Adam too; "torch": none
        )
        self.map = GaussianMap.empty(device=self.device)
        self.keyframes: dict[int, Keyframe] = {}
        self.pixel_store = SpillStore(self.config.keyframe_store, "mapper-keyframes")
        self.stats = MapperStats()
        self._next_id = 0
        self._rng = random.Random(c.seed)
        self._lock = threading.RLock()
        self._readers = 0   # threads waiting for the lock to read the map (:meth:`_reading`)
        self._readers_lock = threading.Lock()
        self._inbox = MapperInbox(self.config.max_backlog)
        self._worker: threading.Thread | None = None
        self._stop = threading.Event()
        self._new = torch.zeros(0, dtype=torch.bool, device=self.device)
        self._dirty = torch.zeros(0, dtype=torch.bool, device=self.device)
        self._removed: list[torch.Tensor] = []
        self._covered: dict[int, int] = {}   # keyframe to release when it leaves the window -> kept keyframe near it
        self._released: set[int] = set()

    # ------------------------------------------------------------------ public API: feeding
    def add_keyframe(self, kf_id: int, T_WC, image, depth, timestamp_ns: int | None = None) -> None:
        """Queue a keyframe: ``T_WC`` (4, 4), ``image`` (H, W[, 3]) uint8 or float [0, 1] RGB/grey, ``depth``
        (H', W') metres (0 or non-finite = invalid; any resolution, resampled to the render size)."""
        size = (self.render_camera.width, self.render_camera.height)
        kf_id = int(kf_id)
        self.pixel_store.put(kf_id, (_prepare_image(image, size) * 255.0).round_().to(torch.uint8).cpu().numpy(),
                         _prepare_depth(depth, size).cpu().numpy())
        kf = Keyframe(kf_id, torch.as_tensor(T_WC, dtype=torch.float64).reshape(4, 4).clone(), self.pixel_store,
                      self.device, timestamp_ns)
        self._inbox.put_keyframe(kf)

    def update_keyframe_poses(self, poses: dict[int, object], scales: dict[int, float] | None = None) -> None:
        """Queue corrected keyframe poses ``{kf_id: T_WC (4, 4)}`` and optional depth scale corrections
        ``{kf_id: s}``; anchored Gaussians follow (Eq. 6-7). Unknown ids are ignored (listed in ``stats``)."""
        poses = {int(k): torch.as_tensor(v, dtype=torch.float64).reshape(4, 4).clone() for k, v in poses.items()}
        self._inbox.put_poses(poses, {int(k): float(s) for k, s in (scales or {}).items()})

    def pending(self) -> int:
        """Number of events not yet applied: queued keyframes, plus one for pending pose corrections (deferred
        keyframes aside: :meth:`deferred`)."""
        return len(self._inbox)

    def deferred(self) -> int:
        """Keyframes set aside while the mapper was behind (``max_backlog``), not yet mapped."""
        return self._inbox.deferred()

    def step(self) -> bool:
        """Apply the next pending event (synchronous use); False when there was none."""
        event = self._inbox.take()
        if event is None:
            return False
        try:
            self._apply(event)
        finally:
            self._inbox.done()
        return True

    def process_pending(self) -> int:
        """Apply every queued event; returns how many."""
        count = 0
        while self.step():
            count += 1
        return count

    def drain(self, seconds: float, hurry: threading.Event | None = None) -> int:
        """At shutdown (worker stopped): apply the queued events within ``seconds`` (and until ``hurry`` is set,
        e.g. by the launcher's escalation to SIGTERM), each queued or deferred keyframe inserted from its depth
        without optimisation steps (one render for the densification mask instead of ``iterations`` steps), so
        the saved map holds every keyframe received, unrefined where there was no time to refine it. Returns
        how many events (deferred keyframes included) are left."""
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline and not (hurry is not None and hurry.is_set()):
            event = self._inbox.take()
            if event is None:
                break
            try:
                if event[0] == "keyframe":
                    self._integrate(event[1], optimise=False)
                else:
                    self._apply(event)
            finally:
                self._inbox.done()
        return self.pending() + self.deferred()

    def run_async(self) -> None:
        """Start a worker thread that applies queued events as they arrive (idempotent)."""
        if self._worker is not None and self._worker.is_alive():
            return
        self._stop.clear()
        self._worker = threading.Thread(target=self._work, name="gaussian-mapper", daemon=True)
        self._worker.start()

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until every queued event has been applied (by the worker or by :meth:`step`), or ``timeout``
        seconds passed; whether it has."""
        return self._inbox.wait_empty(timeout)

    def stop(self) -> None:
        """Stop the worker thread after the event it is applying, a keyframe's insertion cut short after the
        optimisation step in hand (queued events stay queued)."""
        self._stop.set()
        if self._worker is not None:
            self._worker.join()
            self._worker = None

    def close(self) -> None:
        """Stop the worker and remove the keyframe store's spill folder (the map stays readable)."""
        self.stop()
        self.pixel_store.close()

    # ------------------------------------------------------------------ public API: reading
    def summary(self) -> MapperSummary:
        """Counters and sizes for a report (a copy: the worker keeps counting)."""
        with self._reading():
            return MapperSummary(replace(self.stats, ignored_pose_ids=list(self.stats.ignored_pose_ids)),
                                 len(self.map), (self.render_camera.width, self.render_camera.height),
                                 len(self.pixel_store) - self.pixel_store.resident_count, self.pixel_store.reads)

    @torch.no_grad()
    def render(self, T_WC, scale: float | None = None) -> RenderOutput:
        """Render the map from ``T_WC`` (4, 4) at ``scale`` x the camera (default: the render scale).
        Colours are clamped to [0, 1]."""
        cam = self.render_camera if scale is None else RenderCamera.from_camera(self.camera, scale)
        with self._reading():
            out = self._render(self.map, torch.as_tensor(T_WC, dtype=torch.float64), cam)
        out.color = out.color.clamp(0.0, 1.0)
        return out

    def evaluate(self, views) -> dict:
        """Render quality on ``views``, an iterable of ``(T_WC (4, 4), image)`` (image as for
        :meth:`add_keyframe`; compared at the render resolution): ``{"psnr", "ssim", "frames"}`` (means, dB).
        Use frames that were not keyframes for the paper's protocol."""
        size = (self.render_camera.width, self.render_camera.height)
        p, s = [], []
        for T_WC, image in views:
            ref = _prepare_image(image, size).to(self.device)
            out = self.render(T_WC)
            p.append(psnr(out.color, ref))
            s.append(ssim(out.color, ref))
        if not p:
            return {"psnr": math.nan, "ssim": math.nan, "frames": 0}
        return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s)), "frames": len(p)}

    def snapshot(self) -> GaussianMap:
        """A detached copy of the current map."""
        with self._reading():
            return self.map.detached()

    def pop_delta(self) -> MapDelta:
        """Gaussians added / changed / removed since the previous call (added wins over changed)."""
        with self._reading():
            added = self.map.select(self._new)
            changed = self.map.select(self._dirty & ~self._new)
            removed = torch.cat(self._removed) if self._removed else torch.zeros(0, dtype=torch.int64)
            self._new.zero_()
            self._dirty.zero_()
            self._removed = []
        return MapDelta(added, changed, removed.cpu())

    def save(self, path: str | Path) -> Path:
        """Write the map as ``path`` (3DGS PLY) plus the keyframe sidecar; returns the sidecar path."""
        with self._reading():
            gmap = self.map.detached()
            poses = {k: kf.T_WC for k, kf in self.keyframes.items()}
            stamps = {k: kf.timestamp_ns for k, kf in self.keyframes.items() if kf.timestamp_ns is not None}
        cam = {name: getattr(self.camera, name) for name in ("width", "height", "fx", "fy", "cx", "cy")}
        return save_map(path, gmap, poses, stamps, cam, {"mapper_config": asdict(self.config)})

    def refine(self, iterations: int) -> None:
        """Final colour refinement: ``iterations`` steps over keyframes drawn uniformly from all of them, with
        the colour and isotropic terms only (no depth, densification or pruning), as MonoGS / Splat-SLAM do
        after the sequence. Queued events are not applied here: call :meth:`process_pending` (or
        :meth:`wait_idle` when running asynchronously) first."""
        ids = sorted(self.keyframes)
        if not ids:
            return
        for _ in range(iterations):
            with self._lock:
                self._optimise_on(self.keyframes[self._rng.choice(ids)], lambda_depth=0.0)

    # ------------------------------------------------------------------ internals
    @contextlib.contextmanager
    def _reading(self):
        """The map lock for a reader on another thread (a render, the node's deltas and point cloud, a save): the
        worker lets it in between two optimisation steps (:meth:`_let_readers_in`). The lock is not fair: a
        worker with queued keyframes took it again step after step, and a reader (the node's executor) could
        wait for seconds, also when a signal asked the node to stop."""
        with self._readers_lock:
            self._readers += 1
        try:
            self._lock.acquire()
        finally:
            with self._readers_lock:
                self._readers -= 1
        try:
            yield
        finally:
            self._lock.release()

    def _let_readers_in(self) -> None:
        """Worker, between steps (lock released): wait until the readers waiting for the lock have it."""
        while self._readers:
            time.sleep(_READER_POLL_S)

    def _work(self) -> None:
        idle = self.config.refine_when_idle
        while not self._stop.is_set():
            event = self._inbox.take(timeout=0.0 if idle and self.keyframes else 0.05)
            if event is None:
                if idle and self.keyframes:
                    self._idle_step()
                    # a pause with the map lock free: a thread waiting for it (a render, the node's deltas, a save)
                    # would otherwise rarely win it between back-to-back steps
                    self._stop.wait(_IDLE_PAUSE_S)
                continue
            try:
                self._apply(event)
            finally:
                self._inbox.done()
            self._let_readers_in()

    def _apply(self, event: tuple) -> None:
        if event[0] == "keyframe":
            self._integrate(event[1])
        else:
            self._move_keyframes(event[1], event[2])

    def _idle_step(self) -> None:
        """One optimisation step on a keyframe drawn uniformly from the mapped ones (a revisit:
        ``lambda_depth_revisit``)."""
        with self._lock:
            kf = self.keyframes[self._rng.choice(sorted(self.keyframes))]
            self._optimise_on(kf, self.config.lambda_depth_revisit)
        self.stats.idle_steps += 1

    def _view(self, gmap: GaussianMap, T_WC: torch.Tensor, camera: RenderCamera) -> tuple[torch.Tensor, ...]:
        """``T_CW`` of the view and the rows of ``gmap`` in its frustum (:func:`frustum_rows`): only these
        are activated, rendered and differentiated, so a step costs nothing for the rest of the map."""
        T_CW = se3_inverse(T_WC.to(self.device)).to(gmap.dtype)
        return T_CW, frustum_rows(gmap.means, gmap.scales(), T_CW, camera, self.rasterizer.settings,
                                  getattr(self.rasterizer, "compiled", False))

    def _rasterize(self, gmap: GaussianMap, T_CW: torch.Tensor, camera: RenderCamera) -> RenderOutput:
        return self.rasterizer(
            gmap.means, gmap.quats, gmap.scales(), gmap.opacities(), gmap.colors, T_CW, camera
        )

    def _render(self, gmap: GaussianMap, T_WC: torch.Tensor, camera: RenderCamera) -> RenderOutput:
        """Render ``gmap`` (no gradient); ``visible`` indexes the rows of ``gmap``."""
        T_CW, rows = self._view(gmap, T_WC, camera)
        out = self._rasterize(gmap.select(rows), T_CW, camera)
        out.visible = rows[out.visible]
        return out

    def _append(self, new: GaussianMap) -> None:
        n = len(new)
        if n == 0:
            return
        self.map = self.map.concat(new)
        self.optimizer.add_rows(n, {k: getattr(new, k) for k in PARAMETER_FIELDS})
        self._new = torch.cat((self._new, torch.ones(n, dtype=torch.bool, device=self.device)))
        self._dirty = torch.cat((self._dirty, torch.zeros(n, dtype=torch.bool, device=self.device)))
        self.stats.added += n

    def _remove(self, drop: torch.Tensor) -> None:
        if not bool(drop.any()):
            return
        self._removed.append(self.map.ids[drop & ~self._new].cpu())
        keep = ~drop
        self.map = self.map.select(keep)
        self.optimizer.keep_rows(keep)
        self._new = self._new[keep]
        self._dirty = self._dirty[keep]
        self.stats.pruned += int(drop.sum())

    def _integrate(self, kf: Keyframe, optimise: bool = True) -> None:
        c = self.config
        t0 = time.perf_counter()
        with self._lock:
            self.keyframes[kf.id] = kf
            depth = kf.depth
            mask = None
            if len(self.map) > 0:
                with torch.no_grad():
                    out = self._render(self.map, kf.T_WC, self.render_camera)
                expected = out.depth / out.alpha.clamp_min(1e-6)
                mask = (out.alpha < c.densify_alpha) | (depth < (1.0 - c.densify_depth_ratio) * expected)
                cover = self._kept_keyframe_near(kf, depth, mask) if c.cull_keyframes else None
                if cover is not None:
                    self._covered[kf.id] = cover
            new = gaussians_from_depth(
                kf.image(), depth, kf.T_WC.float(), self.render_camera, kf.id, self._next_id,
                c.init_stride, c.init_scale, mask,
            )  # fmt: skip
            self._next_id += len(new)
            self._append(new)
        steps = 0
        window = self._window(kf.id)
        for kf_step in self._schedule(kf.id) if optimise else ():
            if self._inbox.full() or self._stop.is_set():   # behind, or shutting down: the rest waits
                break
            with self._lock:
                self._optimise_on(self.keyframes[kf_step],
                                  c.lambda_depth if kf_step in window else c.lambda_depth_revisit)
            self._let_readers_in()
            steps += 1
        with self._lock:
            self._prune()
            self._release_covered()
        self.stats.keyframes += 1
        self.stats.steps += steps
        self.stats.cut_short += steps < c.iterations
        self.stats.mapping_seconds += time.perf_counter() - t0

    def _window(self, new_id: int) -> list[int]:
        """The local window of keyframe ``new_id``: the ``window`` keyframes up to it (the most recent ones, unless
        it was deferred), itself last."""
        ids = sorted(self.keyframes)
        end = ids.index(new_id) + 1
        return ids[max(0, end - self.config.window) : end]

    def _schedule(self, new_id: int) -> list[int]:
        """Keyframe ids for the ``iterations`` steps: the new keyframe first, then the rest of its local
        window (:meth:`_window`) and ``global_keyframes`` random others, shuffled, cycled to length
        ``iterations``."""
        c = self.config
        window = self._window(new_id)[:-1]
        local = set(window) | {new_id}
        older = [k for k in sorted(self.keyframes) if k not in local]
        extra = self._rng.sample(older, min(c.global_keyframes, len(older)))
        rest = window + extra
        self._rng.shuffle(rest)
        cycle = [new_id] + rest
        return [cycle[i % len(cycle)] for i in range(c.iterations)]

    def _optimise_on(self, kf: Keyframe, lambda_depth: float) -> None:
        c = self.config
        if len(self.map) == 0:
            return
        T_CW, rows = self._view(self.map, kf.T_WC, self.render_camera)
        # the rows in the frustum as leaf tensors: gradients and Adam only touch the part of the map in view
        sub = self.map.select(rows)
        for k in PARAMETER_FIELDS:
            getattr(sub, k).requires_grad_(True)
        out = self._rasterize(sub, T_CW, self.render_camera)
        if out.visible.numel() == 0:
            return
        loss = c.lambda_color * (out.color - kf.image()).abs().mean()
        if lambda_depth > 0:   # the depth is read only for a step that weighs it (a revisit's does not)
            depth = kf.depth
            valid = depth > 0
            n_valid = int(valid.sum())
            if n_valid > 0:   # mean over valid pixels, as a masked sum (cheaper than gathering them, same gradient)
                depth_err = (out.depth - depth).abs_().mul_(valid).sum() / n_valid
                loss = loss + lambda_depth * depth_err
        if c.lambda_iso > 0:
            s = sub.log_scales.index_select(0, out.visible).exp()
            loss = loss + c.lambda_iso * (s - s.mean(dim=1, keepdim=True)).abs().mean()
        loss.backward()
        touched = rows[out.visible]
        grads = {k: getattr(sub, k).grad.index_select(0, out.visible) for k in PARAMETER_FIELDS}
        self.optimizer.step({k: getattr(self.map, k) for k in PARAMETER_FIELDS}, touched, grads)
        self._dirty[touched] = True

    @torch.no_grad()
    def _prune(self) -> None:
        c = self.config
        if len(self.map) == 0:
            return
        ids = sorted(self.keyframes)
        centres = torch.stack([self.keyframes[k].T_WC[:3, 3] for k in ids]).to(self.device, self.map.dtype)
        pos = torch.searchsorted(torch.tensor(ids, device=self.device), self.map.anchor_ids)
        dist = (self.map.means - centres[pos.clamp_max(len(ids) - 1)]).norm(dim=1)
        too_big = self.map.scales().max(dim=1).values > c.prune_max_angular * dist
        drop = (self.map.opacities() < c.prune_min_opacity) | too_big
        self._remove(drop)

    def _kept_keyframe_near(self, kf: Keyframe, depth: torch.Tensor, new_mask: torch.Tensor) -> int | None:
        """The nearest kept keyframe within ``cull_baseline`` x the median depth and ``cull_rotation_deg`` of ``kf``
        when the map covered its view (``new_mask``: pixels that get new Gaussians), else None."""
        c = self.config
        valid = depth > 0
        if float(new_mask.float().mean()) > c.cull_max_new_fraction or not bool(valid.any()):
            return None
        kept = [k for k in self.keyframes if k != kf.id and k not in self._covered]
        if not kept:
            return None
        poses = torch.stack([self.keyframes[k].T_WC for k in kept])
        dist = (poses[:, :3, 3] - kf.T_WC[:3, 3]).norm(dim=1)
        cos = relative_rotation_cosines(kf.T_WC[:3, :3], poses[:, :3, :3])
        near = (dist <= c.cull_baseline * float(depth[valid].median())) & (
            cos >= math.cos(math.radians(c.cull_rotation_deg)))
        if not bool(near.any()):
            return None
        return kept[int(torch.where(near, dist, torch.full_like(dist, math.inf)).argmin())]

    def _release_covered(self) -> None:
        """Release the covered keyframes that left the local window (the ``window`` most recent): their Gaussians
        follow the kept keyframe near them from now on (:func:`anchored_update` moves them with it)."""
        if not self._covered:
            return
        recent = set(self._window(max(self.keyframes)))
        for k in [k for k in self._covered if k not in recent]:
            cover = self._covered.pop(k)
            on = self.map.anchor_ids == k
            self.map.anchor_ids = self.map.anchor_ids.masked_fill(on, cover)
            self._dirty |= on
            del self.keyframes[k]
            self.pixel_store.discard(k)
            self._released.add(k)
            self.stats.released += 1

    def _move_keyframes(self, poses: dict[int, torch.Tensor], scales: dict[int, float]) -> None:
        with self._lock:
            known = {k: v for k, v in poses.items() if k in self.keyframes}
            self.stats.ignored_pose_ids.extend(sorted(set(poses) - set(known) - self._released))
            if not known:
                return
            known_scales = {k: float(s) for k, s in scales.items() if k in known}
            old = {k: self.keyframes[k].T_WC for k in known}
            means, quats, log_scales, moved = anchored_update(
                self.map.means, self.map.quats, self.map.log_scales, self.map.anchor_ids, old, known, known_scales
            )
            self.map.means, self.map.quats, self.map.log_scales = means, quats, log_scales
            self.optimizer.reset_rows(moved)  # world-frame moments no longer match the moved Gaussians
            self._dirty |= moved
            for k, T in known.items():
                kf = self.keyframes[k]
                kf.T_WC = T
                kf.depth_scale *= known_scales.get(k, 1.0)
            self.stats.pose_updates += 1
