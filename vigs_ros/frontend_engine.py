"""The frontend node's computation, free of ROS: the core's streaming odometry plus what the node publishes.

:class:`FrontendEngine` wraps :class:`vigs_core.system.stream.OdometryStream`, the object ``vigs run`` drives the
same way (``add_imu`` per IMU sample, then the image: undistort + resize to the processing resolution; the
visual-inertial odometry of VIGS-SLAM 3.1-3.3 when ``config.imu.enabled`` and the node synchronises with the
IMU, else vision-only), and turns each frame's result into what the node publishes.

It reports per frame the camera pose, the keyframes created (with their inertial state), the keyframes whose
pose moved (BA, world alignment at IMU initialisation), and whether the world was re-expressed (the
gravity-aligned metric alignment: a discontinuity for REP-105's map frame). Poses: ``T_world_camera``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from collections.abc import Callable

import numpy as np
import torch

from msg_adapters.image import to_mono8
from msg_adapters.vigs import KeyframeData
from vigs_core.camera import CameraModel
from vigs_core.frontend.keyframe_changes import SentKeyframes
from vigs_core.geometry import nearest_rotation
from vigs_core.loop import apply_to_odometry, rotate_velocities
from vigs_core.system import OdometryStream, PipelineConfig
from vigs_core.system.stream import IMU_HISTORY_S
from vigs_core.types import ImuNoise
from vigs_ros.frames import invert


@dataclass
class KeyframeState:
    """Inertial state of a keyframe: velocity (3,) m/s in the world, biases (3,) rad/s and m/s^2."""

    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_acc: np.ndarray


@dataclass
class FrameOutput:
    """Result of one frame: ``T_wc`` (4, 4) or None while initialising; new keyframes with their inertial
    states; ``updated_keyframes`` {id: (T_wc, c)} of existing keyframes whose pose moved, or whose depths
    grew by a factor ``c`` (:class:`vigs_core.frontend.keyframe_changes.SentKeyframes`), by more than the tolerance
    since they were last published;
    ``realigned``: the world was re-expressed (IMU initialisation); ``inertial_initialized``: the world is
    metric and gravity-aligned; ``rotation_error``: the largest ``max|R^T R - I|`` of the core's poses before
    projection onto SO(3) (a core that loses orthonormality is reported by the node, not hidden); ``status``: the
    estimator's status after the frame (:data:`vigs_core.vio.odometry.FRAME_STATUSES`, ``vision_only`` without
    the IMU); ``failure``: the reason of a failure the estimator detected at this frame, else None."""

    t_ns: int
    T_wc: np.ndarray | None
    new_keyframes: list[KeyframeData] = field(default_factory=list)
    keyframe_states: dict[int, KeyframeState] = field(default_factory=dict)
    updated_keyframes: dict[int, tuple[np.ndarray, float]] = field(default_factory=dict)
    realigned: bool = False
    inertial_initialized: bool = False
    rotation_error: float = 0.0
    status: str = "initialising"
    failure: str | None = None


class FrontendEngine:
    """The streaming odometry and its published view (module docstring).

    Args:
        camera: the input camera (any distortion model).
        config: pipeline settings (processing size, threads, odometry, IMU fusion).
        T_bc: (4, 4) camera pose in the body (IMU) frame.
        noise: IMU noise densities; None: vision-only (the node does not synchronise with an IMU).
        imu_history_s: IMU kept behind the newest sample (s).
        pose_update_tolerance: a keyframe pose change (m, or Frobenius norm of the rotation difference) above
            which an update is reported.
    """

    def __init__(self, camera: CameraModel, config: PipelineConfig, T_bc: np.ndarray, noise: ImuNoise | None,
                 imu_history_s: float | None = IMU_HISTORY_S, pose_update_tolerance: float = 1e-6) -> None:
        self.stream = OdometryStream(camera, config, T_bc, noise, imu_history_s)
        self.camera = self.stream.camera
        self.odometry = self.stream.odometry
        self.grid_shape = (self.odometry.grid.rows, self.odometry.grid.cols)
        self.pose_update_tolerance = pose_update_tolerance
        self._published = SentKeyframes()   # T_wc and depths last published of each keyframe
        self._changes = self.odometry.keyframes.subscribe()   # keyframes changed since the last report
        self._metric = False
        self.last_corrections: dict[int, np.ndarray] = {}   # keyframe id -> Sim(3) C (4, 4) of the last correction

    @property
    def inertial(self) -> bool:
        return self.stream.inertial

    def track(self, t_ns: int, image: np.ndarray, encoding: str,
              on_pose: Callable[[np.ndarray], None] | None = None) -> FrameOutput | None:
        """Process one frame (input camera's size, mono8/rgb8/bgr8), after the IMU samples up to its stamp were
        given to ``stream.add_imu``. ``on_pose(T_wc)`` gets the tracked camera pose before the keyframe work
        (:meth:`OdometryStream.add_prepared`). None for a frame the stride leaves out."""
        if not self.stream.takes_next():
            self.stream.add_prepared(t_ns, None)
            return None
        grey = self.stream.prepare(to_mono8(image, encoding))
        out = FrameOutput(int(t_ns), None)
        notify = None if on_pose is None else (lambda T_cw: on_pose(self._rigid_inverse(T_cw.numpy(), out)))
        failures_before = len(self._failures())
        T_cw = self.stream.add_prepared(int(t_ns), grey, notify)
        if T_cw is not None:
            out.T_wc = self._rigid_inverse(T_cw.numpy(), out)
        out.status = self.status
        if len(self._failures()) > failures_before:
            out.failure = self._failures()[-1]["reason"]
        metric = self.stream.metric
        out.realigned, out.inertial_initialized = metric and not self._metric, metric
        self._metric = metric
        if not self.odometry.in_keyframe_work:   # a nested frame: the keyframe is reported once its work is done
            self.report_keyframes(out, metric)
        return out

    @property
    def status(self) -> str:
        """The estimator's status now (:attr:`FrameOutput.status`)."""
        return getattr(self.odometry, "status", "vision_only")

    def _failures(self) -> list[dict]:
        vio = getattr(self.odometry, "vio", None)
        return [] if vio is None else vio.failures

    def report_keyframes(self, out: FrameOutput, metric: bool) -> None:
        """Fill ``out.new_keyframes`` (with their states) and ``out.updated_keyframes`` from the core's
        keyframes against what was published before. Only keyframes the core changed since the last call (its
        change log, :class:`vigs_core.frontend.keyframe_changes.KeyframeTable`) are visited: a long run keeps
        thousands of keyframes, of which BA changes only the window's."""
        for kf_id in self._changes.take():
            kf = self.odometry.keyframes[kf_id]
            if kf_id not in self._published:
                T_wc = self._rigid_inverse(kf.pose.numpy(), out)
                disparity = kf.disp.numpy().astype(np.float32).reshape(self.grid_shape)
                out.new_keyframes.append(KeyframeData(kf_id, kf.t_ns, T_wc, kf.image, "mono8", self.camera,
                                                      disparity, metric=metric))
                out.keyframe_states[kf_id] = self.keyframe_state(kf_id)
            else:
                change = self._published.change(kf)
                if change is None:
                    continue
                T_old, c = change
                T_wc = self._rigid_inverse(kf.pose.numpy(), out)
                if max(_pose_distance(T_old, T_wc), abs(np.log(c))) <= self.pose_update_tolerance:
                    continue   # changes below the tolerance accumulate until they exceed it
                out.updated_keyframes[kf_id] = (T_wc, c)
            self._published.record(kf, T_wc)

    def apply_corrections(self, poses: dict[int, np.ndarray], scales: dict[int, float]) -> int:
        """Apply external keyframe corrections (loop closure: new ``T_WC`` (4, 4) and depth scale ``c`` per
        keyframe id) through :func:`vigs_core.loop.apply_to_odometry`, as the in-process loop closure does:
        the Sim(3) correction of keyframe ``k`` is ``C_k = S'_k T_WC,k^-1`` with ``S'_k = [c R', t']`` and
        inertial velocities rotate with it. Returns how many keyframes were corrected."""
        ids = [int(k) for k in poses if int(k) in self.odometry.keyframes]
        if not ids:
            return 0
        S = torch.from_numpy(np.stack([np.asarray(poses[k], dtype=np.float64) for k in ids]))
        S[:, :3, :3] *= torch.tensor([float(scales.get(k, 1.0)) for k in ids], dtype=torch.float64)[:, None, None]
        C = S @ torch.stack([self.odometry.keyframes[k].pose for k in ids]).to(torch.float64)   # kf.pose = T_WC^-1
        corrections = dict(zip(ids, C.unbind(0)))
        self.last_corrections = dict(zip(ids, C.numpy()))
        updates = apply_to_odometry(self.odometry, corrections)
        if self.inertial:
            rotate_velocities(self.odometry.vio.states, corrections)
        for k, (T_wc, _) in updates.items():   # the loop detector publishes these corrections itself
            self._published.record(self.odometry.keyframes[k], T_wc.numpy())
        return len(updates)

    def pose_before_correction(self, T_wc: np.ndarray, kf_id: int | None) -> np.ndarray | None:
        """``T_wc`` (4, 4) of a frame tracked after the last :meth:`apply_corrections`, mapped back to the world
        before it through the correction of the frame's reference keyframe ``kf_id``, ``x_old = C^-1 x_new`` with
        ``C = [c R_c, t_c]``: the pose the odometry would have given without the correction (REP-105's odom
        continues by that motion). None when that keyframe was not corrected."""
        C = self.last_corrections.get(kf_id) if kf_id is not None else None
        if C is None:
            return None
        c = float(np.cbrt(np.linalg.det(C[:3, :3])))
        R = C[:3, :3] / c
        out = np.eye(4)
        out[:3, :3] = R.T @ T_wc[:3, :3]
        out[:3, 3] = R.T @ (T_wc[:3, 3] - C[:3, 3]) / c
        return out

    def body_twist(self, t_ns: int, T_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Linear (m/s) and angular (rad/s) velocity in the body frame of the frame at ``t_ns`` with camera pose
        ``T_wc`` (4, 4), from the core's :meth:`~vigs_core.vio.odometry.VisualInertialOdometry.frame_twist`
        (``v_b = R_wb^T v_w``); None without one (not metric, across an IMU gap, vision only)."""
        twist = self.odometry.frame_twist(t_ns) if self.inertial else None
        if twist is None:
            return None
        R_wb = T_wc[:3, :3] @ self.odometry.vio.T_cb[:3, :3].numpy()
        return R_wb.T @ twist[0].numpy(), twist[1].numpy()

    def keyframe_state(self, kf_id: int) -> KeyframeState:
        """The keyframe's velocity and biases (zeros for the vision-only core)."""
        if not self.inertial or kf_id not in self.odometry.vio.states:
            return KeyframeState(np.zeros(3), np.zeros(3), np.zeros(3))
        st = self.odometry.vio.states[kf_id]
        b = self.odometry.vio.bias_of(kf_id).numpy()
        return KeyframeState(st.velocity.numpy().copy(), b[:3].copy(), b[3:].copy())

    @staticmethod
    def _rigid_inverse(T_cw: np.ndarray, out: FrameOutput) -> np.ndarray:
        """``T_wc``, with the rotation projected onto SO(3) (nearest rotation, SVD); records the deviation."""
        R = T_cw[:3, :3]
        out.rotation_error = max(out.rotation_error, float(np.abs(R.T @ R - np.eye(3)).max()))
        T = T_cw.copy()
        T[:3, :3] = nearest_rotation(R)
        return invert(T)


def _pose_distance(A: np.ndarray, B: np.ndarray) -> float:
    """max(translation difference (m), rotation difference (Frobenius norm of R_A - R_B))."""
    return max(float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(np.linalg.norm(A[:3, :3] - B[:3, :3])))
