"""Loop candidate detection and verification for a new keyframe (VIGS-SLAM Sec. 3.1, loop closure).

A new keyframe ``k`` is compared with keyframes at least ``min_keyframe_gap`` (55) keyframes older:

1. orientation: the current estimates' relative rotation angle ``theta = |Log(R_k^T R_j)|`` must be below
   120 deg, tested for all old keyframes at once through ``cos theta = (tr(R_k^T R_j) - 1) / 2``;
2. appearance ranking (ours, to bound the cost): the survivors are ranked by the correlation of small
   zero-mean grey thumbnails and the best ``max_flow_checks`` get dense correspondences ``k -> j``, those
   whose estimated relative rotation is within ``max_check_rotation_deg`` (beyond it, step 5 would need a true
   relative rotation that step 3's flow bound practically rules out);
3. flow: a candidate needs a confidence-weighted mean flow magnitude ``k -> j`` below 22 px (and a mean
   confidence above ``min_mean_confidence``);
4. verification (:func:`vigs_core.loop.two_view.estimate_relative_sim3`): dense two-view consistency in both
   directions (forward-backward flow confidence, reprojection with the keyframes' depths, depth agreement) on
   correspondences ``j -> k`` and ``k -> j`` whose flows start from the warp of each grid at the current
   relative pose estimate (as the frontend's keyframe edges do). Every flow starts from an explicit initial
   flow (zero for step 3), so a pair's correspondences do not depend on the pairs checked before it (see
   :meth:`~vigs_core.frontend.dis_flow.DISFlowEstimator.dense_flow`);
5. drift plausibility (ours): the measured relative pose may differ from the current relative estimate only
   by what odometry can have drifted over the path between the two keyframes (translation at most
   ``max_drift_fraction`` of the path length plus ``min_drift_m``, rotation and scale bounded). A repeated
   texture seen at another place along the path passes 1-4 (the images agree) but would claim a correction
   of the whole distance travelled; a true loop after moderate drift does not.

The best verified candidate (most inliers) becomes a loop edge ``(j, k, Z_jk, information)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Sequence

import cv2
import numpy as np
import torch

from vigs_core.frontend.correspondence import CorrespondenceEstimator, PixelGrid
from vigs_core.geometry import relative_rotation_cosines, se3_inverse, sim3_log, so3_log
from vigs_core.loop.config import LoopDetectionConfig, LoopVerificationConfig
from vigs_core.loop.two_view import TwoViewCorrespondences, TwoViewResult, estimate_relative_sim3
from vigs_core.solver import Intrinsics, reproject
from vigs_core.spill import SpillConfig, SpillStore

F64 = torch.float64


@dataclass
class KeyframeView:
    """What loop closure reads of a keyframe.

    Attributes:
        id: keyframe id (increasing with time).
        image: (H, W) uint8 grey image (undistorted, the frontend's input); None for a keyframe the detector has
            already seen (:meth:`LoopDetector.keep` keeps the image, spilled to disk when old), so the callers'
            views need not keep it.
        T_WC: (4, 4) float64 current world-from-camera pose estimate (rigid).
        disp: (P,) disparities (inverse depths) of the reduced grid pixels, inverse map units (<= 0 = unknown):
            the frontend's own tensor, shared rather than copied (its depths are :attr:`depth`); None where the
            detector already holds this revision of them (:meth:`LoopDetector.depth`).
        unit: product of the depth scales applied to this keyframe by loop corrections before the view was
            taken (its depth units relative to the original ones; see :meth:`KeyframePoseGraph.build`).
        revision, depth_scale: the frontend keyframe's disparity revision and the product of the uniform depth
            scalings applied to it (:class:`vigs_core.frontend.odometry.Keyframe`): disparities of the same
            revision taken at ``depth_scale`` ``s`` are now ``s / depth_scale`` times their values then.
    """

    id: int
    image: np.ndarray | None
    T_WC: torch.Tensor
    disp: torch.Tensor | None
    unit: float = 1.0
    revision: int = 0
    depth_scale: float = 1.0

    @classmethod
    def from_depth(cls, id: int, image: np.ndarray | None, T_WC: torch.Tensor, depth: torch.Tensor,
                   unit: float = 1.0) -> "KeyframeView":
        """The view of a keyframe given by its grid depths (P,) (0 = unknown)."""
        return cls(id, image, T_WC, positive_reciprocal(torch.as_tensor(depth)), unit)

    @property
    def depth(self) -> torch.Tensor:
        """(P,) float64 depths of the grid pixels, map units (0 = unknown); the view must carry ``disp``."""
        return positive_reciprocal(self.disp)

    def bare(self) -> "KeyframeView":
        """This view without image and disparities (for a detector that keeps them, :meth:`LoopDetector.keep`)."""
        return self if self.image is None and self.disp is None else replace(self, image=None, disp=None)


def positive_reciprocal(x: torch.Tensor) -> torch.Tensor:
    """``1 / x`` in float64 where ``x > 0``, else 0: depths from disparities and back, unknown staying unknown."""
    x = x.to(F64)
    return torch.where(x > 0, 1.0 / x.clamp_min(1e-12), 0.0)


@dataclass
class LoopEdge:
    """A verified loop: ``relative = S_old^{-1} S_new`` (4, 4) with ``information`` (7, 7), measured in the
    keyframes' depth units ``unit_old``, ``unit_new`` of the time (:attr:`KeyframeView.unit`)."""

    old: int
    new: int
    relative: torch.Tensor
    information: torch.Tensor
    inlier_fraction: float
    unit_old: float = 1.0
    unit_new: float = 1.0


@dataclass
class LoopDecision:
    """What happened for one new keyframe: the candidates that passed detection (ids), the rejected ones with
    the reason, and the accepted loop edge (or None)."""

    candidates: list[int] = field(default_factory=list)
    rejected: dict[int, str] = field(default_factory=dict)
    accepted: LoopEdge | None = None


def thumbnail(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Zero-mean, unit-norm float32 thumbnail (size[1] * size[0],) of a grey image (area averaging)."""
    small = cv2.resize(image.astype(np.float32), size, interpolation=cv2.INTER_AREA).reshape(-1)
    small -= small.mean()
    return small / max(float(np.linalg.norm(small)), 1e-6)


class ThumbnailRows:
    """Keyframe thumbnails (D,) float32 as the rows of one growing array (capacity doubled when full): a long run
    keeps one per keyframe, and a block of its own per keyframe stayed in the heap between image-sized
    temporaries for the whole run (issue 19); rows also rank all candidates in one product."""

    def __init__(self, dim: int, capacity: int = 256) -> None:
        self._rows = np.zeros((capacity, dim), dtype=np.float32)
        self._index: dict[int, int] = {}

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._index

    def put(self, kf_id: int, thumb: np.ndarray) -> None:
        n = len(self._index)
        if n == len(self._rows):
            grown = np.zeros((2 * n, self._rows.shape[1]), dtype=np.float32)
            grown[:n] = self._rows
            self._rows = grown
        self._rows[n] = thumb
        self._index[kf_id] = n

    def row(self, kf_id: int) -> np.ndarray:
        """The thumbnail of ``kf_id`` (a copy)."""
        return self._rows[self._index[kf_id]].copy()

    def scores(self, ids: list[int], thumb: np.ndarray) -> np.ndarray:
        """Correlations (N,) of the thumbnails of ``ids`` with ``thumb`` (one product over all rows, then picked:
        no copy of the rows)."""
        return (self._rows[:len(self._index)] @ thumb)[[self._index[k] for k in ids]]


def rotation_angle_deg(T_a: torch.Tensor, T_b: torch.Tensor) -> float:
    """Angle (degrees) of the relative rotation of two poses (4, 4)."""
    return math.degrees(float(so3_log(T_a[:3, :3].T @ T_b[:3, :3]).norm()))


def rotation_cosines(T_new: torch.Tensor, T_old: Sequence[torch.Tensor]) -> np.ndarray:
    """``cos`` of the relative rotation angle between ``T_new`` (4, 4) and each pose of ``T_old`` (N of (4, 4)), (N,)
    (:func:`~vigs_core.geometry.relative_rotation_cosines`, where :func:`rotation_angle_deg` per pair costs an
    SO(3) logarithm each; the poses are stacked in one copy, not sliced and converted one by one: the history
    grows with the run)."""
    if not len(T_old):
        return np.zeros(0)
    return relative_rotation_cosines(T_new[:3, :3].to(F64), torch.stack(T_old)[:, :3, :3].to(F64)).numpy()


def path_length(positions: torch.Tensor) -> float:
    """Length of the polyline through positions (N, 3)."""
    return float((positions[1:] - positions[:-1]).norm(dim=-1).sum()) if positions.shape[0] > 1 else 0.0


class LoopDetector:
    """Proposes, verifies and measures loop edges for new keyframes (module docstring).

    Args:
        estimator: dense correspondence estimator on ``estimator.grid`` (the frontend's, or a separate one).
        intrinsics: pinhole intrinsics of the input images.
        detection, verification: settings.
        images: where the keyframe images live (memory for the most recent, disk beyond).
    """

    def __init__(self, estimator: CorrespondenceEstimator, intrinsics: Intrinsics,
                 detection: LoopDetectionConfig | None = None, verification: LoopVerificationConfig | None = None,
                 images: SpillConfig | None = None):
        self.estimator = estimator
        self.grid: PixelGrid = estimator.grid
        self.intr = intrinsics
        self.detection = detection or LoopDetectionConfig()
        self.verification = verification or LoopVerificationConfig()
        w, h = self.detection.thumbnail_size
        self._thumbs = ThumbnailRows(w * h)
        self._images = SpillStore(images, "loop-images")
        self._disps = SpillStore(images, "loop-depths")   # id -> (disparities (P,), [their depth_scale])
        self._revisions: dict[int, int] = {}   # id -> revision of the kept disparities
        self._coords = torch.from_numpy(self.grid.coords()).to(F64)   # (P, 2) grid pixels
        self._last_loop_kf: int | None = None

    def _keep_thumbnail(self, kf: KeyframeView) -> None:
        if kf.id not in self._thumbs:
            self._thumbs.put(kf.id, thumbnail(self.image(kf), self.detection.thumbnail_size))

    def image(self, kf: KeyframeView) -> np.ndarray:
        """The view's image, or the one kept when the keyframe was new (KeyError for a keyframe never seen)."""
        return kf.image if kf.image is not None else self._images.get(kf.id)[0]

    def keep(self, kf: KeyframeView) -> None:
        """Keep what ``kf`` carries for later views without it: its image (once) and its disparities (when of
        a revision not kept yet)."""
        if kf.image is not None and kf.id not in self._images:
            self._images.put(kf.id, kf.image)
        if kf.disp is not None and self._revisions.get(kf.id) != kf.revision:
            # a copy, with its scale in the same entry: a reader on another thread never pairs one with the other's
            # predecessor
            self._disps.put(kf.id, kf.disp.to(F64, copy=True).numpy(), np.array([kf.depth_scale]))
            self._revisions[kf.id] = kf.revision

    def depth(self, kf: KeyframeView) -> torch.Tensor:
        """(P,) float64 grid depths of the view, from its disparities or, without them, from the kept ones
        rescaled to the view's depth scale (KeyError for a keyframe whose disparities were never given)."""
        if kf.disp is not None:
            return kf.depth
        disp, scale = self._disps.get(kf.id)
        return positive_reciprocal(torch.from_numpy(disp)) * (kf.depth_scale / float(scale[0]))

    def close(self) -> None:
        """Drop the kept images and disparities (and their spill folders)."""
        self._images.close()
        self._disps.close()

    def candidates(self, new: KeyframeView, history: Sequence[KeyframeView]) -> list[KeyframeView]:
        """Keyframes of ``history`` old enough and within the orientation bound, best thumbnail match first:
        of the best ``max_flow_checks``, those within ``max_check_rotation_deg``."""
        cfg = self.detection
        old = [kf for kf in history if kf.id <= new.id - cfg.min_keyframe_gap]
        cos_max = math.cos(math.radians(cfg.max_orientation_deg))
        ranked = [(kf, c) for kf, c in zip(old, rotation_cosines(new.T_WC, [kf.T_WC for kf in old])) if c > cos_max]
        for kf in (new, *(kf for kf, _ in ranked)):
            self._keep_thumbnail(kf)
        scores = self._thumbs.scores([kf.id for kf, _ in ranked], self._thumbs.row(new.id))
        ranked = [ranked[i] for i in np.argsort(-scores, kind="stable")]
        cos_check = math.cos(math.radians(cfg.max_check_rotation_deg))
        return [kf for kf, c in ranked[:cfg.max_flow_checks] if c > cos_check]

    def _mean_flow(self, src: KeyframeView, dst: KeyframeView) -> float:
        """Mean flow ``src -> dst`` of dense correspondences from zero flow (which the estimator passes to DIS
        explicitly) with forward-backward confidences; inf without confident matches (step 3)."""
        corr = self.estimator.estimate(self.image(src), self.image(dst))
        weight = np.asarray(corr.weight, dtype=np.float64)
        return corr.mean_flow if weight.mean() > self.detection.min_mean_confidence else float("inf")

    def _warped_correspondences(self, a: KeyframeView, b: KeyframeView, depth_a: torch.Tensor,
                                depth_b: torch.Tensor) -> tuple[TwoViewCorrespondences, TwoViewCorrespondences]:
        """Dense correspondences ``a -> b`` and ``b -> a`` that measure a loop (module docstring, step 4), given
        the keyframes' grid depths (:meth:`depth`): each flow starts from the warp of its source grid at the
        current relative pose estimate (unknown depths warp as points at infinity), and each serves as the
        other's forward-backward check. From zero flow, DIS fell short of the large displacements of
        wide-baseline loops, and the measured loop was too short."""
        T_cw = se3_inverse(torch.stack([a.T_WC, b.T_WC]).to(F64))
        disp = positive_reciprocal(torch.stack([depth_a, depth_b]))
        warp = reproject(T_cw, T_cw.flip(0), disp, self._coords, self.intr)
        targets = torch.where(warp.valid[..., None], warp.uv, float("nan")).numpy()
        ab, ba = self.estimator.estimate_pair(self.image(a), self.image(b), targets[0], targets[1])
        return TwoViewCorrespondences.of(ab), TwoViewCorrespondences.of(ba)

    def drift_check(self, old: KeyframeView, new: KeyframeView, relative: torch.Tensor,
                    history: Sequence[KeyframeView]) -> str:
        """"" when the measured ``S_old^{-1} S_new`` is a plausible drift correction of the current relative
        estimate, else the reason (module docstring, step 5)."""
        cfg = self.verification
        current = torch.linalg.inv(old.T_WC) @ new.T_WC
        between = torch.stack([kf.T_WC for kf in history if old.id <= kf.id <= new.id] + [new.T_WC])[:, :3, 3]
        allowed = cfg.max_drift_fraction * path_length(between) + cfg.min_drift_m
        moved = float((relative[:3, 3] - current[:3, 3]).norm())
        if moved > allowed:
            return f"loop would move the keyframe by {moved:.2f} > {allowed:.2f} (drift allowance along the path)"
        xi = sim3_log(torch.linalg.inv(current) @ relative)
        angle = math.degrees(float(xi[3:6].norm()))
        if angle > cfg.max_drift_rotation_deg:
            return f"loop rotation correction {angle:.1f} deg > {cfg.max_drift_rotation_deg} deg"
        if abs(float(xi[6])) > cfg.max_drift_log_scale:
            return f"loop scale correction exp({float(xi[6]):.2f}) beyond exp(+-{cfg.max_drift_log_scale})"
        return ""

    def detect(self, new: KeyframeView, history: Sequence[KeyframeView]) -> LoopDecision:
        """Look for a loop between ``new`` and the keyframes of ``history`` (all earlier keyframes, any order).
        Keeps what the views carry (:meth:`keep`) and ``new``'s thumbnail for later calls, where the views may
        come without image and disparities."""
        cfg = self.detection
        for kf in (new, *history):
            self.keep(kf)
        self._keep_thumbnail(new)
        decision = LoopDecision()
        if self._last_loop_kf is not None and new.id - self._last_loop_kf < cfg.min_keyframes_between_loops:
            return decision
        history = sorted(history, key=lambda kf: kf.id)
        best: tuple[TwoViewResult, KeyframeView] | None = None
        depth_new = None
        for old in self.candidates(new, history):
            if self._mean_flow(new, old) >= cfg.max_mean_flow_px:
                continue
            decision.candidates.append(old.id)
            depth_old = self.depth(old)   # read once (an old keyframe's may come from the spill on disk)
            depth_new = self.depth(new) if depth_new is None else depth_new
            ba, ab = self._warped_correspondences(old, new, depth_old, depth_new)
            # a = old, b = new: Z = S_old^{-1} S_new
            result = estimate_relative_sim3(depth_old, depth_new, ba, ab, self.grid, self.intr, self.verification)
            reason = result.reason if not result.accepted else self.drift_check(old, new, result.relative, history)
            if reason:
                decision.rejected[old.id] = reason
                continue
            if best is None or result.inlier_fraction > best[0].inlier_fraction:
                best = (result, old)
        if best is not None:
            result, old = best
            decision.accepted = LoopEdge(old.id, new.id, result.relative, result.information, result.inlier_fraction,
                                         old.unit, new.unit)
            self._last_loop_kf = new.id
        return decision
