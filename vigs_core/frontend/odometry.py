"""Dense monocular visual odometry: two-view initialisation, pose-only tracking of every frame, keyframing,
sliding-window dense bundle adjustment with correspondence refinement (VIGS-SLAM 3.1 with a classical
correspondence estimator in place of DROID-SLAM's learned update).

Per frame (after initialisation):

1. predict the pose with a constant-velocity model, warp the latest keyframe's grid with it and estimate the
   correspondences keyframe -> frame initialised by that warp;
2. align the frame's pose against the keyframe's fixed disparities (:func:`vigs_core.solver.align_pose`);
3. if the keyframe policy fires, the frame becomes a keyframe: its disparities are propagated from the previous
   keyframe, the frame graph adds its edges (correspondences initialised by the geometric warp), dense BA runs
   over the window, then for ``refine_rounds`` rounds the new keyframe's correspondences are re-estimated from
   the updated warp and BA runs again.

Initialisation (monocular): frames are matched against the first frame until a two-view geometry with enough
translational parallax exists (essential matrix, RANSAC); its translation sets the (arbitrary) scale, the first
frame's grid is triangulated, the intermediate keyframes are aligned, and BA with both views fixed refines all
(followed by at least one correspondence refinement round).
Frames seen before that get their poses then.

Poses are world->camera ``T_cw`` (4, 4) float64 with the first camera as the world. Each frame keeps its pose
relative to a reference keyframe, so final poses follow later keyframe updates (``final_frame_poses``), while
``odometry_poses`` holds the causal estimate at the time each frame was processed. A frame between keyframe
``a`` (its reference) and the keyframe ``b`` made next from a frame tracked against ``a`` also takes part of
the correction BA applied to ``b``: with ``R`` the tracked and ``R*`` the final relative pose of ``b`` to
``a``, the frame at time fraction ``alpha = (t - t_a) / (t_b - t_a)`` gets ``T = T_rel Exp(alpha Log(R^-1 R*))
T_a`` (the end-point correction spread linearly in time over the frames in between, in ``a``'s camera frame),
so the final trajectory has no saw-tooth where tracking overshot and the next keyframe's BA pulled back.

Live callers (interleaved tracking): the keyframe work of step 3 takes several frame periods. It has yield points,
before and after each edge's correspondence estimate, after each BA linearisation and between BA iterations (and
before the visual-inertial stages), where ``interleave`` (when set) is called, and while a keyframe pair's flows
run on the estimator's threads it is called every few milliseconds: a caller with a frame that arrived meanwhile
tracks it there by calling :meth:`DenseOdometry.process` again, so its pose is out within one step of the work
instead of after all of it.
Such a frame is tracked against the new keyframe at its pre-BA pose and disparities (it keeps its pose relative
to that keyframe, so it follows the BA like any other frame) and cannot become a keyframe. Yield points are
counted (``yield_points``), so a run can be replayed with every frame tracked at the same point
(:mod:`vigs_core.io.frame_schedule`). Time spent in ``interleave`` is left out of the keyframe work's timings.
"""
from __future__ import annotations

import itertools
import time
from collections import defaultdict
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from vigs_core.frontend.correspondence import Correspondences, PixelGrid
from vigs_core.frontend.dis_flow import DISFlowConfig, DISFlowEstimator
from vigs_core.frontend.frame_graph import FrameGraph, FrameGraphConfig
from vigs_core.frontend.keyframe_changes import WATCHED, KeyframeTable
from vigs_core.frontend.keyframe_policy import KeyframePolicy, KeyframePolicyConfig
from vigs_core.geometry import nearest_rotation, se3_exp, se3_inverse, se3_log
from vigs_core.ranges import bounded
from vigs_core.solver import BAConfig, EdgeSet, Intrinsics, align_pose, bundle_adjust, reproject


INIT_ALIGN_ITERATIONS = 10  # Gauss-Newton iterations aligning the frames seen before initialisation
WAIT_POLL_S = 0.002         # how often a live caller looks for frames while keyframe flows run on other threads


@dataclass
class OdometryConfig:
    """Settings of :class:`DenseOdometry` (defaults tuned for 376x240 EuRoC-like input).

    Args:
        grid_stride: reduced-grid cell size, input pixels (8 = 1/8 resolution).
        flow: DIS estimator of the keyframe edges (BA correspondences). Default: ultrafast refined down to
            the input resolution (``finest_scale=0``): on the first 30 s of hybrid V1_01 (vision only) the
            camera-frame Sim(3) ATE fell from 2.43 to 1.62 cm (1.98 to 1.01 cm with ``hold_fixed_disparity``)
            for about 15 ms more CPU per frame at one keyframe per 12 frames (each new keyframe's edges then
            cost about 12 DIS calls of about 17 ms; computing both directions of a pair together,
            :meth:`~vigs_core.frontend.dis_flow.DISFlowEstimator.estimate_pair`, halved that to 6); presets
            fast / medium at ``finest_scale=1`` gave 1.6 cm (with ``hold_fixed_disparity``) for about 7-10 ms.
        covis_flow: DIS estimator of the co-visibility edges (``graph.covis_max_edges``; temporal edges use
            ``flow``). Same as ``flow`` by default: ``finest_scale=1`` here saved about 3 ms per frame on the
            whole hybrid MH_03 (vision only) but its recall@10cm fell from 29 to 17 %.
        tracking_flow: DIS estimator of every frame against the latest keyframe (pose-only tracking and the
            pre-initialisation matching); kept at ultrafast / ``finest_scale=1`` (about 4 ms): refining it to the
            input resolution cost 16 ms per frame for less gain (2.43 to 2.15 cm).
        keyframes: keyframe policy.
        graph: frame graph / window.
        ba: dense BA settings used per new keyframe: at most 3 LM iterations, stopping early once an accepted
            step lowers the cost by less than 1 % (``rel_tol=0.01``). On hybrid MH_03 the median relative
            decrease was 58 % in the first iteration, 0.37 % in the second and 5e-6 in the third, so the third
            was nearly always wasted; the early stop cut BA's CPU time per keyframe from 82 to 65 ms.
        init_ba_iterations: LM iterations of the initial BA.
        init_min_parallax_px: median translation-induced flow needed to initialise, input pixels.
        init_min_inliers: fraction of confident correspondences that must be essential-matrix inliers.
        init_max_flow_px: if the mean flow to the first frame exceeds this without enough parallax (pure
            rotation), the reference frame is reset to the current frame.
        refine_rounds: correspondence re-estimation + BA rounds after each keyframe's first BA (1 round
            lowered the ATE on 20 s of hybrid V1_01 from 0.71 to 0.57 cm but costs about 60 % more time).
        tracking_iterations: Gauss-Newton iterations of pose-only tracking.
        min_confidence: correspondences below this confidence are ignored, [0, 1].
        solver_dtype: "float32" (faster) or "float64" for tracking and BA's visual terms (linearisation, Schur
            complement, cost; :func:`~vigs_core.solver.bundle_adjust` ``visual_dtype``); poses are stored, and
            the reduced camera system is solved, in float64. float32 BA cut its CPU time by about 35 % with
            the same ATE (first 600 frames of hybrid V1_01 / MH_03: 1.11 / 5.75 cm either way).
        hold_fixed_disparity: the window's fixed keyframes (``graph.fixed``) keep their disparities as well as
            their poses in BA, so their depth maps pin the monocular scale (the gauge, see
            :mod:`vigs_core.frontend.frame_graph`); off, the scale is a free direction of BA that only the LM
            damping holds. On by default: on the whole hybrid V1_01 (vision only) holding lowered the camera
            ATE from 6.91 to 4.15 cm (first 30 s: 1.62 to 1.01 cm; but on the first 70 s with ``finest_scale=1``
            it raised it from 4.14 to 4.55 cm). The visual-inertial odometry leaves them free (the IMU fixes the
            scale; :meth:`vigs_core.vio.odometry.VisualInertialOdometry._holds_scale_gauge`).
        cv_rescale_tolerance: the constant-velocity pose prediction extrapolates the last inter-frame motion
            over time: when the gap to the new frame differs from the last gap by more than this fraction
            (frames skipped by a live caller that fell behind, or dropped), the motion is scaled to the gap,
            ``Exp(r Log T)``; within it the plain product ``T T_last`` is used.
    """

    grid_stride: int = bounded(8, 1)
    flow: DISFlowConfig = field(default_factory=lambda: DISFlowConfig(finest_scale=0))
    tracking_flow: DISFlowConfig = field(default_factory=DISFlowConfig)
    covis_flow: DISFlowConfig = field(default_factory=lambda: DISFlowConfig(finest_scale=0))
    keyframes: KeyframePolicyConfig = field(default_factory=KeyframePolicyConfig)
    graph: FrameGraphConfig = field(default_factory=FrameGraphConfig)
    ba: BAConfig = field(default_factory=lambda: BAConfig(iterations=3, rel_tol=0.01))
    init_ba_iterations: int = bounded(15, 0)
    init_min_parallax_px: float = bounded(10.0, 0)
    init_min_inliers: float = bounded(0.6, 0, 1)
    init_max_flow_px: float = bounded(80.0, 0)
    refine_rounds: int = bounded(0, 0)
    tracking_iterations: int = bounded(3, 0)
    min_confidence: float = bounded(0.05, 0, 1)
    solver_dtype: str = "float32"
    hold_fixed_disparity: bool = True
    cv_rescale_tolerance: float = bounded(0.25, 0)

    def __post_init__(self) -> None:
        if self.solver_dtype not in ("float32", "float64"):
            raise ValueError(f"OdometryConfig.solver_dtype {self.solver_dtype!r}; expected float32 or float64")


@dataclass
class Keyframe:
    """A keyframe: id, time (ns), grey image (H, W) uint8, pose ``T_cw`` (4, 4) and disparities (P,); ``tracked``:
    the reference keyframe id and the relative pose ``T_cw T_cw(ref)^-1`` (4, 4) its frame was tracked at, when
    it was made from a tracked frame (module docstring, final poses).

    Image and disparities are dropped (None) at the first frame after the keyframe left the window: only window
    keyframes are matched and adjusted, and loop closure and the mapper took them while it was there, so a long
    run does not keep every keyframe's pixels and depths. ``revision`` counts the disparities' re-estimates
    (:meth:`set_disparities`); ``depth_scale`` is the product of the uniform depth scalings applied since
    creation (:meth:`rescale_depth`: world alignment, loop corrections). A consumer that took the disparities at
    ``(revision, s)`` knows, while the revision is unchanged, that they are now its copy times ``s /
    depth_scale``, without keeping them (:class:`vigs_core.frontend.keyframe_changes.SentKeyframes`)."""

    id: int
    t_ns: int
    image: np.ndarray | None
    pose: torch.Tensor
    disp: torch.Tensor | None
    tracked: tuple[int, torch.Tensor] | None = None
    revision: int = 0
    depth_scale: float = 1.0

    def __setattr__(self, name: str, value: object) -> None:
        """Assign, and note a change of a watched attribute in the log of the table holding the keyframe
        (:class:`~vigs_core.frontend.keyframe_changes.KeyframeTable`; none before it is put in one)."""
        object.__setattr__(self, name, value)
        if name in WATCHED and (changes := self.__dict__.get("changes")) is not None:
            changes.note(self.id)

    def set_disparities(self, disp: torch.Tensor) -> None:
        """New estimates of the disparities (P,): a new revision."""
        self.disp = disp
        self.revision += 1

    def rescale_depth(self, c: float) -> None:
        """Depths scaled by ``c`` (disparities by ``1 / c``), the revision kept; applies to a settled keyframe
        too (its disparities are gone, ``depth_scale`` carries the scaling)."""
        if self.disp is not None:
            self.disp = self.disp / c
        self.depth_scale *= float(c)


class FrameRows:
    """Per-frame float64 records of one ``shape``, in chunks of ``chunk`` frames (a long run keeps every frame,
    and an array of its own costs a frame hundreds of bytes more); an unset record is NaN. Rows are the frames'
    indices in :class:`PoseRows`, which hands them out."""

    def __init__(self, shape: tuple[int, ...], chunk: int = 4096) -> None:
        self.shape = shape
        self._chunk = chunk
        self._blocks: list[np.ndarray] = []

    def record(self, row: int) -> np.ndarray:
        """The record of ``row`` (a view: writing to it stores), chunks added as needed."""
        block, offset = divmod(row, self._chunk)
        while len(self._blocks) <= block:
            self._blocks.append(np.full((self._chunk, *self.shape), np.nan))
        return self._blocks[block][offset]

    def take(self, rows: np.ndarray, part: int | None = None) -> np.ndarray:
        """Copies (M, *shape) of the records of ``rows`` (M,), or of their ``part`` along the first axis of
        ``shape``; NaN where unset: one gather per chunk."""
        rows = np.asarray(rows, dtype=np.int64)
        out = np.full((len(rows), *(self.shape if part is None else self.shape[1:])), np.nan)
        block, offset = np.divmod(rows, self._chunk)
        for b in np.unique(block[block < len(self._blocks)]):
            sel = block == b
            out[sel] = self._blocks[b][offset[sel]] if part is None else self._blocks[b][offset[sel], part]
        return out

    def put(self, rows: np.ndarray, values: np.ndarray, part: int) -> None:
        """Store ``values`` (M, *shape[1:]) as ``part`` of the records of ``rows`` (M,), rows handed out
        already: one scatter per chunk."""
        rows = np.asarray(rows, dtype=np.int64)
        block, offset = np.divmod(rows, self._chunk)
        for b in np.unique(block):
            sel = block == b
            self._blocks[b][offset[sel], part] = values[sel]


class PoseRows:
    """Append-only storage of the frames' poses: two (4, 4) float64 slots per frame (``rel`` and ``odom``) in a
    :class:`FrameRows` (two tensors of their own cost a frame about 1.2 KB more). An unset slot is NaN."""

    def __init__(self, chunk: int = 4096) -> None:
        self._records = FrameRows((2, 4, 4), chunk)
        self._rows = 0

    def add(self) -> int:
        """A new frame's row index, both slots unset."""
        self._records.record(self._rows)
        self._rows += 1
        return self._rows - 1

    def get(self, row: int, slot: int) -> torch.Tensor | None:
        """A copy of the pose in ``slot`` of ``row``, or None if unset."""
        pose = self._records.record(row)[slot]
        return None if np.isnan(pose[3, 3]) else torch.from_numpy(pose.copy())

    def take(self, rows: np.ndarray, slot: int) -> np.ndarray:
        """Copies (M, 4, 4) of the poses in ``slot`` of ``rows`` (M,), NaN where unset (the outputs read every
        frame's pose)."""
        return self._records.take(rows, slot)

    def set(self, row: int, slot: int, pose: torch.Tensor | None) -> None:
        """Store ``pose`` (4, 4) as float64 in ``slot`` of ``row`` (None unsets it)."""
        self._records.record(row)[slot] = np.nan if pose is None else pose.detach().to("cpu", torch.float64).numpy()

    def put(self, rows: np.ndarray, slot: int, poses: np.ndarray) -> None:
        """Store ``poses`` (M, 4, 4) in ``slot`` of ``rows`` (M,) in one scatter per chunk (NaN rows: unset)."""
        self._records.put(rows, poses, slot)


class _PoseSlot:
    """A frame's pose held in slot ``slot`` of its :class:`PoseRows` row (reading gives a copy)."""

    def __init__(self, slot: int) -> None:
        self.slot = slot

    def __get__(self, frame: "_Frame | None", owner: type | None = None):
        return self if frame is None else frame._rows.get(frame._row, self.slot)

    def __set__(self, frame: "_Frame", pose: torch.Tensor | None) -> None:
        frame._rows.set(frame._row, self.slot, pose)


class _Frame:
    """A frame's record: time, reference keyframe, its poses (``rel = T_cw(frame) T_cw(ref)^-1`` and the causal
    world->camera ``odom``, kept in the odometry's :class:`PoseRows`; reading gives a copy), whether it became a
    keyframe, and before initialisation its correspondences from the first frame."""

    __slots__ = ("t_ns", "ref", "keyframe", "pending", "_rows", "_row")
    rel = _PoseSlot(0)
    odom = _PoseSlot(1)

    def __init__(self, t_ns: int, rows: PoseRows, ref: int | None = None, rel: torch.Tensor | None = None,
                 odom: torch.Tensor | None = None, keyframe: bool = False) -> None:
        self.t_ns, self.ref, self.keyframe = t_ns, ref, keyframe
        self.pending: Correspondences | None = None
        self._rows, self._row = rows, rows.add()
        self.rel, self.odom = rel, odom


class DenseOdometry:
    """Monocular dense visual odometry over a stream of undistorted grey images (module docstring).

    Args:
        intrinsics: pinhole intrinsics of the input images (undistorted).
        width, height: input image size, pixels.
        config: settings.
    """

    def __init__(self, intrinsics: Intrinsics, width: int, height: int, config: OdometryConfig | None = None):
        self.config = config or OdometryConfig()
        self.intr = intrinsics
        self.grid = PixelGrid(width, height, self.config.grid_stride)
        self.estimator = DISFlowEstimator(self.grid, self.config.flow)
        self.tracking_estimator = DISFlowEstimator(self.grid, self.config.tracking_flow)
        # one estimator (DIS instances, pair thread) for both kinds of edge when their settings agree
        self.covis_estimator = (self.estimator if self.config.covis_flow == self.config.flow
                                else DISFlowEstimator(self.grid, self.config.covis_flow))
        self.policy = KeyframePolicy(self.config.keyframes)
        self.graph = FrameGraph(self.config.graph)
        self.coords = torch.from_numpy(self.grid.coords())
        self.keyframes: KeyframeTable = KeyframeTable()   # id -> Keyframe, changes logged for the consumers
        self._left_window: list[int] = []   # keyframes that left the window, images not yet dropped
        self.frames: list[_Frame] = []
        self._pose_rows = PoseRows()
        self.edges: dict[tuple[int, int], Correspondences] = {}
        self.initialized = False
        self._dtype = getattr(torch, self.config.solver_dtype)
        self.timings: dict[str, float] = defaultdict(float)
        self.ba_calls = 0
        self._next_kf = 0
        self._init_candidates: list[tuple[int, np.ndarray, Correspondences]] = []  # (frame idx, image, corr)
        self._ref_image: np.ndarray | None = None
        self._on_pose: Callable[[torch.Tensor], None] | None = None
        self.interleave: Callable[[], None] | None = None   # called at the keyframe work's yield points
        self.yield_points = 0          # yield points passed (module docstring, live callers)
        self.in_keyframe_work = False  # True while a keyframe's work runs (a frame processed now is nested)
        self._paused_s = 0.0           # time spent in ``interleave``, left out of the timings

    # ------------------------------------------------------------------ public
    def process(self, t_ns: int, image: np.ndarray,
                on_pose: Callable[[torch.Tensor], None] | None = None) -> torch.Tensor | None:
        """Consume one frame; returns its world->camera pose (4, 4), or None while not yet initialised.

        ``on_pose`` is called with the frame's tracked pose as soon as it is known, before the keyframe work
        (new keyframe, BA) that may follow: a live caller publishes odometry without waiting for the BA. The
        returned pose is the causal one after that work (it differs from the tracked one on keyframes).
        Called during the keyframe work (from ``interleave``), the frame is tracked only (module docstring)."""
        if not self.in_keyframe_work:   # the callers of the previous frame have taken what they need of the
            settled = [k for k in self._left_window if k in self.keyframes]   # (Keyframe)
            for k in settled:
                self.keyframes[k].image = self.keyframes[k].disp = None
            self._left_window.clear()
            self._on_settled(settled)
        frame = _Frame(int(t_ns), self._pose_rows)
        self.frames.append(frame)
        outer, self._on_pose = self._on_pose, on_pose   # a nested frame's callback is its own
        try:
            if not self.initialized:
                self._process_uninitialized(image)
            else:
                self._track(image)
            if frame.keyframe and self.initialized:   # after its keyframe work: the keyframe's pose
                pose = self.keyframes[frame.ref].pose
            else:
                pose = frame.odom if frame.odom is not None else self._pose_before_initialization(frame.t_ns)
            if pose is not None:   # posed without tracking (the initialisation's frame, a held one)
                self._send_pose(pose)
        finally:
            self._on_pose = outer
        return pose

    def _on_settled(self, ids: list[int]) -> None:
        """Hook: keyframes ``ids`` left the window (their frames are final up to later corrections)."""

    def _pose_before_initialization(self, t_ns: int) -> torch.Tensor | None:
        """Hook: a pose for a frame the front end could not pose yet (e.g. held still); None: no pose."""
        return None

    def _send_pose(self, pose: torch.Tensor) -> None:
        """Give ``process``'s ``on_pose`` the frame's pose, once per frame."""
        if self._on_pose is not None:
            on_pose, self._on_pose = self._on_pose, None
            on_pose(pose)

    def final_frame_poses(self) -> tuple[np.ndarray, torch.Tensor]:
        """Times (N,) ns and world->camera poses (N, 4, 4) of every posed frame, relative to the final
        keyframe poses, with the next keyframe's correction spread over the frames in between (module
        docstring)."""
        pairs = [(self.keyframes[b.tracked[0]], b) for b in self.keyframes.values()
                 if b.tracked is not None and b.tracked[0] in self.keyframes]
        correction = {}   # reference keyframe a -> (next keyframe b, Log(R^-1 R*)) (6,), in one batch
        if pairs:
            final = torch.stack([b.pose for _, b in pairs]) @ se3_inverse(torch.stack([a.pose for a, _ in pairs]))
            tracked = torch.stack([b.tracked[1] for _, b in pairs])
            correction = {a.id: (b, xi) for (a, b), xi in zip(pairs, se3_log(se3_inverse(tracked) @ final))}
        posed = [f for f in self.frames if f.ref is not None]
        if not posed:
            return np.zeros(0, dtype=np.int64), self._stack([])
        n = len(posed)
        t = np.fromiter((f.t_ns for f in posed), np.int64, n)
        is_kf = np.fromiter((f.keyframe for f in posed), bool, n)
        ids, which = np.unique(np.fromiter((f.ref for f in posed), np.int64, n), return_inverse=True)
        refs = [self.keyframes[int(k)] for k in ids]
        zero = (None, torch.zeros(6, dtype=torch.float64))   # no next keyframe: no correction
        nexts = [correction.get(a.id, zero) for a in refs]
        t_a = np.array([a.t_ns for a in refs], dtype=np.int64)[which]
        # any span will do where there is no correction (xi = 0)
        t_b = np.array([a.t_ns + 1 if b is None else b.t_ns for a, (b, _) in zip(refs, nexts)], dtype=np.int64)[which]
        xi = torch.stack([x for _, x in nexts])[torch.from_numpy(which)]
        # the next keyframe's correction, spread linearly in time between the two (none on a keyframe's own frame)
        frac = np.where(is_kf, 0.0, np.clip((t - t_a) / (t_b - t_a), 0.0, 1.0))
        rel = torch.from_numpy(self._pose_rows.take([f._row for f in posed], 0))
        ref_pose = torch.stack([a.pose for a in refs])[torch.from_numpy(which)]
        poses = rel @ se3_exp(xi * torch.from_numpy(frac)[:, None]) @ ref_pose
        return t, poses

    def scale_relative_translations(self, scales: dict[int, float]) -> None:
        """Multiply the translation of every pose kept relative to a keyframe -- each frame's ``rel`` and each
        keyframe's ``tracked`` pose -- by the factor ``scales[reference keyframe id]`` (1 for keyframes not in
        ``scales``), rotations unchanged: what re-expressing the reference keyframes' depth in new units (a
        loop correction's depth scale, the IMU alignment's metric scale) does to them. The frames' poses are
        scaled in their rows (one gather and one scatter: a loop correction late in a long run touches tens of
        thousands of frames); the keyframes' tracked poses are replaced by new tensors (never edited in place)."""
        owners = [f for f in self.frames if f.ref in scales]
        if owners:
            rows = np.fromiter((f._row for f in owners), np.int64, len(owners))
            rel = self._pose_rows.take(rows, 0)   # an unset pose is NaN and stays so
            rel[:, :3, 3] *= np.fromiter((scales[f.ref] for f in owners), np.float64, len(owners))[:, None]
            self._pose_rows.put(rows, 0, rel)
        tracked = [kf for kf in self.keyframes.values() if kf.tracked is not None and kf.tracked[0] in scales]
        if tracked:
            rels = torch.stack([kf.tracked[1] for kf in tracked])
            rels[:, :3, 3] *= torch.tensor([scales[kf.tracked[0]] for kf in tracked], dtype=rels.dtype)[:, None]
            for kf, rel in zip(tracked, rels.unbind(0)):
                kf.tracked = (kf.tracked[0], rel)

    def odometry_poses(self) -> tuple[np.ndarray, torch.Tensor]:
        """Times (N,) ns and causal world->camera poses (N, 4, 4) as output while running."""
        n = len(self.frames)
        t = np.fromiter((f.t_ns for f in self.frames), np.int64, n)
        odom = self._pose_rows.take(np.fromiter((f._row for f in self.frames), np.int64, n), 1)
        posed = ~np.isnan(odom[:, 3, 3])
        return t[posed], torch.from_numpy(odom[posed])

    def keyframe_poses(self, ids: list[int] | None = None) -> tuple[np.ndarray, torch.Tensor]:
        """Times (K,) ns and world->camera poses (K, 4, 4) of the keyframes ``ids`` (default: all, ascending)."""
        kfs = [self.keyframes[k] for k in (sorted(self.keyframes) if ids is None else ids)]
        return np.array([k.t_ns for k in kfs], dtype=np.int64), self._stack([k.pose for k in kfs])

    def predicted_flow(self, i: int, j: int) -> float:
        """Mean flow (input pixels) of keyframe ``i``'s grid warped into keyframe ``j``; inf when fewer than
        half of the points land in front of ``j`` and inside its image."""
        uv, ok = self._warp(self.keyframes[i], self.keyframes[j].pose)
        if float(ok.double().mean()) < 0.5:
            return float("inf")
        return float((uv[ok] - self.coords[ok]).norm(dim=-1).mean())

    # ------------------------------------------------------------------ helpers
    @staticmethod
    def _stack(poses: list[torch.Tensor]) -> torch.Tensor:
        return torch.stack(poses) if poses else torch.zeros(0, 4, 4, dtype=torch.float64)

    def _tic(self) -> float:
        return time.perf_counter() - self._paused_s

    def _toc(self, name: str, t0: float) -> None:
        self.timings[name] += time.perf_counter() - self._paused_s - t0

    def _yield_point(self) -> None:
        """A point of the keyframe work where ``interleave`` may track a frame that arrived (module docstring)."""
        if not self.in_keyframe_work:
            return
        self.yield_points += 1
        if self.interleave is not None:
            t0 = time.perf_counter()
            try:
                self.interleave()
            finally:
                self._paused_s += time.perf_counter() - t0

    def _wait(self, job: Future):
        """The result of a job of the keyframe work running on other threads; until it is done ``interleave``
        is called every ``WAIT_POLL_S``, so a frame that arrives meanwhile is tracked at once. Such frames
        count as tracked at the yield point just passed: the job changes nothing they read."""
        while self.interleave is not None and self.in_keyframe_work:
            try:
                return job.result(timeout=WAIT_POLL_S)
            except FutureTimeout:
                t0 = time.perf_counter()
                try:
                    self.interleave()
                finally:
                    self._paused_s += time.perf_counter() - t0
        return job.result()

    def _warp(self, kf: Keyframe, T_target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Keyframe grid warped into a camera at ``T_target``: coordinates (P, 2) and whether they land in
        front of it and inside its image (P,). Points behind the camera get the median flow of the others."""
        proj = reproject(kf.pose[None], T_target[None], kf.disp[None], self.coords, self.intr)
        uv, valid = proj.uv[0], proj.valid[0]
        g = self.grid
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= g.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= g.height - 1)
        if bool(valid.any()) and not bool(valid.all()):
            flow = (uv - self.coords)[valid].median(dim=0).values
            uv = torch.where(valid[:, None], uv, self.coords + flow)
        return uv, valid & inside

    def _estimate(self, source: np.ndarray, target: np.ndarray, init: torch.Tensor | None,
                  forward_backward: bool = True, estimator: DISFlowEstimator | None = None) -> Correspondences:
        """Correspondences source -> target with ``estimator`` (default: the keyframe-edge estimator)."""
        t0 = self._tic()
        est = estimator or self.estimator
        corr = est.estimate(source, target, None if init is None else init.numpy(), forward_backward)
        self._toc("flow", t0)
        return corr

    def _weights(self, corr: Correspondences) -> torch.Tensor:
        w = torch.from_numpy(corr.weight.astype(np.float64))
        return torch.where(w >= self.config.min_confidence, w, torch.zeros_like(w))

    def _new_keyframe(self, frame_idx: int, image: np.ndarray, pose: torch.Tensor, disp: torch.Tensor) -> Keyframe:
        f = self.frames[frame_idx]
        tracked = (f.ref, f.rel) if f.ref is not None and f.rel is not None else None
        kf = Keyframe(self._next_kf, f.t_ns, image, pose, disp, tracked)
        self.keyframes[kf.id] = kf
        self._next_kf += 1
        f.keyframe, f.ref, f.rel = True, kf.id, torch.eye(4, dtype=torch.float64)
        return kf

    def _propagate_disparity(self, src: Keyframe, corr: Correspondences, pose: torch.Tensor) -> torch.Tensor:
        """Disparities (P,) of a new keyframe at ``pose``: the source keyframe's points, moved to the new camera
        and splatted at their measured targets into the nearest cell (nearest point wins); empty cells get
        the median."""
        proj = reproject(src.pose[None], pose[None], src.disp[None], self.coords, self.intr)
        T = pose @ se3_inverse(src.pose)
        rays = torch.stack(((self.coords[:, 0] - self.intr.cx) / self.intr.fx,
                            (self.coords[:, 1] - self.intr.cy) / self.intr.fy,
                            torch.ones(self.coords.shape[0], dtype=torch.float64)), -1)
        Pz = rays @ T[2, :3] + T[2, 3] * src.disp                   # = disp_src * z_new
        new_disp = (src.disp / Pz.clamp(min=1e-6)).numpy()
        ok = proj.valid[0].numpy() & (corr.weight >= self.config.min_confidence) & (Pz.numpy() > 1e-6)
        cell, inside = self.grid.cell_of(corr.target)
        ok &= inside
        out = np.zeros(self.grid.size)
        np.maximum.at(out, cell[ok], new_disp[ok])
        fill = float(np.median(new_disp[ok])) if ok.any() else float(src.disp.median())
        out[out <= 0] = fill
        return torch.from_numpy(out)

    # ------------------------------------------------------------------ initialisation
    def _process_uninitialized(self, image: np.ndarray) -> None:
        idx = len(self.frames) - 1
        if self._ref_image is None:
            self._ref_image = image
            self._init_candidates = [(idx, image, None)]
            self.frames[idx].pending = None
            return
        last = self.frames[idx - 1].pending
        corr = self._estimate(self._ref_image, image, None if last is None else torch.from_numpy(last.target),
                              estimator=self.tracking_estimator)
        self.frames[idx].pending = corr
        cand_idx, _, cand_corr = self._init_candidates[-1]
        base = self.coords.numpy() if cand_corr is None else cand_corr.target
        w = np.minimum(corr.weight, 1.0 if cand_corr is None else cand_corr.weight)
        rel_flow = float((w * np.linalg.norm(corr.target - base, axis=-1)).sum() / max(w.sum(), 1e-6))
        dt = (self.frames[idx].t_ns - self.frames[cand_idx].t_ns) * 1e-9
        if not self.policy.is_keyframe(rel_flow, dt):
            return
        self._init_candidates.append((idx, image, corr))
        t0 = self._tic()
        geometry = self._two_view(corr)
        self._toc("init", t0)
        if geometry is not None:
            t0 = self._tic()
            self._initialize(*geometry)
            self._toc("init", t0)
        elif corr.mean_flow > self.config.init_max_flow_px:
            self._reset_reference(idx, image)

    def _reset_reference(self, idx: int, image: np.ndarray) -> None:
        """Pure rotation so far: restart the initialisation from the current frame. Frames before it cannot
        be posed from the two-view geometry and stay without pose."""
        for f in self.frames[:idx]:
            f.pending = None
        self._ref_image = image
        self.frames[idx].pending = None
        self._init_candidates = [(idx, image, None)]

    def _two_view(self, corr: Correspondences) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Essential matrix from the first frame to the latest candidate: pose ``T_10`` (4, 4) with unit
        translation and first-frame disparities (P,), or None without enough inliers or parallax.

        The median flow of the confident correspondences must reach ``init_min_parallax_px`` before any fit:
        translational parallax cannot exceed the flow, and from a camera standing still (sub-pixel flow noise,
        e.g. a still start seen at 2 Hz) RANSAC returns a geometry fitted to noise (hybrid V1_01 at frame stride
        10: a rotation 180 deg off, ATE 119 cm)."""
        cfg, intr = self.config, self.intr
        good = corr.weight > 0.5
        if good.sum() < 30:
            return None
        c = self.coords.numpy()
        if np.median(np.linalg.norm(corr.target[good] - c[good], axis=-1)) < cfg.init_min_parallax_px:
            return None
        x0 = np.stack(((c[:, 0] - intr.cx) / intr.fx, (c[:, 1] - intr.cy) / intr.fy), -1)
        x1 = np.stack(((corr.target[:, 0] - intr.cx) / intr.fx, (corr.target[:, 1] - intr.cy) / intr.fy), -1)
        E, mask = cv2.findEssentialMat(x0[good], x1[good], focal=1.0, pp=(0.0, 0.0), method=cv2.RANSAC,
                                       prob=0.999, threshold=1.0 / intr.fx)
        if E is None or E.shape != (3, 3) or mask is None or mask.mean() < cfg.init_min_inliers:
            return None
        _, R, t, _ = cv2.recoverPose(E, x0[good], x1[good], focal=1.0, pp=(0.0, 0.0), mask=mask.copy())
        R, t = R.astype(np.float64), t[:, 0].astype(np.float64)
        a = np.concatenate((x0, np.ones((len(x0), 1))), 1) @ R.T             # R ray (P, 3)
        A = np.stack((a[:, 0] - x1[:, 0] * a[:, 2], a[:, 1] - x1[:, 1] * a[:, 2]), -1)
        B = np.stack((t[0] - x1[:, 0] * t[2], t[1] - x1[:, 1] * t[2]), -1)
        d = -(A * B).sum(-1) / np.maximum((B * B).sum(-1), 1e-12)
        parallax_px = intr.fx * np.linalg.norm(B, axis=-1) * np.abs(d) / np.maximum(np.abs(a[:, 2]), 1e-6)
        ok = good & (d > 0)
        if ok.sum() < 30 or np.median(parallax_px[ok]) < cfg.init_min_parallax_px:
            return None
        fill = np.median(d[ok])
        d = np.where(ok, d, fill).clip(min=fill * 0.05, max=fill * 20.0)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        return torch.from_numpy(T), torch.from_numpy(d)

    def _initialize(self, T_10: torch.Tensor, disp0: torch.Tensor) -> None:
        cands = self._init_candidates
        ident = torch.eye(4, dtype=torch.float64)
        kf0 = self._new_keyframe(cands[0][0], cands[0][1], ident, disp0)
        kfs = [kf0]
        prev_pose = ident
        for n, (idx, image, corr) in enumerate(cands[1:], start=1):
            if n == len(cands) - 1:
                pose = T_10
            else:
                pose = align_pose(kf0.pose, kf0.disp, self.coords, self.intr, torch.from_numpy(corr.target),
                                  self._weights(corr), prev_pose, INIT_ALIGN_ITERATIONS,
                                  self.config.ba.huber_delta).pose
            kf = self._new_keyframe(idx, image, pose, self._propagate_disparity(kf0, corr, pose))
            self.edges[(kf0.id, kf.id)] = corr
            kfs.append(kf)
            prev_pose = pose
        for kf in kfs:
            self._insert_into_graph(kf)
        self._ba(self.config.init_ba_iterations, fixed=[kf0.id, kfs[-1].id])
        for _ in range(max(1, self.config.refine_rounds)):
            self._refine_edges(self.graph.sorted_edges())
            self._ba(self.config.init_ba_iterations, fixed=[kf0.id, kfs[-1].id])
        # frames seen so far: align against the first keyframe with their stored correspondences
        prev_pose = ident
        for f in self.frames:
            if f.keyframe:
                prev_pose = self._current_pose(f)
                f.odom = prev_pose
            elif f.pending is not None:
                pose = align_pose(kf0.pose, kf0.disp, self.coords, self.intr, torch.from_numpy(f.pending.target),
                                  self._weights(f.pending), prev_pose, INIT_ALIGN_ITERATIONS,
                                  self.config.ba.huber_delta).pose
                f.ref, f.rel, f.odom = kf0.id, pose @ se3_inverse(kf0.pose), pose
                prev_pose = pose
            f.pending = None
        self._init_candidates = []
        self._ref_image = None
        self.initialized = True

    # ------------------------------------------------------------------ tracking and mapping
    def _insert_into_graph(self, kf: Keyframe) -> list[tuple[int, int]]:
        new_edges, left = self.graph.add_keyframe(kf.id, self.predicted_flow)
        self._left_window += left
        for k in left:   # window membership is a change for the loop driver (it sends the last disparities)
            self.keyframes.changes.note(k)
        for e in list(self.edges):
            if e not in self.graph.edges:
                del self.edges[e]
        new_edges = [e for e in new_edges if e in self.graph.edges]   # not to a keyframe that left the window
        self._refine_edges([e for e in new_edges if e not in self.edges])
        return new_edges

    def _refine_edges(self, edges: list[tuple[int, int]]) -> None:
        """(Re-)estimate the correspondences of ``edges``, each initialised by the geometric warp, temporal edges
        with ``flow`` and co-visibility edges with ``covis_flow``; an edge whose reverse is in ``edges`` too is
        estimated together with it (:meth:`CorrespondenceEstimator.estimate_pair`: two flows instead of four)."""
        todo = set(edges)
        for i, j in edges:
            if (i, j) not in todo:
                continue
            todo.discard((i, j))
            src, dst = self.keyframes[i], self.keyframes[j]
            est = self.estimator if self.graph.is_temporal(i, j) else self.covis_estimator
            uv_ij, _ = self._warp(src, dst.pose)
            if (j, i) not in todo:
                self.edges[(i, j)] = self._estimate(src.image, dst.image, uv_ij, estimator=est)
                self._yield_point()
                continue
            todo.discard((j, i))
            uv_ji, _ = self._warp(dst, src.pose)
            self._yield_point()   # frames tracked here and while the flows run see the same state
            t0 = self._tic()
            self.edges[(i, j)], self.edges[(j, i)] = self._wait(est.submit_pair(src.image, dst.image,
                                                                                uv_ij.numpy(), uv_ji.numpy()))
            self._toc("flow", t0)
            self._yield_point()

    def _ba(self, iterations: int, fixed: list[int] | None = None) -> None:
        """BA over the window. ``fixed``: keyframes whose poses are held (disparities free); by default the
        graph's fixed keyframes, with poses held and, with ``hold_fixed_disparity``, disparities (scale gauge)."""
        t0 = self._tic()
        ids = list(self.graph.keyframes)
        index = {k: n for n, k in enumerate(ids)}
        edges = [e for e in self.graph.sorted_edges() if e in self.edges]
        if not edges:
            return
        ii = torch.tensor([index[i] for i, _ in edges])
        jj = torch.tensor([index[j] for _, j in edges])
        target = torch.from_numpy(np.stack([self.edges[e].target for e in edges]))
        weight = torch.stack([self._weights(self.edges[e]) for e in edges])
        poses = torch.stack([self.keyframes[k].pose for k in ids])
        disps = torch.stack([self.keyframes[k].disp for k in ids])
        fixed_ids = set(self.graph.fixed_ids() if fixed is None else fixed)
        mask = torch.tensor([k in fixed_ids for k in ids])
        cfg = BAConfig(**{**self.config.ba.__dict__, "iterations": iterations})
        extra, extra_state = self._additional_terms(ids, poses)
        hold = mask if (fixed is None and self._holds_scale_gauge()) else None
        res = bundle_adjust(poses, disps, EdgeSet(ii, jj, target, weight), self.coords, self.intr, mask, cfg,
                            extra=extra, extra_state=extra_state, fixed_disparity=hold, visual_dtype=self._dtype,
                            between=self._yield_point)
        self._after_ba(ids, res)
        for n, k in enumerate(ids):   # copies: a view would keep the whole window's solution alive per keyframe
            self.keyframes[k].pose = res.poses[n].clone()
            self.keyframes[k].set_disparities(res.disps[n].clone())
        self.ba_calls += 1
        self._toc("ba", t0)

    def _holds_scale_gauge(self) -> bool:
        """Hook: whether BA holds the fixed keyframes' disparities (``hold_fixed_disparity``)."""
        return self.config.hold_fixed_disparity

    def _additional_terms(self, ids: list[int], poses: torch.Tensor):
        """Hook: extra BA terms ``(AdditionalTerms, state)`` over the window ``ids`` with poses (n, 4, 4), e.g. the
        inertial terms of :class:`vigs_core.vio.odometry.VisualInertialOdometry`; ``(None, None)`` = vision only."""
        return None, None

    def _after_ba(self, ids: list[int], result) -> None:
        """Hook: called with each BA's :class:`~vigs_core.solver.BAResult` (e.g. to keep the extra states)."""

    def _translation_flow(self, kf: Keyframe, rel: torch.Tensor, corr: Correspondences) -> float:
        """Confidence-weighted mean flow (pixels) that the translation of ``rel = T_frame T_kf^-1`` (4, 4)
        causes: projections of the keyframe's points under ``rel`` minus under its rotation alone."""
        targets = torch.stack((rel, rel))
        targets[1, :3, 3] = 0.0                                       # rotation only
        proj = reproject(torch.eye(4, dtype=rel.dtype).expand(2, 4, 4), targets, kf.disp.expand(2, -1),
                         self.coords, self.intr)
        w = self._weights(corr) * proj.valid.all(0)
        d = (proj.uv[0] - proj.uv[1]).norm(dim=-1)
        return float((w * d).sum() / w.sum()) if float(w.sum()) > 0 else 0.0

    def _current_pose(self, f: _Frame) -> torch.Tensor:
        """A posed frame's pose in the map as it is now: relative to its reference keyframe's current pose (BA and
        loop corrections move keyframes; ``odom`` keeps the pose as output), or as output when it has none."""
        return f.rel @ self.keyframes[f.ref].pose if f.ref is not None and f.rel is not None else f.odom

    def _predict_pose(self) -> torch.Tensor:
        posed = []   # the last two posed frames before the current one, oldest first, in the current map
        for f in itertools.islice(reversed(self.frames), 1, None):
            if f.odom is not None:
                posed.insert(0, (f.t_ns, self._current_pose(f)))
                if len(posed) == 2:
                    break
        if len(posed) == 1:
            return posed[0][1]
        (t0, T0), (t1, T1) = posed
        step = T1 @ se3_inverse(T0)
        ratio = (self.frames[-1].t_ns - t1) / max(t1 - t0, 1)
        if abs(ratio - 1.0) > self.config.cv_rescale_tolerance:
            # frames skipped or dropped: constant velocity over time, not over frames, T^r = Exp(r Log T)
            step = se3_exp(ratio * se3_log(step))
        pred = step @ T1
        # re-orthonormalise: each extrapolation doubles the rounding error of the rotation, which otherwise
        # grows from frame to frame until the poses overflow
        pred[:3, :3] = nearest_rotation(pred[:3, :3])
        return pred

    def _track(self, image: np.ndarray) -> None:
        cfg = self.config
        idx = len(self.frames) - 1
        kf = self.keyframes[self.graph.keyframes[-1]]
        pred = self._predict_pose()
        uv, _ = self._warp(kf, pred)
        corr = self._estimate(kf.image, image, uv, forward_backward=False, estimator=self.tracking_estimator)
        t0 = self._tic()
        dt = self._dtype   # the projections' type; the pose stays float64
        pose = align_pose(kf.pose, kf.disp.to(dt), self.coords, self.intr, torch.from_numpy(corr.target),
                          self._weights(corr), pred, cfg.tracking_iterations, cfg.ba.huber_delta).pose.clone()
        self._toc("tracking", t0)
        f = self.frames[idx]
        f.ref, f.rel, f.odom = kf.id, pose @ se3_inverse(kf.pose), pose
        self._send_pose(pose)
        if self.in_keyframe_work or not self.policy.is_keyframe(corr.mean_flow, (f.t_ns - kf.t_ns) * 1e-9,
                                                                self._translation_flow(kf, f.rel, corr)):
            return   # a frame tracked during the keyframe work (module docstring) is not a candidate
        self.in_keyframe_work = True
        try:
            new = self._new_keyframe(idx, image, pose, self._propagate_disparity(kf, corr, pose))
            new_edges = self._insert_into_graph(new)
            self._ba(cfg.ba.iterations)
            for _ in range(cfg.refine_rounds):
                self._refine_edges(new_edges)
                self._ba(cfg.ba.iterations)
            self._yield_point()
            self._after_keyframe()
        finally:
            self.in_keyframe_work = False

    def _after_keyframe(self) -> None:
        """Hook: the end of a new keyframe's work (e.g. the visual-inertial stages)."""
