"""Loop closure bound to the in-process pipeline: a :class:`~vigs_core.frontend.DenseOdometry` (or its
visual-inertial subclass) and optionally the Gaussian mapper (VIGS-SLAM Sec. 3.1 and 3.3).

:meth:`LoopClosureDriver.step`, called after every ``odometry.process(...)``:

1. applies a finished PGBA: keyframe poses and disparities, frame poses (:func:`~vigs_core.loop.apply.
   apply_to_odometry`), inertial velocities ``v' = c R_c v`` of the visual-inertial odometry, and one batch of
   keyframe pose/scale updates for the mapper's anchored Gaussians (or the ``on_update`` callback);
2. registers the keyframes created since the last call: their views (image, ``T_WC``, grid disparities) and
   an odometry edge to the previous keyframe whose information comes from the frontend's dense correspondences
   of the pair (:func:`~vigs_core.loop.two_view.edge_information`; the configured standard deviations when the
   frontend has none);
3. starts PGBA on the current poses when a loop is pending. Every keyframe created while the visual-inertial
   odometry is metric gets an absolute prior of standard deviation ``sigma_metric_log_scale`` on its log scale:
   the IMU observes the scale at each such keyframe, so a loop corrects position and orientation drift and does
   not trade the metric scale away (:meth:`~vigs_core.loop.pgba.KeyframePoseGraph.build`).

Detection, the odometry-edge information and PGBA run on the loop-closure worker: a child process by default
(:mod:`vigs_core.loop.process`, ``LoopConfig.process``), else a thread; the tracking thread only builds keyframe
views (cached, sent to a child process once per change; image and disparities only when new and the disparities
once more as the keyframe leaves the frontend's window, :meth:`LoopClosureDriver._current_views`) and applies
corrections.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from vigs_core.frontend.correspondence import Correspondences, PixelGrid
from vigs_core.frontend.dis_flow import DISFlowEstimator
from vigs_core.geometry import se3_inverse
from vigs_core.loop.apply import apply_to_mapper, apply_to_odometry, corrections_for, rotate_velocities
from vigs_core.loop.closure import LoopClosure
from vigs_core.loop.config import LoopConfig, LoopVerificationConfig
from vigs_core.loop.detection import KeyframeView, positive_reciprocal
from vigs_core.loop.pgba import PGBAResult
from vigs_core.loop.process import LoopClosureProcess
from vigs_core.loop.two_view import TwoViewCorrespondences, edge_information
from vigs_core.solver import Intrinsics

F64 = torch.float64


def keyframe_views(kfs: list[Any], units: list[float], images: list[bool], disps: list[bool]) -> list[KeyframeView]:
    """The :class:`KeyframeView` of frontend keyframes (``pose`` world->camera, ``disp`` grid inverse depth, shared
    with the view, ``revision``, ``depth_scale``) whose depth units are ``units`` (see :class:`KeyframeView`),
    with the image where ``images`` and the disparities where ``disps``, the poses inverted in one batch (a loop
    correction changes every keyframe at once)."""
    if not kfs:
        return []
    T_WC = se3_inverse(torch.stack([kf.pose for kf in kfs]).to(F64))
    return [KeyframeView(int(kf.id), kf.image if i else None, T, kf.disp if d else None, unit, kf.revision,
                         kf.depth_scale) for kf, T, unit, i, d in zip(kfs, T_WC.unbind(0), units, images, disps)]


@dataclass
class OdometryEdgeInformation:
    """The information of the odometry edge ``(a, b)`` from the frontend's dense correspondences of the pair
    (:func:`~vigs_core.loop.two_view.edge_information`), computed when called (on the loop-closure worker): the
    keyframes' poses ``T_WC`` (4, 4) and grid depths (P,) at registration (float64 arrays: they pickle fast), the
    correspondences ``a -> b`` and, when the frontend has them, ``b -> a``. Picklable, for the worker process."""

    a: int
    b: int
    T_WC_a: np.ndarray
    T_WC_b: np.ndarray
    depth_a: np.ndarray
    depth_b: np.ndarray
    forward: Correspondences
    backward: Correspondences | None
    grid: PixelGrid
    intr: Intrinsics
    verification: LoopVerificationConfig

    def __call__(self) -> dict[int, torch.Tensor]:
        Z = torch.from_numpy(np.linalg.inv(self.T_WC_a) @ self.T_WC_b)
        back = None if self.backward is None else TwoViewCorrespondences.of(self.backward)
        info = edge_information(Z, torch.from_numpy(self.depth_a), torch.from_numpy(self.depth_b),
                                TwoViewCorrespondences.of(self.forward), back, self.grid, self.intr,
                                self.verification)
        return {self.a: info}


class LoopClosureDriver:
    """Loop closure beside a running odometry (module docstring).

    Args:
        config: loop-closure settings.
        odometry: the frontend (``keyframes``, ``frames``, ``edges``, ``grid``, ``intr``, ``config.tracking_flow``).
        mapper: optional :class:`~vigs_core.mapping.mapper.GaussianMapper` fed with camera poses ``T_WC``.
        on_update: optional callback ``{kf_id: (T_WC (4, 4), depth scale)}`` called with every applied
            correction (e.g. to publish keyframe pose updates, or to feed a mapper with another pose convention).
    """

    def __init__(self, config: LoopConfig, odometry: Any, mapper: Any = None,
                 on_update: Callable[[dict[int, tuple[torch.Tensor, float]]], None] | None = None) -> None:
        self.config = config
        self.odometry = odometry
        self.mapper = mapper
        self.on_update = on_update
        # the worker's own instance, with the per-frame tracking settings: loop pairs are verified by a full
        # two-view solve, which the keyframe edges' finer (about 3x dearer) flow does not make more reliable
        if config.asynchronous and config.process:
            self.closure = LoopClosureProcess(config, odometry.grid, odometry.config.tracking_flow, odometry.intr)
        else:
            self.closure = LoopClosure(config, DISFlowEstimator(odometry.grid, odometry.config.tracking_flow),
                                       odometry.intr)
        self.corrections_applied = 0
        self._registered: list[int] = []
        # cached views (without image and disparities), with the keyframe's pose tensor, disparity revision,
        # depth scale and whether it was in the frontend's window when they were built
        self._views: dict[int, tuple[torch.Tensor, int, float, bool, KeyframeView]] = {}
        self._changes = odometry.keyframes.subscribe()   # the odometry's change log (every keyframe at first)
        self._dirty: set[int] = set()                    # keyframes it listed since the views were refreshed

    def step(self) -> PGBAResult | None:
        """Apply a finished PGBA, register new keyframes, start PGBA if a loop waits; returns the applied result."""
        result = self.closure.poll()
        if result is not None:
            self.apply(result)
        self._dirty.update(self._changes.take())
        new = sorted(k for k in self._dirty if not self._registered or k > self._registered[-1])
        if new:
            views = self._current_views()
            carrying = [k for k, v in views.items() if v.image is not None or v.disp is not None]
            view = lambda i: views[i] if i in views else self._views[i][4]   # noqa: E731  (rebuilt, else cached)
            for k in new:
                history = [view(i) for i in self._registered]
                prev = self._registered[-1] if self._registered else None
                edges = {e: self.odometry.edges[e] for e in ((prev, k), (k, prev)) if e in self.odometry.edges}
                a = None if prev is None else view(prev)
                b = view(k)
                info = None if a is None or (prev, k) not in edges else OdometryEdgeInformation(
                    prev, k, a.T_WC.numpy().copy(), b.T_WC.numpy().copy(), self._depth(prev), self._depth(k),
                    edges[(prev, k)], edges.get((k, prev)), self.odometry.grid,
                    self.odometry.intr, self.config.verification)
                self.closure.add_keyframe(b, history, info, self._metric())
                self._registered.append(k)
                for i in [i for i in carrying if i <= k]:   # handed over: not sent again in this step
                    views[i] = self._views[i][4]
                    carrying.remove(i)
        if self.closure.pending:
            self._start_pgba()
        return result

    def finish(self) -> None:
        """At the end of a run: wait for detection, run the last PGBA if loops are pending, apply everything
        (the worker is closed also when this raises its error)."""
        try:
            while True:
                result = self.closure.wait()
                if result is not None:
                    self.apply(result)
                if not self.closure.pending:
                    break
                self._start_pgba()
        finally:
            self.closure.close()

    def _start_pgba(self) -> None:
        T_WC = se3_inverse(torch.stack([self.odometry.keyframes[k].pose for k in self._registered]).to(F64))
        poses = dict(zip(self._registered, T_WC.unbind(0)))
        self.closure.start_pgba(poses)

    def apply(self, result: PGBAResult) -> dict[int, tuple[torch.Tensor, float]]:
        """Apply PGBA corrections to the odometry (and its inertial states), the mapper and ``on_update``."""
        corrections = corrections_for(sorted(self.odometry.keyframes), result.corrections)
        updates = apply_to_odometry(self.odometry, corrections)
        self.closure.record_applied({k: c for k, (_, c) in updates.items()})
        vio = getattr(self.odometry, "vio", None)
        if vio is not None:
            rotate_velocities(vio.states, corrections)
        if self.mapper is not None:
            apply_to_mapper(self.mapper, updates)
        if self.on_update is not None:
            self.on_update(updates)
        self.corrections_applied += 1
        return updates

    def _current_views(self) -> dict[int, KeyframeView]:
        """Views of the keyframes rebuilt since the last call: those the odometry's change log listed (new, BA in
        the window, the visual-inertial world alignment that re-expresses every keyframe, a loop correction, a
        keyframe leaving the window) whose pose tensor, revision, depth scale or window membership differ from
        their cached view's; the others' views are the cache's (``_views``).

        A view carries image and disparities when new, and the disparities again when the keyframe has just left
        the window (their last revision: the frontend drops them at the next frame). The detector keeps what
        views carry (:meth:`LoopDetector.keep`), so the cache holds views without either."""
        self._dirty.update(self._changes.take())
        window = set(self.odometry.graph.keyframes)
        stale, images, disps = [], [], []
        for k in sorted(self._dirty):
            kf = self.odometry.keyframes[k]
            cached = self._views.get(k)
            state = (kf.revision, kf.depth_scale, k in window)
            if cached is None or cached[0] is not kf.pose or cached[1:4] != state:
                stale.append(kf)
                images.append(cached is None)
                disps.append(cached is None or (k not in window and kf.disp is not None))
        views = {}
        units = [self.closure.unit(kf.id) for kf in stale]
        for kf, view in zip(stale, keyframe_views(stale, units, images, disps)):
            views[kf.id] = view
            self._views[kf.id] = (kf.pose, kf.revision, kf.depth_scale, kf.id in window, view.bare())
        self._dirty.clear()
        return views

    def _depth(self, k: int) -> np.ndarray:
        """(P,) float64 grid depths of window keyframe ``k`` (0 = unknown), from the frontend's disparities."""
        return positive_reciprocal(self.odometry.keyframes[k].disp).numpy()

    def _metric(self) -> bool:
        vio = getattr(self.odometry, "vio", None)
        return bool(vio is not None and getattr(vio, "metric", False))

    def report(self) -> dict:
        """Loop-closure numbers for report.json."""
        out = self.closure.stats.as_dict()
        out["corrections_applied"] = self.corrections_applied
        return out
