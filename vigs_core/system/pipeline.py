"""The in-process pipeline behind ``vigs run``: read frames, undistort and resize them (on a reader thread ahead
of tracking, :mod:`vigs_core.system.prefetch`), run the dense odometry on every frame, write trajectories and a
JSON report (with accuracy when ground truth exists; ``frames_per_s_excluding_io`` leaves out the time tracking
waited for the next frame, ``timings_s.input_reader_thread`` is the reader's own time).

Outputs in the output folder:

* ``trajectory.txt``: TUM, every posed frame, body (IMU) pose in the world ``T_WB = T_WC inv(T_BS)``, frames
  relative to the final keyframe poses;
* ``trajectory_cam.txt``: the same as camera poses ``T_WC``;
* ``odometry.txt``: TUM body poses as output causally while running (camera-rate odometry);
* ``keyframes.txt``: TUM body poses of the keyframes;
* ``frame_status.txt``: with the IMU, every processed frame's estimator status (:mod:`vigs_core.io.frame_status`);
* ``report.json``: counts, seconds per stage, frames/s, peak memory (``peak_rss_mb``: this process; each worker
  process its own, ``loop.process_peak_rss_mb`` and ``mapping.process_peak_rss_mb``), accuracy (Sim(3)-aligned
  ATE and recall against the ground truth sampled at the frame times).
* ``report.html``: figures (``report_figures/``) of the trajectory against the ground truth, the error over time,
  scale and biases, time per stage, keyframes and loops (:mod:`vigs_core.eval.report_html`; written last, a
  failure to plot is a warning).

A run that is not metric (vision only, or the IMU never initialised) has an arbitrary scale s, but
``T_WB = T_WC inv(T_BS)`` applies the metric camera-IMU lever arm: the body positions are off by
``R_WC (s - 1) t_CB``, a rotating error no Sim(3) alignment removes. Such runs are therefore scored on camera
poses against the ground-truth camera poses ``T_WB_gt T_BS`` (``accuracy.frame`` says which frame was scored);
evaluate their ``trajectory_cam.txt`` rather than ``trajectory.txt``.

The world frame is the first camera's at an arbitrary monocular scale (hence the Sim(3) alignment). With IMU data
and ``imu.enabled`` the odometry is visual-inertial (:mod:`vigs_core.vio`): once the IMU is initialised the world
is metric and gravity-aligned, ``velocity.txt`` holds every posed frame's body velocity (m/s) and report.json
adds ``vio`` (stage, scale history, biases, keyframe states) and ``accuracy_se3`` (no scale correction).
With ``loop.enabled`` loop closure (:class:`vigs_core.loop.LoopClosureDriver`: detection and Sim(3) PGBA in a
worker process) corrects the keyframes as it goes; report.json adds ``loop`` (candidates, loops found and
rejected, PGBA runs and seconds). With ``mapping.enabled`` the Gaussian mapper
(:class:`vigs_core.system.mapping.OnlineMapping`) maps the keyframes in a worker process: ``map.ply`` (3DGS
layout) and ``map.json`` (keyframes) are written and report.json adds ``mapping`` (Gaussians, keyframes mapped,
seconds, PSNR/SSIM on non-keyframe frames at the final poses, before and after the optional final refinement).
If that process fails, the rest is still written and ``mapping`` holds the error.

While the run goes on, the pose outputs and a partial ``report.json`` (``partial: true``) are rewritten every
``checkpoint_period_s`` and ``map.ply`` every ``map_checkpoint_period_s`` (:class:`Checkpoints`; every file is
replaced atomically), so a killed process leaves its last checkpoint. Ctrl-C (SIGINT) or SIGTERM stops the run at
the next frame boundary; everything computed so far is written (the
map without waiting for the mapper's backlog and without render quality) and ``report.json`` says
``interrupted`` (the signal's name); a second signal interrupts at once. An error during the run is written out
the same way (``report.json`` ``error``) and then raised. A frame that cannot be read or decoded is skipped with
a warning (``bad_frames``); more than ``max_bad_frames`` of them is such an error.
"""
from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from vigs_core.camera import CameraModel
from vigs_core.geometry import interpolate_poses, matrix_to_quat
from vigs_core.heap import allocator, peak_rss_mb
from vigs_core.imu.samples import ordered_samples
from vigs_core.loop import LoopClosureDriver
from vigs_core.mapping.process import MapperProcess, MappingProcessError
from vigs_core.system.config import PipelineConfig
from vigs_core.system.mapping import OnlineMapping
from vigs_core.system.prefetch import FramePrefetcher
from vigs_core.system.sources import InputSequence, open_input
from vigs_core.system.stream import OdometryStream, Preprocessor
from vigs_core.types import BadFrame, ImuNoise, ImuSamples, Trajectory
from vigs_core.vio.odometry import VisualInertialOdometry


class ImuFeed:
    """Feeds a recording's IMU samples to an :class:`OdometryStream` as they would have arrived: before a frame at
    ``t``, every sample up to and including the first one at or after ``t`` (what the frontend node's synchroniser
    waits for before it releases the frame). Disordered or repeated stamps are sanitised first (with a warning)."""

    def __init__(self, imu: ImuSamples | None, stream: OdometryStream) -> None:
        self.imu = ordered_samples(imu) if imu is not None and stream.inertial else None
        self.stream = stream
        self.next = 0

    def until(self, t_ns: int) -> None:
        imu = self.imu
        if imu is None:
            return
        end = min(int(np.searchsorted(imu.t_ns, t_ns, side="left")) + 1, len(imu))
        for k in range(self.next, end):
            self.stream.add_imu(int(imu.t_ns[k]), imu.gyro[k], imu.acc[k])
        self.next = max(self.next, end)


def poses_to_trajectory(t_ns: np.ndarray, T: np.ndarray) -> Trajectory:
    """Trajectory of poses (N, 4, 4) (frame in world) at times (N,) ns."""
    q = matrix_to_quat(torch.as_tensor(T[:, :3, :3])).numpy() if len(T) else np.zeros((0, 4))
    return Trajectory(np.asarray(t_ns, dtype=np.int64), T[:, :3, 3].copy(), q)


def groundtruth_at(gt: Trajectory, t_ns: np.ndarray) -> tuple[Trajectory, np.ndarray]:
    """Ground truth interpolated at the times inside its span; returns it and the mask of those times."""
    inside = (t_ns >= gt.t_ns[0]) & (t_ns <= gt.t_ns[-1])
    q = t_ns[inside]
    if len(q) == 0:
        return poses_to_trajectory(q, np.zeros((0, 4, 4))), inside
    R, p = interpolate_poses(torch.as_tensor(gt.t_s), torch.as_tensor(gt.matrices()[:, :3, :3]),
                             torch.as_tensor(gt.position), torch.as_tensor(q * 1e-9))
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R.numpy(), p.numpy()
    return poses_to_trajectory(q, T), inside


@dataclass
class LoadedFrames:
    """A whole input read into memory at the processing resolution (benchmarks, offline tools).

    Attributes:
        sequence: the opened input (IMU, its noise, ``T_BS``, ground truth).
        camera: the pinhole camera of ``images``.
        t_ns: (N,) stamps of the frames inside the ground truth's time span.
        images: (N, h, w) uint8 grey images, undistorted and resized as ``vigs run`` does.
        T_WB: (N, 4, 4) ground-truth body poses interpolated at ``t_ns``.
    """

    sequence: InputSequence
    camera: CameraModel
    t_ns: np.ndarray
    images: np.ndarray
    T_WB: np.ndarray


def load_frames(path: str | Path, width: int, height: int, duration_s: float | None = None) -> LoadedFrames:
    """Read the frames of ``path`` (EuRoC ASL folder or bag with ground truth) from the first one for at most
    ``duration_s`` (None: all), preprocessed to ``width`` x ``height``; frames outside the ground truth's span
    are dropped."""
    seq = open_input(path)
    if seq.groundtruth is None:
        raise ValueError(f"{path}: an input with ground truth is needed")
    pre = Preprocessor(seq.camera, width, height)
    stamps, images = [], []
    for t_ns, raw in seq.frames():
        if duration_s is not None and stamps and t_ns > stamps[0] + int(duration_s * 1e9):
            break
        if isinstance(raw, BadFrame):
            raise ValueError(f"{path}: frame at {t_ns} ns: {raw.reason}")
        stamps.append(t_ns)
        images.append(pre(raw))
    t_ns = np.array(stamps, dtype=np.int64)
    gt, inside = groundtruth_at(seq.groundtruth, t_ns)
    if not inside.any():
        raise ValueError(f"{path}: no frame lies inside the ground truth's time span")
    return LoadedFrames(seq, pre.camera, t_ns[inside], np.stack(images)[inside], gt.matrices())


def _reference(gt: Trajectory, frame_t_ns: np.ndarray, T_BX: np.ndarray | None = None) -> Trajectory:
    """What a run is scored against: the ground truth at the input frame times inside its span, as poses of frame X
    (``T_WB_gt T_BX``; the body when ``T_BX`` is None)."""
    ref, _ = groundtruth_at(gt, frame_t_ns)
    return ref if T_BX is None or not len(ref) else poses_to_trajectory(ref.t_ns, ref.matrices() @ T_BX)


def _write_html_report(out: Path, seq: InputSequence, frame_t_ns: np.ndarray, metric: bool) -> None:
    """``report.html`` beside report.json (:mod:`vigs_core.eval.report_html`): the estimate plotted against the
    reference it was scored on (body poses, camera poses when not metric). Written last, and a failure to plot is
    a warning: the run's other outputs are written already."""
    try:
        from vigs_core.eval.report_html import write_run_report

        T_BX = None if metric else seq.T_BS
        ref = None if seq.groundtruth is None else _reference(seq.groundtruth, frame_t_ns, T_BX)
        write_run_report(out, ref, "trajectory.txt" if metric else "trajectory_cam.txt")
    except Exception as err:   # noqa: BLE001 - plotting must not cost the run its outputs or its exit status
        print(f"vigs run: report.html not written: {type(err).__name__}: {err}", file=sys.stderr)


def _accuracy(gt: Trajectory, frame_t_ns: np.ndarray, t_ns: np.ndarray, T_WX: np.ndarray,
              align: str = "sim3", T_BX: np.ndarray | None = None) -> dict:
    """Sim(3)-aligned (or ``align``-aligned) ATE and recall of the posed frames against the ground truth sampled at
    every input frame time (so frames without a pose count as recall misses).

    ``T_WX`` are poses of frame X: the body when ``T_BX`` is None, else the ground-truth body poses are mapped to X
    by ``T_WB_gt T_BX`` first (``T_BX = T_BS`` scores camera poses)."""
    from vigs_core.eval import evaluate_trajectory

    ref = _reference(gt, frame_t_ns, T_BX)
    if len(ref) < 3 or len(t_ns) < 3:
        return {"error": "fewer than 3 frames inside the ground truth's time span or posed"}
    try:
        out = evaluate_trajectory(ref, poses_to_trajectory(t_ns, T_WX), align=align, thresholds=(0.05, 0.10),
                                  max_diff_s=1e-3)
    except ValueError as err:   # e.g. a platform held still: the alignment is undetermined
        return {"error": str(err)}
    result = {k: (float(v) if isinstance(v, (int, float, np.floating)) else v) for k, v in out.items()
              if isinstance(v, (int, float, np.floating, str))}
    return {**result, "frame": "body" if T_BX is None else "camera"}


class StopRequest:
    """SIGINT / SIGTERM during the run, until its outputs are written: the loop stops at the next frame boundary
    (``requested`` names the signal), the map's end-of-run drain and refinement give way, and the run writes what
    it computed; a second signal interrupts at once. Installed only when called
    from the main thread (signal handlers can be set nowhere else)."""

    def __init__(self) -> None:
        self.requested: str | None = None
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, frame) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}


def _replace_atomically(path: Path, write: Callable[[Path], Any]) -> None:
    """``write(tmp)`` then rename over ``path``: a reader (or a crash) never sees a half-written file."""
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def pose_outputs(odo, T_BS: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The odometry's current poses as written: ``{file stem: (stamps (N,) ns, poses (N, 4, 4))}`` for
    ``trajectory`` (final frame poses, body ``T_WB = T_WC inv(T_BS)``), ``trajectory_cam`` (the same, camera
    ``T_WC``), ``odometry`` (causal, body) and ``keyframes`` (body)."""
    def world_from(T_cw: torch.Tensor) -> np.ndarray:
        return np.linalg.inv(T_cw.numpy()) if len(T_cw) else np.zeros((0, 4, 4))

    t_ns, T_cw = odo.final_frame_poses()
    to, T_odo = odo.odometry_poses()
    tk, T_kf = odo.keyframe_poses()
    T_WC, T_SB = world_from(T_cw), np.linalg.inv(T_BS)
    return {"trajectory": (t_ns, T_WC @ T_SB), "trajectory_cam": (t_ns, T_WC),
            "odometry": (to, world_from(T_odo) @ T_SB), "keyframes": (tk, world_from(T_kf) @ T_SB)}


def write_pose_outputs(out: Path, poses: dict[str, tuple[np.ndarray, np.ndarray]],
                       frame_status: dict[int, str] | None) -> None:
    """Write ``poses`` (:func:`pose_outputs`) as TUM files and, with the IMU, ``frame_status`` (the odometry's
    ``{stamp_ns: status}``; None without the IMU) as ``frame_status.txt`` into ``out``, each atomically."""
    from vigs_core.io import write_frame_status, write_tum

    for name, (t, T) in poses.items():
        _replace_atomically(out / f"{name}.txt", lambda path, t=t, T=T: write_tum(path, poses_to_trajectory(t, T)))
    if frame_status is not None:
        _replace_atomically(out / "frame_status.txt", lambda path: write_frame_status(path, frame_status))


def frame_statuses(odo) -> dict[int, str] | None:
    """A copy of the odometry's per-frame statuses (:attr:`VisualInertialOdometry.frame_status`); None without
    the IMU."""
    return dict(odo.frame_status) if isinstance(odo, VisualInertialOdometry) else None


class Checkpoints:
    """Outputs kept current while the run goes on (so a killed process or a power loss leaves the run so far):
    every ``period_s`` of wall time the pose outputs and a partial report (``partial: true``, as ``report_name``),
    every ``map_period_s`` the map as well; 0 switches either off. Call :meth:`step` from the thread that
    changes the odometry: it computes the poses there, and a thread of its own writes the files (their text
    grows with the run, and tracking would otherwise wait for it). A checkpoint due while the previous one is still being written waits
    for the next period, and a write error is raised at the next :meth:`step`. Call :meth:`wait` before writing
    the final outputs, so that no checkpoint replaces them."""

    def __init__(self, out: Path | None, period_s: float, map_period_s: float,
                 report_name: str = "report.json") -> None:
        self.out, self.period_s, self.map_period_s, self.report_name = out, period_s, map_period_s, report_name
        now = time.monotonic()
        self._next, self._next_map = now + period_s, now + map_period_s
        self._writer: threading.Thread | None = None
        self._error: Exception | None = None

    def step(self, odo, T_BS: np.ndarray, frames: int, mapping) -> None:
        if self.out is None:
            return
        self._raise_error()
        now = time.monotonic()
        if self.period_s > 0 and now >= self._next and not (self._writer is not None and self._writer.is_alive()):
            self._next = now + self.period_s
            poses = pose_outputs(odo, T_BS)
            partial = {"partial": True, "frames": frames, "frames_posed": int(len(poses["trajectory"][0])),
                       "keyframes": len(odo.keyframes)}
            if isinstance(odo, VisualInertialOdometry):
                partial["vio"] = {k: v for k, v in odo.report().items() if k in ("stage", "metric", "frame_status",
                                                                                  "failures")}
            self._writer = threading.Thread(target=self._write, args=(poses, frame_statuses(odo), partial),
                                            name="checkpoint-writer", daemon=True)
            self._writer.start()
        if mapping is not None and self.map_period_s > 0 and now >= self._next_map:
            self._next_map = now + self.map_period_s
            self.out.mkdir(parents=True, exist_ok=True)
            mapping.save(self.out / "map.ply")

    def wait(self) -> None:
        """Wait for the checkpoint being written, if any."""
        if self._writer is not None:
            self._writer.join()
            self._writer = None

    def _write(self, poses: dict, frame_status: dict[int, str] | None, partial: dict) -> None:
        try:
            self.out.mkdir(parents=True, exist_ok=True)
            write_pose_outputs(self.out, poses, frame_status)
            _replace_atomically(self.out / self.report_name,
                                lambda path: path.write_text(json.dumps(partial, indent=2)))
        except Exception as exc:   # raised on the caller's thread at the next step
            self._error = exc

    def _raise_error(self) -> None:
        if self._error is not None:
            error, self._error = self._error, None
            raise error


def _finish_recording(recorder, odo, seq: InputSequence, poses: dict, report: dict, mapping) -> None:
    """The run's end in the rerun recording: final trajectory and keyframes, loop edges, the map, and the ground
    truth (camera positions, :func:`_reference`) mapped into the estimate's world by the inverse of the
    evaluation's alignment (SE(3) when metric, else Sim(3); :func:`~vigs_core.eval.align_estimate`)."""
    from vigs_core.eval import align_estimate

    t_ns, T_WC = poses["trajectory_cam"]
    _, T_WB_kf = poses["keyframes"]
    gt = None
    if seq.groundtruth is not None and len(t_ns) >= 3:
        ref = _reference(seq.groundtruth, t_ns, seq.T_BS)
        metric = report.get("vio", {}).get("metric", False)
        try:
            al = align_estimate(ref, poses_to_trajectory(t_ns, T_WC), "se3" if metric else "sim3", 1e-3).alignment
            gt = (ref.position - al.translation) @ al.rotation / al.scale
        except ValueError:   # fewer than 3 frames in the ground truth's span, or a platform held still
            gt = None
    pairs = [tuple(p) for p in report.get("loop", {}).get("accepted_pairs", [])]
    recorder.finish(T_WC, sorted(odo.keyframes), T_WB_kf @ seq.T_BS, pairs, gt)
    if mapping is not None:
        recorder.map(mapping.mapper.snapshot)
    recorder.close()


def run_pipeline(input_path: str | Path, config: PipelineConfig | None = None, out_dir: str | Path | None = None,
                 progress: bool = True, sequence: InputSequence | None = None,
                 schedule: dict[int, int | None] | None = None, viz: str | Path | None = None) -> dict:
    """Run the dense odometry over a recording and write the outputs (module docstring).

    Args:
        input_path: EuRoC ASL folder or ROS bag.
        config: pipeline settings (defaults when None).
        out_dir: output folder (created); None writes nothing.
        progress: show a progress bar on stderr.
        sequence: an already opened input (``input_path`` is then only used in the report).
        schedule: process only the frames with these stamps (ns), each at its yield point (None: between
            frames), and skip the rest, as a live run that fell behind did (the frontend node's
            ``frames_processed.txt``, :mod:`vigs_core.io.frame_schedule`): the same input with the same skips
            and interleaving gives the same trajectory.
        viz: log the run to rerun (:class:`~vigs_core.viz.rerun_log.RerunRecorder` target: ``"spawn"``, a
            viewer's URL or an ``.rrd`` path), with ``config.rerun``; None logs nothing.
    Returns:
        The report (also written as ``report.json``).
    """
    cfg = config or PipelineConfig()
    t_start = time.perf_counter()
    seq = sequence or open_input(input_path, cfg.image_topic)
    stream = OdometryStream(seq.camera, cfg, seq.T_BS, (seq.imu_noise or ImuNoise()) if seq.imu is not None else None)
    imu_feed = ImuFeed(seq.imu, stream)
    odo, cam = stream.odometry, stream.camera
    mapping = OnlineMapping(cfg.mapping, odo, cam) if cfg.mapping.enabled else None
    loop = LoopClosureDriver(cfg.loop, odo, mapper=mapping and mapping.mapper,
                             on_update=mapping and mapping.on_correction) if cfg.loop.enabled else None
    recorder = None
    if viz is not None:
        from vigs_core.viz.rerun_log import RerunRecorder

        recorder = RerunRecorder(viz, cam.width, cam.height, (cam.fx, cam.fy, cam.cx, cam.cy), cfg.rerun)
    total = seq.frame_count // cfg.frame_stride
    if cfg.max_frames is not None:
        total = min(total, cfg.max_frames)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, desc=f"vigs run {seq.name}", unit="frame", file=sys.stderr)
    t_wait = 0.0
    n = 0
    read_ahead: list[tuple[int, Any]] = []
    nested_until: dict[int, int] = {}   # yield point -> stamp of the last frame the schedule tracks there
    for t_sched, y in (schedule or {}).items():
        if y is not None:
            nested_until[y] = max(nested_until.get(y, t_sched), t_sched)
    reader = FramePrefetcher(seq.frames(), lambda k, raw: None if k % cfg.frame_stride else (
        raw if isinstance(raw, BadFrame) else stream.prepare(raw)), count=total * cfg.frame_stride)
    t_loop = time.perf_counter()
    stop = StopRequest()
    checkpoints = Checkpoints(None if out_dir is None else Path(out_dir), cfg.checkpoint_period_s,
                              cfg.map_checkpoint_period_s)
    bad_frames: list[dict] = []
    failure: Exception | None = None

    def next_frame() -> tuple[int, Any]:
        nonlocal t_wait
        if read_ahead:
            return read_ahead.pop()
        t0 = time.perf_counter()
        item = next(reader)
        t_wait += time.perf_counter() - t0
        return item

    def take(t_ns: int, image: Any) -> bool:
        """Give one frame to the odometry (after its IMU); False for a frame skipped, unreadable or strided."""
        nonlocal n
        if isinstance(image, BadFrame):   # skipped like a frame the run could not keep up with
            bad_frames.append({"t_ns": int(t_ns), "reason": image.reason})
            print(f"vigs run: frame at {t_ns} ns skipped: {image.reason}", file=sys.stderr)
            if len(bad_frames) > cfg.max_bad_frames:
                raise ValueError(f"{len(bad_frames)} frames could not be read (max_bad_frames "
                                 f"{cfg.max_bad_frames}); the last: {image.reason}")
            stream.skip(t_ns)
            return False
        if schedule is not None and t_ns not in schedule:
            stream.skip(t_ns)
            return False
        imu_feed.until(t_ns)
        stream.add_prepared(t_ns, image)
        if image is None:   # between strided frames
            return False
        if recorder is not None:
            recorder.frame(odo, t_ns, image)
        n += 1
        if bar is not None:
            bar.update(1)
        return True

    def at_yield_point() -> None:
        """The schedule's frames tracked during the keyframe work at this yield point (mapping, loop closure and
        checkpoints wait for the next frame between keyframe work)."""
        last = nested_until.get(odo.yield_points)
        while last is not None:
            try:
                t_ns, image = next_frame()
            except StopIteration:
                return
            if t_ns > last:
                read_ahead.append((t_ns, image))
                return
            take(t_ns, image)

    if nested_until:
        odo.interleave = at_yield_point
    try:
        while not stop.requested:
            try:
                t_ns, image = next_frame()
            except StopIteration:
                break
            if not take(t_ns, image):
                continue
            if mapping is not None:
                mapping.step(image)
            corrected = loop is not None and loop.step() is not None
            if recorder is not None:
                if corrected:
                    recorder.loop_corrected(odo)
                if mapping is not None:
                    recorder.map(mapping.mapper.snapshot, None if corrected else time.monotonic())
            checkpoints.step(odo, seq.T_BS, n, mapping)
            if bar is not None and n % 20 == 0:
                bar.set_postfix(kf=len(odo.keyframes), init=odo.initialized)
    except Exception as err:   # noqa: BLE001 - written out below, then raised
        failure = err
    finally:
        reader.close()
        checkpoints.wait()   # no checkpoint may replace the final outputs
    try:   # until the outputs are written a signal only asks to stop (StopRequest), so they are written
        if bar is not None:
            bar.close()
        if stop.requested or failure is not None:
            why = stop.requested or f"{type(failure).__name__}: {failure}"
            print(f"vigs run: stopped after {n} frames ({why}): writing what was computed", file=sys.stderr)
        if loop is not None:
            try:
                loop.finish()
            except RuntimeError as err:   # its worker failed: the outputs are still written, then the error raised
                print(f"vigs run: {err}", file=sys.stderr)
                failure = failure or err
        loop_s = time.perf_counter() - t_loop
        poses = pose_outputs(odo, seq.T_BS)   # scored below, then written
        (t_ns, T_WB), (_, T_WC), (to, T_WB_odo) = poses["trajectory"], poses["trajectory_cam"], poses["odometry"]
        timings = {"input_wait": t_wait, "input_reader_thread": reader.reader_seconds, **dict(odo.timings)}
        report = {
            "input": str(input_path), "sequence": seq.name,
            "resolution": [cam.width, cam.height], "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
            "frames": n, "frames_skipped": len(stream.skipped_ns), "frames_posed": int(len(t_ns)), "keyframes": len(odo.keyframes), "ba_calls": odo.ba_calls,
            "timings_s": {k: round(v, 3) for k, v in timings.items()},
            "processing_s": round(loop_s, 3), "frames_per_s": round(n / loop_s, 2) if loop_s > 0 else None,
            "frames_per_s_excluding_io": round(n / max(loop_s - t_wait, 1e-9), 2),
            "peak_rss_mb": round(peak_rss_mb(), 1), "allocator": allocator(),
            "error": None if failure is None else f"{type(failure).__name__}: {failure}",
            "bad_frames": bad_frames,
        }
        if loop is not None:
            report["loop"] = loop.report()
        cut_short = stop.requested is not None or failure is not None
        if mapping is not None:   # wait for the mapper's backlog, then render quality at the final poses
            def stopping() -> bool:   # a signal after the run loop cuts the map's drain and refinement short
                return stop.requested is not None

            try:
                if not mapping.finish(drain=not cut_short, stop=stopping) and not cut_short:
                    cut_short = True
                    print(f"vigs run: {stop.requested} while the mapper finished: its backlog is inserted "
                          "unrefined", file=sys.stderr)
                if cut_short:
                    summary = mapping.mapper.summary()
                    report["mapping"] = {"gaussians": summary.gaussians, "keyframes_mapped": summary.stats.keyframes,
                                         "interrupted": True}
                else:
                    report["mapping"] = mapping.evaluate(t_ns, T_WC, stop=stopping)
                if isinstance(mapping.mapper, MapperProcess):   # tracking waited for a mapping process that lagged
                    report["mapping"]["queue_wait_seconds"] = round(mapping.mapper.channel.waited_s, 3)
                    report["mapping"]["process_peak_rss_mb"] = round(mapping.mapper.peak_rss_mb(), 1)
            except MappingProcessError as err:   # the trajectory and the report are still written, then it is raised
                print(f"vigs run: {err}\nvigs run: no map is written", file=sys.stderr)
                report["mapping"] = {"error": str(err).splitlines()[0]}
                report["error"] = report["error"] or f"{type(err).__name__}: {report['mapping']['error']}"
                failure = failure or err
                mapping.close()
                mapping = None
        metric = isinstance(odo, VisualInertialOdometry) and odo.vio.metric
        frame_t = np.array([f.t_ns for f in odo.frames], dtype=np.int64)
        if seq.groundtruth is not None and len(t_ns):
            if metric:
                report["accuracy"] = _accuracy(seq.groundtruth, frame_t, t_ns, T_WB)
                report["accuracy_odometry"] = _accuracy(seq.groundtruth, frame_t, to, T_WB_odo)
            else:   # arbitrary scale: score camera poses (module docstring)
                T_WC_odo = T_WB_odo @ seq.T_BS
                report["accuracy"] = _accuracy(seq.groundtruth, frame_t, t_ns, T_WC, T_BX=seq.T_BS)
                report["accuracy_odometry"] = _accuracy(seq.groundtruth, frame_t, to, T_WC_odo, T_BX=seq.T_BS)
        velocities = None
        if isinstance(odo, VisualInertialOdometry):
            # stage, scale history, biases; metric runs are also scored with SE(3) alignment (no scale correction)
            report["vio"] = {**odo.report(), "keyframe_states": odo.keyframe_states()}
            tv, velocities = odo.frame_velocities()
            if metric and seq.groundtruth is not None and len(t_ns):
                report["accuracy_se3"] = _accuracy(seq.groundtruth, frame_t, t_ns, T_WB, align="se3")
        report["interrupted"] = stop.requested   # set here: also by a signal while the map was finished
        report["total_s"] = round(time.perf_counter() - t_start, 3)
        if recorder is not None:
            _finish_recording(recorder, odo, seq, poses, report, mapping)
        if out_dir is not None:
            out = Path(out_dir)
            out.mkdir(parents=True, exist_ok=True)
            write_pose_outputs(out, poses, frame_statuses(odo))
            if velocities is not None:
                np.savetxt(out / "velocity.txt", np.column_stack((tv * 1e-9, velocities.numpy())), fmt="%.9f",
                           header="timestamp[s] vx vy vz [m/s], body velocity in the world (nan before IMU init)")
            if mapping is not None:
                mapping.save(out / "map.ply")
            _replace_atomically(out / "report.json", lambda path: path.write_text(json.dumps(report, indent=2)))
            _write_html_report(out, seq, frame_t, metric)
        if mapping is not None:
            mapping.close()
        if failure is not None:
            raise failure
        return report
    finally:
        stop.restore()
