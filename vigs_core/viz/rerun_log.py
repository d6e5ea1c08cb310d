"""A run seen live or recorded with rerun (https://rerun.io): camera, trajectory, keyframes, map, loop edges and
time series, logged from the core's objects as the run goes.

Timelines: ``frame`` (index of the processed frame, from 0) and ``time`` (the frame's stamp).
Entity paths:

* ``world``: the estimator's world (``RIGHT_HAND_Z_UP``: gravity-aligned once the IMU is initialised).
* ``world/camera``: the current camera pose ``T_WC`` (Transform3D); ``world/camera/image``: its pinhole and the
  processed grey image (every ``image_every`` frames).
* ``world/body``: the body pose, where the input is a graph's ``/odometry`` (:mod:`vigs_ros.viewer_node`).
* ``world/trajectory``: the causal (odometry) positions so far (of the camera in ``vigs run``, of the body in the
  viewer node), one line strip, every ``trajectory_every`` poses; ``world/trajectory_final``: the final frame
  positions (after BA and loop corrections) when the run ends; ``world/groundtruth``: the ground truth aligned to
  them, when there is one.
* ``world/keyframes``: keyframe positions (re-logged on every new keyframe, pose update and loop correction);
  ``world/keyframe_points``: the newest keyframe's grid points from its depth, coloured by its image (they
  project onto ``world/camera/image``: the tracked keyframe depth over the current image).
* ``world/map``: the Gaussian map's centres and colours (every ``map_period_s`` and after loop corrections).
* ``world/loops``: one segment per accepted loop, between the two keyframes (at the end of the run).
* ``metrics/timing_ms/<stage>``: wall ms each odometry stage took for the frame; ``metrics/keyframes``;
  ``metrics/scale``, ``metrics/speed`` (m/s), ``metrics/bias_gyro/{x,y,z}`` (rad/s),
  ``metrics/bias_acc/{x,y,z}`` (m/s^2) with the IMU; ``status``: text events (status changes, loop corrections).

rerun is imported only when a recorder is made: a run without ``--viz`` / ``--rrd`` pays nothing.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from vigs_core.ranges import bounded

AXES = "xyz"


@dataclass
class RerunConfig:
    """Settings of :class:`RerunRecorder`.

    Args:
        image_every: the current image is logged every this many frames (1: all).
        jpeg_quality: the images are logged JPEG-compressed at this quality (a raw 376x240 grey image is 90 KB).
        trajectory_every: the causal trajectory strip (all positions so far) is re-logged every this many
            frames; each log holds the whole strip, so its cost grows with the run.
        map_period_s: the Gaussian map is logged at most this often (wall seconds), and after each loop
            correction.
        max_map_points: a map log holds at most this many Gaussians (an even subsample above it).
    """

    image_every: int = bounded(1, 1)
    jpeg_quality: int = bounded(85, 1, 100)
    trajectory_every: int = bounded(10, 1)
    map_period_s: float = bounded(5.0, 0)
    max_map_points: int = bounded(100_000, 1)


def camera_from_world(T_cw: torch.Tensor) -> np.ndarray:
    """``T_WC`` (4, 4) float64 of a world->camera pose ``T_cw``."""
    return np.linalg.inv(T_cw.detach().to(torch.float64).numpy())


def keyframe_points(image: np.ndarray, disp: np.ndarray, coords: np.ndarray, T_WC: np.ndarray,
                    intrinsics: tuple[float, float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """World points (M, 3) and grey colours (M,) uint8 of a keyframe's grid pixels with positive disparity
    (inverse depth): ``X_c = z K^-1 (u, v, 1)``, ``z = 1 / disp``, then ``X_W = T_WC X_c``."""
    fx, fy, cx, cy = intrinsics
    d = np.asarray(disp, dtype=np.float64)
    ok = d > 1e-9
    z = 1.0 / d[ok]
    u, v = coords[ok, 0], coords[ok, 1]
    X_c = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    X_w = X_c @ T_WC[:3, :3].T + T_WC[:3, 3]
    grey = image[np.clip(np.round(v).astype(int), 0, image.shape[0] - 1),
                 np.clip(np.round(u).astype(int), 0, image.shape[1] - 1)]
    return X_w, grey


class RerunRecorder:
    """Logs a run to rerun (module docstring).

    Args:
        target: ``"spawn"`` (start a local viewer and stream to it), a ``rerun+http://`` URL (stream to a running
            viewer, e.g. on a laptop watching a robot) or a file path (record to ``.rrd``).
        width, height, intrinsics: the processing camera (pixels; ``(fx, fy, cx, cy)``).
        config: what is logged how often.
        application_id: the rerun application the recording belongs to.
    """

    def __init__(self, target: str | Path, width: int, height: int, intrinsics: tuple[float, float, float, float],
                 config: RerunConfig | None = None, application_id: str = "vigs") -> None:
        import rerun as rr

        self.rr = rr
        self.config = config or RerunConfig()
        self.intrinsics = tuple(float(x) for x in intrinsics)
        self.rec = rr.RecordingStream(application_id)
        target = str(target)
        if target == "spawn":
            self.rec.spawn()
        elif target.startswith(("rerun+http://", "rerun+https://", "rerun://")):
            self.rec.connect_grpc(target)
        else:
            Path(target).parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(target)
        fx, fy, cx, cy = self.intrinsics
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log("world/camera/image", rr.Pinhole(focal_length=[fx, fy], principal_point=[cx, cy],
                                                      resolution=[width, height],
                                                      camera_xyz=rr.ViewCoordinates.RDF), static=True)
        self.frames = 0
        self._positions: list[np.ndarray] = []
        self._keyframe_positions: dict[int, np.ndarray] = {}
        self._timings: dict[str, float] = {}
        self._keyframes = 0
        self._status: str | None = None
        self._next_map = 0.0

    # ------------------------------------------------------------------ logging calls (any caller)
    def set_frame(self, index: int, t_ns: int) -> None:
        """Put what follows on the timelines at frame ``index`` and stamp ``t_ns``."""
        self.rr.set_time("frame", sequence=index, recording=self.rec)
        self.rr.set_time("time", timestamp=np.datetime64(int(t_ns), "ns"), recording=self.rec)

    def camera(self, T_WC: np.ndarray | None, image: np.ndarray | None = None, trajectory: bool = True) -> None:
        """The current camera pose (4, 4) (None: not known yet) and, when given, its image (grey or RGB, the
        processing camera's size); with ``trajectory`` its position joins ``world/trajectory``."""
        if image is not None:
            self.rec.log("world/camera/image", self.rr.Image(image).compress(jpeg_quality=self.config.jpeg_quality))
        if T_WC is None:
            return
        self.rec.log("world/camera", self.rr.Transform3D(translation=T_WC[:3, 3], mat3x3=T_WC[:3, :3]))
        if trajectory:
            self._extend_trajectory(T_WC[:3, 3])

    def body(self, T_WB: np.ndarray) -> None:
        """The body (IMU) pose (4, 4) as ``world/body`` (e.g. a graph's ``/odometry``); its position joins
        ``world/trajectory``."""
        self.rec.log("world/body", self.rr.Transform3D(translation=T_WB[:3, 3], mat3x3=T_WB[:3, :3]))
        self._extend_trajectory(T_WB[:3, 3])

    def _extend_trajectory(self, position: np.ndarray) -> None:
        self._positions.append(np.array(position, dtype=np.float64))
        if (len(self._positions) - 1) % self.config.trajectory_every == 0:
            self.rec.log("world/trajectory", self.rr.LineStrips3D([np.asarray(self._positions)],
                                                                  colors=[[230, 120, 20]]))

    def keyframe(self, kf_id: int, T_WC: np.ndarray, image: np.ndarray | None = None,
                 disp: np.ndarray | None = None, coords: np.ndarray | None = None) -> None:
        """A keyframe's pose (4, 4) (new, or moved by BA or a loop correction); with its grey ``image``, grid
        disparities ``disp`` (P,) and grid pixel ``coords`` (P, 2), its points (:func:`keyframe_points`)."""
        self.move_keyframes({kf_id: T_WC})
        if image is not None and disp is not None and coords is not None:
            points, grey = keyframe_points(image, disp, coords, T_WC, self.intrinsics)
            self.rec.log("world/keyframe_points", self.rr.Points3D(points, radii=0.01,
                                                                    colors=np.repeat(grey[:, None], 3, axis=1)))

    def move_keyframes(self, poses: dict[int, np.ndarray]) -> None:
        """New poses (4, 4) of keyframes ``{id: T_WC}`` (BA, a loop correction): ``world/keyframes`` logged once."""
        for kf_id, T_WC in poses.items():
            self._keyframe_positions[int(kf_id)] = np.array(T_WC[:3, 3], dtype=np.float64)
        self.rec.log("world/keyframes", self.rr.Points3D(list(self._keyframe_positions.values()), radii=0.02,
                                                         colors=[[40, 120, 230]]))

    def map_points(self, means: np.ndarray, colors: np.ndarray, radii: np.ndarray | None = None) -> None:
        """The map as points: centres (N, 3), RGB colours (N, 3) in [0, 1], radii (N,) (at most
        ``max_map_points``: an even subsample above)."""
        n = len(means)
        if n == 0:
            return
        keep = slice(None, None, -(-n // self.config.max_map_points))   # every k-th, k = ceil(n / max)
        rgb = (np.clip(colors[keep], 0.0, 1.0) * 255).astype(np.uint8)
        self.rec.log("world/map", self.rr.Points3D(means[keep], colors=rgb,
                                                   radii=None if radii is None else radii[keep]))

    def scalar(self, name: str, value: float) -> None:
        """One sample of the time series ``metrics/<name>``."""
        self.rec.log(f"metrics/{name}", self.rr.Scalars(float(value)))

    def event(self, text: str) -> None:
        """A text event on ``status``."""
        self.rec.log("status", self.rr.TextLog(text))

    # ------------------------------------------------------------------ from the in-process pipeline
    def frame(self, odo, t_ns: int, image: np.ndarray) -> None:
        """Log the frame just processed by ``odo`` (a :class:`~vigs_core.frontend.odometry.DenseOdometry`, or its
        visual-inertial subclass) at ``t_ns`` with its processed grey ``image``."""
        self.set_frame(self.frames, t_ns)
        pose = odo.frames[-1].odom if odo.frames else None
        self.camera(None if pose is None else camera_from_world(pose),
                    image if self.frames % self.config.image_every == 0 else None)
        for name, total in odo.timings.items():
            self.scalar(f"timing_ms/{name}", 1e3 * (total - self._timings.get(name, 0.0)))
            self._timings[name] = total
        if len(odo.keyframes) != self._keyframes:
            self._keyframes = len(odo.keyframes)
            self.scalar("keyframes", self._keyframes)
            self.keyframes(odo)
        self._inertial(odo, t_ns)
        self.frames += 1

    def keyframes(self, odo) -> None:
        """Log every keyframe's position and the newest keyframe's grid points."""
        newest = max(odo.keyframes, default=None)
        for k, kf in odo.keyframes.items():
            if k != newest:
                self._keyframe_positions[k] = camera_from_world(kf.pose)[:3, 3]
        if newest is not None:
            kf = odo.keyframes[newest]
            self.keyframe(newest, camera_from_world(kf.pose), kf.image, kf.disp.detach().to(torch.float64).numpy(),
                          odo.coords.numpy())

    def _inertial(self, odo, t_ns: int) -> None:
        vio = getattr(odo, "vio", None)
        if vio is None:
            return
        status = odo.status
        if status != self._status:
            self.event(f"status: {status} (stage {vio.stage.value})")
            self._status = status
        if not vio.metric or not vio.states:
            return
        if vio.alignment is not None:
            self.scalar("scale", vio.alignment.scale)
        bias = vio.bias_of(max(vio.states)).detach().to(torch.float64).numpy()
        for i, axis in enumerate(AXES):
            self.scalar(f"bias_gyro/{axis}", bias[i])
            self.scalar(f"bias_acc/{axis}", bias[3 + i])
        twist = odo.frame_twist(t_ns)
        if twist is not None:
            self.scalar("speed", twist[0].norm())

    def map(self, snapshot, now_s: float | None = None) -> None:
        """Log the Gaussian map that ``snapshot()`` returns (a :class:`~vigs_core.mapping.gaussians.GaussianMap`,
        called only when a log is due): at most every ``map_period_s`` of ``now_s`` (monotonic seconds), or at
        once when ``now_s`` is None (e.g. after a loop correction)."""
        if now_s is not None and now_s < self._next_map:
            return
        if now_s is not None:
            self._next_map = now_s + self.config.map_period_s
        g = snapshot()
        self.map_points(g.means.detach().double().cpu().numpy(), g.colors.detach().double().cpu().numpy(),
                        g.log_scales.detach().double().exp().mean(dim=1).cpu().numpy())

    def loop_corrected(self, odo) -> None:
        """A loop correction moved the keyframes: log the event and their new positions."""
        self.event("loop correction applied")
        self.keyframes(odo)

    def finish(self, T_WC_final: np.ndarray, keyframe_ids: list[int], T_WC_keyframes: np.ndarray,
               loop_pairs: list[tuple[int, int]], groundtruth: np.ndarray | None = None) -> None:
        """Log the run's end: final frame positions (from ``T_WC_final`` (N, 4, 4)), the keyframes' final
        positions (``keyframe_ids`` and their ``T_WC_keyframes`` (K, 4, 4)), a segment per loop (a pair of keyframe
        ids) and the ground-truth positions (M, 3) already aligned to the estimate's world."""
        rr = self.rr
        if len(T_WC_final):
            self.rec.log("world/trajectory_final", rr.LineStrips3D([T_WC_final[:, :3, 3]], colors=[[30, 170, 60]]))
        if len(T_WC_keyframes):
            self.rec.log("world/keyframes", rr.Points3D(T_WC_keyframes[:, :3, 3], radii=0.02,
                                                        colors=[[40, 120, 230]]))
        row = {int(k): n for n, k in enumerate(keyframe_ids)}
        segments = [T_WC_keyframes[[row[a], row[b]], :3, 3] for a, b in loop_pairs if a in row and b in row]
        if segments:
            self.rec.log("world/loops", rr.LineStrips3D(segments, colors=[[220, 30, 200]]))
        if groundtruth is not None and len(groundtruth):
            self.rec.log("world/groundtruth", rr.LineStrips3D([groundtruth], colors=[[120, 120, 120]]))

    def close(self) -> None:
        """Flush and end the recording (the file is complete, or the viewer has everything)."""
        self.rec.flush()
        self.rec.disconnect()
