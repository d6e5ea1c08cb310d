"""The Gaussian mapper inside ``vigs run``: feeds the odometry's keyframes to a
:class:`~vigs_core.mapping.GaussianMapper` running in a child process (:mod:`vigs_core.mapping.process`; or on
a thread of this one), keeps the map on the odometry's keyframe poses, and measures render quality at the end
(VIGS-SLAM Sec. 3.3).

Per processed frame (:meth:`OnlineMapping.step`, tracking thread, only queue operations on the mapper):

* **New keyframes** are sent once ``keyframe_delay`` newer keyframes exist (BA has refined their disparities):
  the undistorted grey image at the processing resolution, camera pose ``T_WC = inv(T_cw)`` and depth
  ``z = 1 / d`` on the frontend's reduced grid (the mapper resamples it), with ``z = 0`` (invalid) where the
  disparity is not positive, where no frontend edge leaving the keyframe is at least ``min_confidence``
  confident in that cell, or beyond ``max_depth_ratio`` times the keyframe's median depth.
* **Pose updates**: every sent keyframe whose pose moved by more than ``pose_tolerance`` (BA over the window,
  the visual-inertial world alignment that rescales and gravity-aligns everything) is sent in one batch
  ``update_keyframe_poses({k: T_WC}, {k: c_k})`` with the depth scale ``c_k``, the growth of the keyframe's
  depths since they were last sent (``c_k = s`` for a world rescaled by ``s``;
  :class:`~vigs_core.frontend.keyframe_changes.SentKeyframes`). Loop-closure corrections go to the mapper through
  :class:`~vigs_core.loop.LoopClosureDriver` (``mapper=``) and are recorded here by :meth:`on_correction`
  so they are not sent twice.

At the end (:meth:`finish`) the remaining keyframes are sent and the mapper drained; :meth:`evaluate` renders
every ``eval_stride``-th frame that is not a keyframe at its final pose and compares it with the undistorted
input image (PSNR, SSIM at the render resolution), then optionally runs ``final_refine_iterations`` steps of
colour refinement and evaluates again. Both give way to a ``stop`` request (a signal after the run loop): the
drain checks it every ``WAIT_POLL_S`` and hands over to the bounded shutdown drain, the refinement runs in
chunks of ``REFINE_CHUNK`` steps and keeps those done.
"""
from __future__ import annotations

import itertools
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from vigs_core.frontend.keyframe_changes import SentKeyframes
from vigs_core.geometry import se3_inverse, se3_log
from vigs_core.mapping import GaussianMapper, MapperConfig
from vigs_core.mapping.process import MapperProcess
from vigs_core.ranges import bounded

F64 = torch.float64
WAIT_POLL_S = 0.5    # how often the end-of-run drain checks for a stop request
REFINE_CHUNK = 50    # refinement steps between two checks for a stop request


@dataclass
class MappingConfig:
    """Settings of the mapping inside ``vigs run``.

    Args:
        enabled: run the Gaussian mapper (its CPU cost per keyframe and per evaluated frame: docs/benchmarks.md,
            issue 23). Tracking never waits for it but shares the CPU with it; the run waits for the mapper's
            backlog at the end.
        mapper: the mapper's settings (:class:`vigs_core.mapping.MapperConfig`).
        process: the mapper runs in a child process (:class:`vigs_core.mapping.process.MapperProcess`: it takes
            neither tracking's interpreter lock nor its heap); False: a worker thread of this process.
        process_nice: niceness increment of that child process: on a saturated CPU tracking keeps its core.
        keyframe_delay: a keyframe is mapped once this many newer keyframes exist (its depth refined by BA);
            below the frontend's window (its image is dropped when it leaves the window).
        min_confidence: grid cells whose best outgoing-edge flow confidence is below this get no depth, [0, 1].
        max_depth_ratio: depths beyond this multiple of the keyframe's median depth are treated as invalid.
        pose_tolerance: keyframe pose change (translation in world units plus rotation in rad, norm of the
            SE(3) log) or depth-scale change (|log c|) above which the mapper gets the new pose.
        eval_stride: every n-th input frame that is not a keyframe is rendered for PSNR/SSIM (0: none).
        eval_max_frames: at most this many of those are kept (a uniform random sample of them, reservoir
            sampling with a fixed seed), so a long run's evaluation images and time stay bounded (every 5th
            frame of an hour at 20 Hz would be 650 MB of images and an hour of rendering at the end).
        final_refine_iterations: colour-refinement steps after the run (0: none; a run cut short skips them), on
            keyframes drawn uniformly from all; metrics are reported before and after. On by default: ``vigs run``
            is an offline run, and the pass costs one optimisation step each (docs/benchmarks.md, issue 23).
    """

    enabled: bool = True
    mapper: MapperConfig = field(default_factory=MapperConfig)
    process: bool = True
    process_nice: int = bounded(10, 0, 19)
    keyframe_delay: int = bounded(1, 0)
    min_confidence: float = bounded(0.1, 0, 1)
    max_depth_ratio: float = bounded(5.0, 0)
    pose_tolerance: float = bounded(1e-4, 0)
    eval_stride: int = bounded(5, 0)
    eval_max_frames: int = bounded(100, 0)
    final_refine_iterations: int = bounded(100, 0)

    def __post_init__(self) -> None:
        if self.keyframe_delay < 0 or self.eval_stride < 0 or self.final_refine_iterations < 0 or \
                self.eval_max_frames < 0:
            raise ValueError(
                f"mapping: need keyframe_delay, eval_stride, final_refine_iterations >= 0; got "
                f"{self.keyframe_delay}, {self.eval_stride}, {self.final_refine_iterations}"
            )
        if self.max_depth_ratio <= 1.0 or self.pose_tolerance <= 0:
            raise ValueError(
                f"mapping: need max_depth_ratio > 1 and pose_tolerance > 0; got {self.max_depth_ratio}, "
                f"{self.pose_tolerance}"
            )


class OnlineMapping:
    """The mapper bound to a running odometry (module docstring).

    Args:
        config: :class:`MappingConfig`.
        odometry: the frontend (:class:`vigs_core.frontend.DenseOdometry` or its visual-inertial subclass):
            ``keyframes`` (``pose`` world->camera, ``disp`` (P,), ``image``), ``frames``, ``edges``, ``grid``.
        camera: the undistorted pinhole camera of the processed images.
        device: torch device of the map.
    """

    def __init__(self, config: MappingConfig, odometry: Any, camera, device: torch.device | str = "cpu") -> None:
        window = odometry.graph.config.window
        if config.keyframe_delay >= window:   # the frontend drops a keyframe's image once it leaves the window
            raise ValueError(f"mapping.keyframe_delay ({config.keyframe_delay}) must be below the frontend's "
                             f"window ({window}): a keyframe is mapped while its image is still kept")
        self.config = config
        self.odometry = odometry
        self._changes = odometry.keyframes.subscribe()   # keyframes changed since the last step (new ones too)
        self._unsent: set[int] = set()                   # keyframes not sent to the mapper yet
        if config.process:
            self.mapper: GaussianMapper | MapperProcess = MapperProcess(config.mapper, camera, device,
                                                                        config.process_nice)
        else:
            self.mapper = GaussianMapper(config.mapper, camera, device)
            self.mapper.run_async()
        self._sent = SentKeyframes()                                    # what the mapper has of each keyframe
        self._eval_images: dict[int, np.ndarray] = {}                   # frame index -> processed image
        self._eval_offered = 0                                          # frames offered to the sample so far
        self._eval_rng = random.Random(0)
        self._frame_index = 0
        self.pose_update_batches = 0
        self.wait_seconds = 0.0

    # ------------------------------------------------------------------ tracking thread
    def step(self, image: np.ndarray) -> None:
        """After ``odometry.process(t, image)``: keep ``image`` for evaluation if sampled, send pose updates of
        mapped keyframes, then keyframes that are old enough."""
        stride = self.config.eval_stride
        if stride and self._frame_index % stride == 0:
            self._sample_for_evaluation(image)
        self._frame_index += 1
        self._send_pose_updates()
        newest = list(itertools.islice(reversed(self.odometry.keyframes), self.config.keyframe_delay + 1))
        if len(newest) > self.config.keyframe_delay:   # ids rise with insertion: the newest ``delay`` wait
            for k in sorted(k for k in self._unsent if k <= newest[-1]):
                self._send_keyframe(k)

    def on_correction(self, updates: dict[int, tuple[torch.Tensor, float]]) -> None:
        """``on_update`` callback of the loop-closure driver: the driver has queued ``{kf_id: (T_WC, c)}`` on the
        mapper; record the corrected poses and disparities as sent."""
        for k in updates:
            if k in self._sent:
                kf = self.odometry.keyframes[k]
                self._sent.record(kf, se3_inverse(kf.pose.to(F64)))

    def finish(self, drain: bool = True, interrupted_drain_s: float = 10.0,
               stop: Callable[[], bool] | None = None) -> bool:
        """Send pending pose updates and every keyframe not yet mapped, then wait for the mapper to drain
        (``drain`` False, an interrupted run, or ``stop()`` true while waiting: stop it after the optimisation
        step it is taking and insert what is queued without refinement, for at most ``interrupted_drain_s``:
        :meth:`GaussianMapper.drain`). Returns whether the mapper drained with its refinement."""
        self._send_pose_updates()
        for k in sorted(self._unsent):
            self._send_keyframe(k)
        t0 = time.perf_counter()
        while drain and not self.mapper.wait_idle(WAIT_POLL_S):
            drain = not (stop is not None and stop())
        self.mapper.stop()
        if not drain:
            self.mapper.drain(interrupted_drain_s)
        self.wait_seconds = time.perf_counter() - t0
        return drain

    # ------------------------------------------------------------------ end of run
    def _sample_for_evaluation(self, image: np.ndarray) -> None:
        """Reservoir sampling (Vitter's algorithm R): each offered frame ends up kept with the same probability."""
        self._eval_offered += 1
        if len(self._eval_images) < self.config.eval_max_frames:
            self._eval_images[self._frame_index] = image
            return
        j = self._eval_rng.randrange(self._eval_offered)
        if j < len(self._eval_images):
            del self._eval_images[list(self._eval_images)[j]]
            self._eval_images[self._frame_index] = image

    def evaluate(self, t_ns: np.ndarray, T_WC: np.ndarray, stop: Callable[[], bool] | None = None) -> dict:
        """Mapping numbers for report.json, with render quality at the final frame poses ``T_WC`` (N, 4, 4) of
        the frames at times ``t_ns`` (N,) ns (call after :meth:`finish`); the refinement ends early once
        ``stop()`` is true (``refined.iterations``: the steps taken; none taken, no ``refined``; either way
        ``interrupted`` is true, as when the run cut the map short before it)."""
        pose_at = {int(t): T for t, T in zip(t_ns, T_WC)}
        views = []
        for idx, image in self._eval_images.items():
            frame = self.odometry.frames[idx]
            if not frame.keyframe and frame.t_ns in pose_at:
                views.append((pose_at[frame.t_ns], image))
        summary = self.mapper.summary()
        stats = summary.stats
        out = {
            "gaussians": summary.gaussians,
            "keyframes_mapped": stats.keyframes,
            "keyframes_released": stats.released,
            "mapping_s": round(stats.mapping_seconds, 3),
            "keyframes_per_s": round(stats.keyframes / stats.mapping_seconds, 3) if stats.mapping_seconds else None,
            "wait_at_end_s": round(self.wait_seconds, 3),
            "pose_update_batches": self.pose_update_batches,
            "gaussians_added": stats.added, "gaussians_pruned": stats.pruned,
            "render_size": list(summary.render_size),
            "keyframes_on_disk": summary.keyframes_on_disk,
            "keyframe_disk_reads": summary.keyframe_disk_reads,
        }
        t0 = time.perf_counter()
        out["online"] = _rounded(self.mapper.evaluate(views))
        out["eval_s"] = round(time.perf_counter() - t0, 3)
        t0, done = time.perf_counter(), 0
        while done < self.config.final_refine_iterations:
            if stop is not None and stop():
                out["interrupted"] = True   # the refinement cut short (or never started) by a signal
                break
            step = min(REFINE_CHUNK, self.config.final_refine_iterations - done)
            self.mapper.refine(step)
            done += step
        if done > 0:
            out["refined"] = {**_rounded(self.mapper.evaluate(views)), "iterations": done,
                              "refine_s": round(time.perf_counter() - t0, 3)}
        return out

    def save(self, path: str | Path) -> Path:
        """Write the map (3DGS PLY at ``path``) and its keyframe sidecar; returns the sidecar path."""
        return self.mapper.save(path)

    def close(self) -> None:
        """Stop the mapper and free its keyframe store (and its process); the run's map is saved before."""
        self.mapper.close()

    # ------------------------------------------------------------------ internals
    def _depth(self, k: int, disp: torch.Tensor) -> np.ndarray:
        """Grid depth (rows, cols) of keyframe ``k`` from its disparities (P,), 0 where invalid."""
        grid = self.odometry.grid
        d = disp.numpy()
        ok = np.isfinite(d) & (d > 0)
        weights = [c.weight for (i, _), c in self.odometry.edges.items() if i == k]
        if weights:
            ok &= np.max(np.stack(weights), axis=0) >= self.config.min_confidence
        z = np.zeros_like(d)
        z[ok] = 1.0 / d[ok]
        if ok.any():
            z[z > self.config.max_depth_ratio * np.median(z[ok])] = 0.0
        return z.reshape(grid.rows, grid.cols).astype(np.float32)

    def _send_keyframe(self, k: int) -> None:
        kf = self.odometry.keyframes[k]
        T_WC = se3_inverse(kf.pose.to(F64))
        self.mapper.add_keyframe(k, T_WC, kf.image, self._depth(k, kf.disp.to(F64)), kf.t_ns)
        self._sent.record(kf, T_WC)
        self._unsent.discard(k)

    def _send_pose_updates(self) -> None:
        """Pose and depth-scale updates of the sent keyframes the odometry changed since the last call (its
        change log); keyframes new to the log wait in ``_unsent``."""
        poses, scales = {}, {}
        for k in self._changes.take():
            if k not in self._sent:
                self._unsent.add(k)
                continue
            kf = self.odometry.keyframes[k]
            change = self._sent.change(kf)
            if change is None:
                continue
            T_old, c = change
            T_new = se3_inverse(kf.pose.to(F64))
            moved = float(se3_log(torch.linalg.inv(T_old) @ T_new).norm())
            if moved > self.config.pose_tolerance or abs(np.log(c)) > self.config.pose_tolerance:
                poses[k], scales[k] = T_new, c
                self._sent.record(kf, T_new)
        if poses:
            self.mapper.update_keyframe_poses(poses, scales)
            self.pose_update_batches += 1


def _rounded(metrics: dict) -> dict:
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in metrics.items()}
