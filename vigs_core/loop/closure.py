"""Loop closure as one object beside tracking (VIGS-SLAM Sec. 3.1): per new keyframe, grow the relative-pose
graph and queue the keyframe for detection; a single worker thread detects and verifies loops and runs PGBA, so
tracking only pays for building the small snapshots it hands over. Finished corrections are handed out by
:meth:`LoopClosure.poll`; the caller applies them (:mod:`vigs_core.loop.apply`), so this module knows nothing of
the frontend's or the mapper's internals (:class:`vigs_core.loop.driver.LoopClosureDriver` binds them).

Consistency with tracking going on: PGBA runs on a snapshot of the keyframe poses taken by the caller
(:meth:`LoopClosure.start_pgba`) and returns left corrections, applied to whatever the states have become. A
new PGBA is not started while a result waits to be applied, so no correction is ever computed from a state
that misses an earlier one.

Typical use::

    loop = LoopClosure(config, estimator, intrinsics)
    # after each new keyframe's BA
    loop.add_keyframe(view, history_views, odometry_information)
    # every frame
    result = loop.poll()
    if result:
        updates = apply_to_odometry(odom, result.corrections)
        apply_to_mapper(mapper, updates)
        loop.record_applied({k: c for k, (_, c) in updates.items()})
    loop.start_pgba(current_poses)          # no-op unless a loop is pending and nothing is in flight
"""
from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import torch

from vigs_core.frontend.correspondence import CorrespondenceEstimator
from vigs_core.loop.config import LoopConfig
from vigs_core.loop.detection import KeyframeView, LoopDecision, LoopDetector
from vigs_core.loop.pgba import KeyframePoseGraph, PGBAResult, run_pgba
from vigs_core.solver import Intrinsics


InformationSource = dict[int, torch.Tensor] | Callable[[], dict[int, torch.Tensor] | None] | None
MAX_REASONS = 200  # rejection reasons kept for the report (the counters count all)


@dataclass
class LoopStats:
    """Counters and timings for the run report: candidates passing detection, loops accepted and rejected
    (with the reasons of the first rejections), PGBA runs and the seconds of each, detection seconds in total, and
    the seconds the caller waited for a worker process that lagged behind (:class:`~vigs_core.child_process.
    ChildChannel`; 0 with a thread) and that process's peak resident memory, MiB (None without one, or before
    it synced or closed)."""

    candidates: int = 0
    loops_found: int = 0
    loops_rejected: int = 0
    pgba_runs: int = 0
    pgba_seconds: list[float] = field(default_factory=list)
    detection_seconds: float = 0.0
    accepted_pairs: list[tuple[int, int]] = field(default_factory=list)
    rejection_reasons: list[str] = field(default_factory=list)
    queue_wait_seconds: float = 0.0
    process_peak_rss_mb: float | None = None

    def as_dict(self) -> dict:
        n = len(self.pgba_seconds)
        return {
            "candidates": self.candidates,
            "loops_found": self.loops_found,
            "loops_rejected": self.loops_rejected,
            "accepted_pairs": [list(p) for p in self.accepted_pairs],
            "pgba_runs": self.pgba_runs,
            "pgba_seconds_mean": sum(self.pgba_seconds) / n if n else 0.0,
            "pgba_seconds_max": max(self.pgba_seconds) if n else 0.0,
            "detection_seconds": self.detection_seconds,
            "queue_wait_seconds": self.queue_wait_seconds,
            "process_peak_rss_mb": self.process_peak_rss_mb,
            "rejection_reasons": self.rejection_reasons[:20],
        }


class LoopClosure:
    """Detection + relative-pose graph + PGBA on one worker thread (module docstring).

    Args:
        config: :class:`~vigs_core.loop.config.LoopConfig` (``asynchronous=False`` runs every job inline).
        estimator: dense correspondence estimator (its grid is the keyframes' depth grid); used by the worker
            only, so give loop closure its own instance when tracking uses one concurrently.
        intrinsics: pinhole intrinsics of the input images.
    """

    def __init__(self, config: LoopConfig, estimator: CorrespondenceEstimator, intrinsics: Intrinsics) -> None:
        self.config = config
        self.detector = LoopDetector(estimator, intrinsics, config.detection, config.verification, config.images)
        self.graph = KeyframePoseGraph(config.graph)
        self.stats = LoopStats()
        self.decisions: dict[int, LoopDecision] = {}   # new keyframe id -> decision, where there were candidates
        self.units: dict[int, float] = {}   # keyframe id -> product of the depth scales applied (default 1)
        self._lock = threading.Lock()
        self._jobs: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._pending_loops = 0
        self._in_flight = False
        self._result: PGBAResult | None = None
        self._error: BaseException | None = None

    # ------------------------------------------------------------------ caller side
    def add_keyframe(self, new: KeyframeView, history: Sequence[KeyframeView],
                     odometry_information: InformationSource = None, metric: bool = False) -> None:
        """Queue ``new`` for the worker: its odometry edges to its predecessors join the graph (optional
        ``{previous id: (7, 7)}`` information, or a function returning it, evaluated on the worker thread), then
        loop detection runs against ``history`` (the earlier keyframes; snapshots, not modified). ``metric``: the
        keyframe was created while the odometry was metric (:meth:`KeyframePoseGraph.add_keyframe`).

        The detector keeps the images and disparities the views carry now (spilled when old), and the job holds
        the views without them: a worker thread that lags does not hold an image per queued keyframe in memory."""
        for v in (new, *history):
            self.detector.keep(v)
        new, history = new.bare(), [v.bare() for v in history]

        def job() -> None:
            info = odometry_information() if callable(odometry_information) else odometry_information
            with self._lock:
                self.graph.add_keyframe(new.id, info, metric)
            self._detect(new, history)

        self._submit(job)

    @property
    def pending(self) -> bool:
        """Loops accepted since the last PGBA started."""
        with self._lock:
            return self._pending_loops > 0

    def start_pgba(self, poses: dict[int, torch.Tensor]) -> bool:
        """Queue PGBA over the whole graph at the current poses ``{id: T_WC (4, 4)}`` when a loop is pending, no
        PGBA is in flight and no result waits to be polled; True when queued."""
        with self._lock:
            if self._pending_loops == 0 or self._in_flight or self._result is not None:
                return False
            graph, ids = self.graph.build(poses, self.units)
            loops = len(self.graph.loops)
            self._pending_loops = 0
            self._in_flight = True
            self.stats.pgba_runs += 1
        self._submit(lambda: self._pgba(graph, ids, loops))
        return True

    def record_applied(self, scales: dict[int, float]) -> None:
        """Tell loop closure that corrections with depth scales ``{id: c}`` were applied: the keyframes' depth
        units change, which loop edges measured earlier must follow; new views carry :meth:`unit`."""
        with self._lock:
            for k, c in scales.items():
                self.units[k] = self.units.get(k, 1.0) * float(c)

    def unit(self, kf_id: int) -> float:
        """Current depth units of a keyframe (product of the applied correction scales)."""
        with self._lock:
            return self.units.get(kf_id, 1.0)

    def poll(self) -> PGBAResult | None:
        """A finished PGBA's corrections (once), else None; re-raises an error of the worker."""
        with self._lock:
            if self._error is not None:
                err, self._error = self._error, None
                raise RuntimeError("loop closure failed on its worker thread") from err
            out, self._result = self._result, None
        return out

    def wait(self) -> PGBAResult | None:
        """Block until every queued job (detections, PGBA) is done, then :meth:`poll`."""
        self._jobs.join()
        return self.poll()

    def close(self, discard_queued: bool = False) -> int:
        """Stop the worker thread after the queued jobs, or (``discard_queued``) after the running one only: a
        node shutting down waits for no backlog of detections whose results nobody will receive. Returns the
        number of jobs discarded."""
        discarded = 0
        if self._thread is not None:
            while discard_queued:
                try:
                    self._jobs.get_nowait()
                except queue.Empty:
                    break
                self._jobs.task_done()
                discarded += 1
            self._jobs.put(None)
            self._thread.join()
            self._thread = None
        self.detector.close()
        return discarded

    # ------------------------------------------------------------------ worker side
    def _submit(self, job: Callable[[], None]) -> None:
        if not self.config.asynchronous:
            self._run(job)
            return
        if self._thread is None:
            self._thread = threading.Thread(target=self._work, name="loop-closure", daemon=True)
            self._thread.start()
        self._jobs.put(job)

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            try:
                if job is None:
                    return
                self._run(job)
            finally:
                self._jobs.task_done()

    def _run(self, job: Callable[[], None]) -> None:
        try:
            job()
        except BaseException as err:  # handed to the caller by poll()
            with self._lock:
                self._error = err
                self._in_flight = False

    def _detect(self, new: KeyframeView, history: list[KeyframeView]) -> None:
        t0 = time.perf_counter()
        decision = self.detector.detect(new, history)
        with self._lock:
            if decision.candidates:
                self.decisions[new.id] = decision
            self.stats.detection_seconds += time.perf_counter() - t0
            self.stats.candidates += len(decision.candidates)
            self.stats.loops_rejected += len(decision.rejected)
            reasons = [f"{new.id}-{k}: {r}" for k, r in decision.rejected.items()]
            self.stats.rejection_reasons.extend(reasons[:max(0, MAX_REASONS - len(self.stats.rejection_reasons))])
            if decision.accepted is not None:
                self.graph.add_loop(decision.accepted)
                self.stats.loops_found += 1
                self.stats.accepted_pairs.append((decision.accepted.old, decision.accepted.new))
                self._pending_loops += 1

    def _pgba(self, graph, ids: list[int], loops: int) -> None:
        result = run_pgba(graph, ids, loops, self.config.pose_graph)
        with self._lock:
            self._result = result
            self._in_flight = False
            self.stats.pgba_seconds.append(result.seconds)
