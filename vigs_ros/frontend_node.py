"""Frontend node: images + camera info (+ preintegrated IMU) -> odometry, path, TF, keyframes, state.

Computation: :class:`vigs_ros.frontend_engine.FrontendEngine`: the same preprocessing and core odometry as
``vigs run`` (:class:`vigs_core.vio.odometry.VisualInertialOdometry`, dense monocular front end with tightly
coupled IMU fusion; vision-only :class:`vigs_core.frontend.DenseOdometry` with ``imu.enabled: false`` or
``sync_imu: false``). Settings: the :class:`vigs_core.system.PipelineConfig` fields as parameters (params/
frontend.yaml: ``width``, ``height``, ``torch_threads``, ``frame_stride``, ``odometry.*``, ``imu.*``; loop
closure runs in the loop_detector node, not here). Until the IMU initialisation succeeds the world is the first
camera frame at an arbitrary scale; then it is metric and gravity-aligned (``inertial_initialized``), the
map frame jumps once and every keyframe pose is updated. With ``odom_gravity_aligned`` (default) ``odom`` then
becomes that gravity-aligned frame (``odom -> base_link`` jumps once, after poses published as not to be
fused); without it ``odom`` stays continuous (REP-105) and keeps the first camera's orientation.

Topics (names are parameters; see params/frontend.yaml and params/ros.yaml):

* in ``image_topic`` (sensor_msgs/Image, or sensor_msgs/CompressedImage when ``image_transport`` is
  ``compressed``; sensor-data QoS). Encodings mono8, rgb8, bgr8; others are rejected with a warning.
* in ``camera_info_topic`` (sensor_msgs/CameraInfo, sensor-data QoS): intrinsics and distortion
  (plumb_bob, equidistant); frames wait for it (the newest ``image_queue_depth`` are held and processed once it
  arrives), and its absence for ``camera_info_timeout_s`` is reported as an error (frames are then dropped). With ``camera_yaml``
  (EuRoC ``sensor.yaml`` or a Kalibr camchain, :func:`vigs_core.io.read_camera_yaml`) the camera comes from that
  file instead (bags without CameraInfo, e.g. ROS 1 EuRoC bags), its ``T_BS`` replaces ``T_body_camera`` unless
  ``camera_yaml_extrinsic`` is false, and CameraInfo messages are ignored.
* in ``imu_topic`` (sensor_msgs/Imu, sensor-data QoS) when ``sync_imu``, taken by a thread of its own
  (:class:`vigs_ros.runtime.ThreadedSubscription`): frames are processed in stamp order
  once the IMU reaches their stamp (+ ``time_offset_s``), at most ``max_imu_wait_s`` of frame time late
  (:class:`vigs_ros.time_sync.FrameSynchronizer`); frames released without IMU coverage are reported.

Real time: the callbacks only queue what arrives (IMU samples, images, loop corrections); one tracking thread
gives the IMU samples to the core (``OdometryStream.add_imu``) and tracks. When it falls behind the camera,
it tracks the newest frame the IMU covers and skips the older ones (``frames_skipped``, a ``behind`` warning
on the status naming the CPU as the cause, the tracked frames in ``frames_processed.txt``: ``vigs run
--frames-from`` replays the run with the same skips and interleaving);
the estimator bridges the gap with the IMU. Odometry and ``/tf`` are published as soon as a frame's pose is
tracked, before the keyframe work (edge flows, BA) that may follow; a frame that arrives during that work is
tracked at its next yield point (:mod:`vigs_core.frontend.odometry`, live callers; counted as
``frames_tracked_during_keyframe_work``), not after all of it.
No queue grows without bound: images wait at most ``image_queue_depth`` deep for the IMU, IMU samples at most
``imu_buffer_s`` for the tracking thread.
* in ``preintegrated_topic`` (vigs_msgs/PreintegratedImu): validated and counted in diagnostics (the VIO core
  preintegrates from the raw IMU itself, so the IMU node's preintegrations serve other consumers).
* in ``pose_update_topic`` (vigs_msgs/KeyframePoseUpdate): the loop detector's corrections (new poses and
  depth scales), applied to the odometry as the in-process loop closure does
  (:meth:`FrontendEngine.apply_corrections`); the map frame jumps, ``odom`` stays continuous (REP-105).
* out ``odometry_topic`` (nav_msgs/Odometry): ``base_frame`` in ``odom_frame`` per frame (REP-105), with the
  pose covariance of :class:`~vigs_core.vio.odometry_covariance.OdometryCovariance` (``odometry_covariance.*``):
  while metric a drift model that grows with the distance travelled, the unknown covariance (do not fuse) while
  initialising or lost; the twist in ``base_frame`` (REP-105 / robot_localization) while metric: the frame's
  IMU-propagated velocity and its bias-corrected gyro sample (:meth:`FrontendEngine.body_twist`), with the model's
  constant twist covariance; zero with the unknown covariance otherwise;
  ``path_topic`` (nav_msgs/Path, transient-local): the keyframe body poses in ``map_frame`` as they are now
  (after BA, IMU initialisation and loop corrections), at most every ``path_period_s`` of wall time when they
  changed (a path of every frame, rebuilt at each correction, cost the tracking thread hundreds of milliseconds
  on long runs; the frames' poses are on ``/odometry`` and ``/tf``);
  ``/tf``: ``map_frame -> odom_frame -> base_frame``; ``/tf_static``: ``base_frame -> camera_frame``
  (``T_body_camera``).
* out ``keyframe_topic`` (vigs_msgs/Keyframe, transient-local, depth 20): image, disparity, pose, intrinsics;
  ``keyframe_event_topic`` / ``state_topic`` (vigs_msgs/NavState) for the IMU node;
  ``keyframe_update_topic`` (vigs_msgs/KeyframePoseUpdate) when BA moves earlier keyframes;
  ``frame_done_topic`` (std_msgs/Header, one per consumed frame: replay ``--fast`` paces on it);
  ``status_topic`` (diagnostics; ``estimator`` is the estimator's status, an error while it is lost after a
  detected failure, naming the failure, until it is metric again).

Outputs (``output_dir``; empty: none), kept current every ``checkpoint_period_s`` while running (the pose files
and a partial ``frontend_report.json``, replaced atomically) and written at shutdown as ``vigs run`` writes them: ``trajectory.txt`` (TUM, body
pose ``T_WB = T_WC T_body_camera^-1`` of every posed frame relative to the final keyframe poses, i.e. after
BA, IMU initialisation and loop corrections), ``odometry.txt`` (each frame's pose as first estimated,
re-expressed in the final world at IMU initialisation, like ``vigs run``'s), ``keyframes.txt`` (final
keyframe body poses) and ``frontend_report.json`` (frames received / tracked / posed / still pending,
keyframes, the IMU initialisation's stamp, the node's counters, latency from image arrival to odometry
publish p50 / p95 / max, the estimator's failures), ``frames_processed.txt`` (the tracked frames and where:
:mod:`vigs_core.io.frame_schedule`),
``frame_status.txt`` (each tracked frame's status: :mod:`vigs_core.io.frame_status`).
"""
from __future__ import annotations

import json
import math
import pathlib
import sys
import threading
import time
import traceback
from collections import deque

import numpy as np
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
from std_msgs.msg import Header
from tf2_msgs.msg import TFMessage
from vigs_msgs.msg import Keyframe, KeyframePoseUpdate, NavState, PreintegratedImu

from msg_adapters.camera_info import camera_info_to_model
from msg_adapters.common import stamp_to_ns
from msg_adapters.image import compressed_to_numpy, image_to_numpy
from msg_adapters.imu import imu_to_sample
from msg_adapters.odometry import KeyframePath, pose_to_odometry
from msg_adapters.tf import StampedTransform, tf_message
from msg_adapters.types import RclpyTypes
from msg_adapters.vigs import (
    NavStateData,
    PoseUpdateData,
    keyframe_to_msg,
    msg_to_pose_update,
    msg_to_preintegration,
    nav_state_to_msg,
    pose_update_to_msg,
)
from vigs_core.camera import CameraModel
from vigs_core.io import write_frame_schedule
from vigs_core.ranges import Range
from vigs_core.system import PipelineConfig
from vigs_core.system.pipeline import Checkpoints, frame_statuses, pose_outputs, write_pose_outputs
from vigs_core.system.stream import IMU_HISTORY_S
from vigs_core.types import ImuNoise
from vigs_core.vio.odometry import METRIC_STATUSES
from vigs_core.vio.odometry_covariance import OdometryCovariance, OdometryCovarianceConfig
from vigs_ros.diagnostics import StatusReporter
from vigs_ros.frames import Rep105Frames, body_from_camera, invert, matrix_from_param
from vigs_ros.frontend_engine import FrontendEngine
from vigs_ros.params import ParamSpec, build_config, dataclass_specs, declare
from vigs_ros.qos import latched_qos, reliable_qos, sensor_qos
from vigs_ros.runtime import VigsNode, process_nice, run_nodes
from vigs_ros.time_sync import FrameSynchronizer, StampGaps

NODE_NAME = "frontend"
IDENTITY_16 = [float(v) for v in np.eye(4).reshape(-1)]

PARAMS = [
    process_nice(-5),
    ParamSpec("image_topic", "/image", "input image topic (Image, or CompressedImage with image_transport=compressed)"),
    ParamSpec("image_transport", "raw", "raw (sensor_msgs/Image) or compressed (sensor_msgs/CompressedImage)"),
    ParamSpec("camera_info_topic", "/camera_info", "input sensor_msgs/CameraInfo topic"),
    ParamSpec("camera_yaml", "", "camera calibration file (EuRoC sensor.yaml / Kalibr camchain) used instead of "
                                 "CameraInfo (empty: use CameraInfo)"),
    ParamSpec("camera_yaml_extrinsic", True, "with camera_yaml: take T_body_camera from the file's T_BS"),
    ParamSpec("output_dir", "", "at shutdown write trajectory.txt, odometry.txt, keyframes.txt (TUM, body poses) "
                                "and frontend_report.json here (empty: nothing)"),
    ParamSpec("imu_topic", "/imu", "input sensor_msgs/Imu topic, for synchronising frames with the IMU"),
    ParamSpec("sync_imu", True, "process a frame only once the IMU has reached its stamp"),
    ParamSpec("max_imu_wait_s", 0.5, "a frame waits at most this much frame time for the IMU (s)", range=Range(0)),
    ParamSpec("preintegrated_topic", "/vigs/preintegrated_imu", "input vigs_msgs/PreintegratedImu"),
    ParamSpec("pose_update_topic", "/vigs/loop_pose_updates", "input vigs_msgs/KeyframePoseUpdate (loop closure)"),
    ParamSpec("odometry_topic", "/odometry", "output nav_msgs/Odometry (odom_frame -> base_frame)"),
    ParamSpec("path_topic", "/path", "output nav_msgs/Path of the keyframe poses in map_frame"),
    ParamSpec("keyframe_topic", "/vigs/keyframes", "output vigs_msgs/Keyframe"),
    ParamSpec("keyframe_event_topic", "/vigs/keyframe_events", "output vigs_msgs/NavState at each new keyframe"),
    ParamSpec("state_topic", "/vigs/state", "output vigs_msgs/NavState: newest keyframe after optimisation"),
    ParamSpec("keyframe_update_topic", "/vigs/keyframe_pose_updates",
              "output vigs_msgs/KeyframePoseUpdate: keyframes moved by the frontend's BA"),
    ParamSpec("frame_done_topic", "/vigs/frame_done", "output std_msgs/Header per consumed frame (replay pacing)"),
    ParamSpec("status_topic", "/vigs/status", "output diagnostic_msgs/DiagnosticArray"),
    ParamSpec("map_frame", "map", "REP-105 map frame (the estimator's world)"),
    ParamSpec("odom_frame", "odom", "REP-105 odom frame (continuous)"),
    ParamSpec("base_frame", "base_link", "body (IMU) frame"),
    ParamSpec("camera_frame", "camera", "camera optical frame"),
    ParamSpec("odom_gravity_aligned", True, "at the IMU initialisation odom becomes the gravity-aligned metric map "
                                            "frame (z up; odom -> base_link jumps once, from poses published with "
                                            "the unknown covariance); false: odom stays continuous across it and "
                                            "keeps the monocular start's camera orientation"),
    ParamSpec("publish_tf", True, "publish map->odom->base_link on /tf and base_link->camera on /tf_static"),
    ParamSpec("T_body_camera", IDENTITY_16, "camera pose in the body frame T_bc, 4x4 row-major (EuRoC: cam0 T_BS)"),
    ParamSpec("time_offset_s", 0.0, "camera-IMU time offset: t_imu = t_cam + offset (s, Kalibr timeshift_cam_imu)"),
    ParamSpec("track_during_keyframe_work", True, "track a frame that arrives during a keyframe's work at the work's "
                                                  "next yield point, instead of after it (module docstring)"),
    ParamSpec("image_queue_depth", 10, "image subscription queue depth (older frames are dropped when slower)",
              range=Range(1)),
    ParamSpec("camera_info_timeout_s", 2.0, "report an error when images arrive without camera info for this long",
              range=Range(0)),
    ParamSpec("path_period_s", 1.0, "publish the path at most this often (wall s), when keyframes changed",
              range=Range(0)),
    ParamSpec("path_max_poses", 20000, "newest keyframes in the path", range=Range(1)),
    ParamSpec("status_period_s", 1.0, "period of the diagnostics status (s)", range=Range(0, lo_open=True)),
    ParamSpec("imu_buffer_s", IMU_HISTORY_S, "IMU history kept for the VIO core (s; covers its initialisation window); "
                                     "also bounds the samples queued for the tracking thread",
                                     range=Range(0, lo_open=True)),
]
# the in-process pipeline's settings (vigs_core.system.PipelineConfig), minus what belongs to other nodes (the
# loop detector's, and the viewer node's rerun settings)
PIPELINE_PARAMS = dataclass_specs(PipelineConfig, skip=("loop", "rerun"))
PARAMS += PIPELINE_PARAMS
PARAMS += dataclass_specs(OdometryCovarianceConfig, "odometry_covariance.")   # /odometry's covariance model
PARAMS += dataclass_specs(ImuNoise)   # gyro_noise_density, ..., rate_hz (vigs_core.types.ImuNoise)


class FrontendNode(VigsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.p = declare(self, PARAMS)
        if self.p["image_transport"] not in ("raw", "compressed"):
            raise ValueError(f"image_transport must be raw or compressed, got {self.p['image_transport']!r}")
        self.T_bc = matrix_from_param(self.p["T_body_camera"], "T_body_camera")
        yaml_camera = None
        if self.p["camera_yaml"]:
            from vigs_core.io import read_camera_yaml

            calibration = read_camera_yaml(self.p["camera_yaml"])  # ValueError / FileNotFoundError name the file
            yaml_camera = calibration.camera
            if self.p["camera_yaml_extrinsic"]:
                self.T_bc = matrix_from_param(np.asarray(calibration.T_BS).reshape(-1), "camera_yaml T_BS")
        self.offset_ns = int(round(float(self.p["time_offset_s"]) * 1e9))
        self.types = RclpyTypes()
        self.status = StatusReporter(self, self.p["status_topic"], self.p["status_period_s"])
        self.config = build_config(PipelineConfig(), {s.name: self.p[s.name] for s in PIPELINE_PARAMS})
        if int(self.config.frame_stride) < 1:
            raise ValueError(f"frame_stride must be >= 1, got {self.config.frame_stride}")
        self.noise = ImuNoise(self.p["gyro_noise_density"], self.p["gyro_random_walk"], self.p["acc_noise_density"],
                              self.p["acc_random_walk"], self.p["rate_hz"])
        self.camera: CameraModel | None = None
        self.engine: FrontendEngine | None = None
        self.realigned_at_ns: int | None = None
        self.frames = Rep105Frames()
        self.covariance = OdometryCovariance(build_config(OdometryCovarianceConfig(), self.p, "odometry_covariance."))
        self.path_changed = False   # keyframes moved or were added since the path was last published
        self.path_published = -math.inf   # when (monotonic s)
        self.after_correction = False   # a loop correction was applied since the last published pose
        self.pose_metric = False        # the world was metric when the last pose was published
        self.first_image_wall: float | None = None
        self.held_for_camera: list[tuple[np.ndarray, str, object]] = []  # (image, encoding, header)
        self.sync = FrameSynchronizer(self.offset_ns, max_pending=int(self.p["image_queue_depth"]),
                                      max_wait_ns=int(float(self.p["max_imu_wait_s"]) * 1e9))
        # queues from the callbacks (executor thread) to the tracking thread (module docstring)
        self.imu_inbox: deque[tuple[int, np.ndarray, np.ndarray]] = deque(
            maxlen=max(1, int(float(self.p["imu_buffer_s"]) * float(self.p["rate_hz"]))))
        self.imu_received_ns: int | None = None   # newest IMU stamp received (not yet given to the core)
        self.corrections: deque[PoseUpdateData] = deque()
        self.sync_lock = threading.Lock()
        self.wake = threading.Event()
        self.stop = threading.Event()
        self.processed: list[tuple[int, int | None]] = []   # (stamp, yield point or None): frames_processed.txt
        self.latency_s: deque[float] = deque(maxlen=10000)   # image arrival -> odometry publish (wall s)
        self.wait_s: deque[float] = deque(maxlen=10000)      # of which image arrival -> tracking starts
        self.queue_max = {"imu_samples": 0, "frames": 0}     # deepest queues seen by the tracking thread
        self.image_gaps = StampGaps()
        # the pose outputs kept current on the tracking thread (the only one that changes the odometry)
        self.checkpoints = Checkpoints(pathlib.Path(self.p["output_dir"]) if self.p["output_dir"] else None,
                                       float(self.config.checkpoint_period_s), 0.0, "frontend_report.json")
        self.worker = threading.Thread(target=self.work, name="frontend-tracking", daemon=True)

        self.pub_odom = self.create_publisher(Odometry, self.p["odometry_topic"], reliable_qos(50))
        self.pub_path = self.create_publisher(Path, self.p["path_topic"], latched_qos(1))
        self.pub_tf = self.create_publisher(TFMessage, "/tf", reliable_qos(100))
        self.pub_tf_static = self.create_publisher(TFMessage, "/tf_static", latched_qos(1))
        self.pub_kf = self.create_publisher(Keyframe, self.p["keyframe_topic"], latched_qos(20))
        self.pub_event = self.create_publisher(NavState, self.p["keyframe_event_topic"], reliable_qos(100))
        self.pub_state = self.create_publisher(NavState, self.p["state_topic"], latched_qos(1))
        self.pub_update = self.create_publisher(KeyframePoseUpdate, self.p["keyframe_update_topic"], reliable_qos(20))
        self.pub_done = self.create_publisher(Header, self.p["frame_done_topic"], reliable_qos(100))

        depth = int(self.p["image_queue_depth"])
        if self.p["image_transport"] == "compressed":
            self.create_subscription(CompressedImage, self.p["image_topic"], self.on_image, sensor_qos(depth))
        else:
            self.create_subscription(Image, self.p["image_topic"], self.on_image, sensor_qos(depth))
        if yaml_camera is None:
            self.create_subscription(CameraInfo, self.p["camera_info_topic"], self.on_camera_info, sensor_qos(5))
        else:
            self.set_camera(yaml_camera)
        if self.p["sync_imu"]:
            self.create_threaded_subscription(Imu, self.p["imu_topic"], self.on_imu, sensor_qos(200))
        self.create_subscription(PreintegratedImu, self.p["preintegrated_topic"], self.on_preintegrated,
                                 reliable_qos(100))
        self.create_subscription(KeyframePoseUpdate, self.p["pose_update_topic"], self.on_pose_update,
                                 reliable_qos(20))
        if self.p["publish_tf"]:
            self.pub_tf_static.publish(tf_message(self.types, [StampedTransform(
                0, self.p["base_frame"], self.p["camera_frame"], self.T_bc)]))
        self.worker.start()

    # ------------------------------------------------------------------ inputs
    def on_camera_info(self, msg: CameraInfo) -> None:
        camera = self.status.decode(camera_info_to_model, msg, "camera_info", "camera info")
        if camera is None:
            return
        if self.camera is None:
            self.set_camera(camera)
        elif camera != self.camera:
            self.status.warn("camera_info", "camera info changed while running: keeping the first one")

    def set_camera(self, camera: CameraModel) -> None:
        """Create the engine for ``camera`` (from the first CameraInfo, or from ``camera_yaml``)."""
        self.camera = camera
        self.engine = FrontendEngine(camera, self.config, self.T_bc, self.noise if self.p["sync_imu"] else None,
                                     float(self.p["imu_buffer_s"]))
        self.path = KeyframePath(self.types, self.p["map_frame"], int(self.p["path_max_poses"]))
        self.path_changes = self.engine.odometry.keyframes.subscribe()   # keyframes moved since the path was built
        if self.p["track_during_keyframe_work"]:
            self.engine.odometry.interleave = self.track_ready
        self.status.info["core"] = type(self.engine.odometry).__name__
        self.status.clear_error("camera_info")
        self.status.info["camera"] = (f"{camera.width}x{camera.height} {camera.distortion} -> processing "
                                      f"{self.engine.camera.width}x{self.engine.camera.height}")
        self.get_logger().info(f"camera: {self.status.info['camera']}")
        held, self.held_for_camera = self.held_for_camera, []
        for image, encoding, header, arrived in held:  # images that arrived before the camera info
            self.accept_frame(image, encoding, header, arrived)

    def on_imu(self, msgs: list[Imu]) -> None:
        """The IMU samples taken by the subscription's own thread (every one queued): to the tracking thread's
        inbox (a deque: appends are thread-safe)."""
        for m in msgs:
            try:
                t_ns, gyro, acc = imu_to_sample(m)
            except ValueError:
                continue  # reported by the IMU node
            self.imu_inbox.append((t_ns, gyro, acc))
            self.imu_received_ns = t_ns   # the newest arrival (not the largest stamp: an outlier would stick)
        self.wake.set()

    def on_image(self, msg) -> None:
        arrived = time.monotonic()
        self.status.count("images_in")
        try:
            if isinstance(msg, CompressedImage):
                image, encoding = compressed_to_numpy(msg)
            else:
                image, encoding = image_to_numpy(msg)
        except ValueError as exc:
            self.status.warn("image", f"image rejected: {exc}")
            self.frame_done(msg.header)
            return
        lost = self.image_gaps.add(stamp_to_ns(msg.header.stamp))
        if lost:
            self.status.count("frames_lost_before_node", lost)
            self.status.warn("frames_lost", f"{lost} image(s) missing before {stamp_to_ns(msg.header.stamp)} ns: "
                                            "dropped by the subscription queue or the transport")
        if encoding not in ("mono8", "rgb8", "bgr8"):
            self.status.warn("encoding", f"image encoding {encoding!r} is not an intensity image; expected mono8, "
                                         "rgb8 or bgr8")
            self.frame_done(msg.header)
            return
        if self.engine is None:
            now = time.monotonic()
            self.first_image_wall = self.first_image_wall or now
            self.status.count("frames_without_camera_info")
            self.held_for_camera.append((image, encoding, msg.header, arrived))
            if now - self.first_image_wall >= self.p["camera_info_timeout_s"]:
                self.status.set_error("camera_info", f"images arrive but no camera info on "
                                                     f"{self.p['camera_info_topic']}")
                held, self.held_for_camera = self.held_for_camera, []  # stop holding: a replay waits for acks
                for _, _, header, _ in held:
                    self.status.count("frames_dropped_without_camera_info")
                    self.frame_done(header)
            elif len(self.held_for_camera) > int(self.p["image_queue_depth"]):
                header = self.held_for_camera.pop(0)[2]
                self.status.count("frames_dropped_without_camera_info")
                self.frame_done(header)
            return
        self.accept_frame(image, encoding, msg.header, arrived)

    def accept_frame(self, image: np.ndarray, encoding: str, header, arrived: float) -> None:
        """A decoded intensity image, once the camera is known: checked and queued for the tracking thread."""
        if image.shape[:2] != (self.camera.height, self.camera.width):
            self.status.warn("image_size", f"image is {image.shape[1]}x{image.shape[0]} but camera info says "
                                           f"{self.camera.width}x{self.camera.height}: dropped")
            self.frame_done(header)
            return
        t_cam = stamp_to_ns(header.stamp)
        with self.sync_lock:
            dropped = self.sync.push(t_cam, (image, encoding, header, arrived))
        for t_old, (*_, old_header, _) in dropped:
            self.frame_done(old_header)
            imu = self.imu_received_ns
            if t_old == t_cam:
                self.status.warn("frame_order", f"image at {t_cam} ns is not newer than the previous one: dropped")
            elif imu is not None and imu >= t_old + self.offset_ns:   # the IMU was there: tracking is behind
                self.status.count("frames_skipped")
                self.status.warn("behind", f"tracking is behind the camera (CPU): {self.sync.max_pending} frames "
                                           f"queued, dropped the oldest ({t_old} ns)")
            else:
                self.status.warn("frame_sync", f"{self.sync.max_pending} images wait for IMU data (IMU at {imu} "
                                               f"ns): dropped the oldest ({t_old} ns)")
        self.wake.set()

    # ------------------------------------------------------------------ tracking thread
    def work(self) -> None:
        """The tracking thread's loop: wait for input, then :meth:`step` (module docstring); it ends with the
        node's context (a signal shuts it down) or :meth:`stop_tracking`."""
        while not self.stop.is_set() and self.context.ok():
            self.wake.wait(0.1)
            self.wake.clear()
            try:
                self.step()
            except Exception:   # a bug outside the core's per-frame guard: report it, keep the node alive
                if not self.context.ok():   # shut down (Ctrl-C) while publishing: close() saves the outputs
                    return
                self.status.set_error("tracking_thread", "the tracking thread failed: " + traceback.format_exc(limit=1))
                self.get_logger().error("tracking thread failure:\n" + traceback.format_exc())

    def step(self) -> None:
        """Apply queued corrections, then :meth:`track_ready` (module docstring)."""
        if self.engine is None:
            return
        while self.corrections:
            self.apply_update(self.corrections.popleft())
        self.track_ready()
        self.wake.set()   # more may have become ready meanwhile

    def track_ready(self) -> None:
        """Give the queued IMU samples to the core, then track the newest frame the IMU covers and skip the older
        ready ones; also called by the core at the keyframe work's yield points (module docstring)."""
        engine = self.engine
        self.queue_max["imu_samples"] = max(self.queue_max["imu_samples"], len(self.imu_inbox))
        self.queue_max["frames"] = max(self.queue_max["frames"], len(self.sync))
        while self.imu_inbox:
            remark = engine.stream.add_imu(*self.imu_inbox.popleft())
            if remark is not None:
                self.status.warn("imu_stream", remark)
        with self.sync_lock:
            ready = self.sync.release(engine.stream.imu)
        if not ready:
            return
        *behind, (t_ns, (image, encoding, header, arrived), complete) = ready
        for t_old, (*_, old_header, _), _ in behind:
            engine.stream.skip(t_old)
            self.status.count("frames_skipped")
            self.frame_done(old_header)
        if behind:
            self.status.warn("behind", f"tracking is behind the camera (CPU): skipped {len(behind)} frame(s), "
                                       f"tracking the newest ({t_ns} ns)")
        if not complete:
            self.status.warn("imu_coverage", f"frame at {t_ns} ns processed without IMU data up to its stamp "
                                             f"(IMU at {engine.stream.imu and engine.stream.imu.latest_ns} ns)")
        self.track(t_ns, image, encoding, header, arrived)

    def track(self, t_ns: int, image, encoding: str, header, arrived: float) -> None:
        self.wait_s.append(time.monotonic() - arrived)
        try:
            out = self.engine.track(t_ns, image, encoding, lambda T_wc: self.publish_pose(t_ns, T_wc, arrived))
        except Exception as exc:  # a core failure on one frame must not take the graph down: report it
            if not self.context.ok():   # a signal shut the node down while it published: close() saves the run
                return
            self.status.warn("core_error", f"the odometry core failed on the frame at {t_ns} ns: "
                                           f"{type(exc).__name__}: {exc}")
            if self.status.counters["warn.core_error"] == 1:
                self.get_logger().error("first core failure:\n" + traceback.format_exc())
            self.frame_done(header)
            return
        if out is None:   # left out by frame_stride
            self.frame_done(header)
            return
        odometry = self.engine.odometry
        nested = odometry.in_keyframe_work   # tracked at a yield point of the keyframe work
        self.processed.append((t_ns, odometry.yield_points if nested else None))
        self.status.count("frames_tracked")
        if nested:
            self.status.count("frames_tracked_during_keyframe_work")
        else:
            self.checkpoints.step(odometry, self.T_bc, len(self.processed), None)
        if out.rotation_error > 1e-6:
            self.status.warn("core_pose", f"the odometry core returned rotations off SO(3) by {out.rotation_error:.2e}"
                                          " (projected onto SO(3) for output)")
        self.publish_frame(out)
        self.frame_done(header)

    def on_preintegrated(self, msg: PreintegratedImu) -> None:
        pre = self.status.decode(msg_to_preintegration, msg, "preintegration", "preintegrated IMU")
        if pre is None:
            return
        self.status.count("preintegrations_in")
        self.status.info["last_preintegration"] = f"keyframes {pre.from_id} -> {pre.to_id}, {pre.dt:.3f} s"

    def on_pose_update(self, msg: KeyframePoseUpdate) -> None:
        update = self.status.decode(msg_to_pose_update, msg, "pose_update", "keyframe pose update")
        if update is None:
            return
        self.corrections.append(update)   # applied by the tracking thread between frames
        self.wake.set()

    def apply_update(self, update: PoseUpdateData) -> None:
        """Apply a loop detector's correction to the odometry (tracking thread)."""
        ids = [int(i) for i in update.ids]
        n = self.engine.apply_corrections(dict(zip(ids, update.poses)), dict(zip(ids, update.scales)))
        if n:
            self.frames.mark_correction()
            self.after_correction = True
            self.path_changed = True
            self.status.count("corrections_applied")
            self.get_logger().info(f"applied loop-closure corrections to {n} keyframes")

    # ------------------------------------------------------------------ outputs
    def frame_done(self, header) -> None:
        self.pub_done.publish(Header(stamp=header.stamp, frame_id=header.frame_id))

    def publish_pose(self, t_ns: int, T_wc: np.ndarray, arrived: float) -> None:
        """Odometry and ``/tf`` of a frame, as soon as its pose is tracked (before the keyframe work)."""
        p = self.p
        before = None
        if self.after_correction:   # odom continues by the motion the odometry would have given uncorrected
            self.after_correction = False
            T_before = self.engine.pose_before_correction(T_wc, self.engine.odometry.frames[-1].ref)
            before = None if T_before is None else body_from_camera(T_before, self.T_bc)
        if self.engine.stream.metric and not self.pose_metric:   # the IMU initialisation re-expressed the world
            if p["odom_gravity_aligned"]:
                self.frames.reset_to_map()
                self.covariance.restart()
            else:
                self.frames.mark_correction()
        self.pose_metric = self.engine.stream.metric
        T_map_odom, T_odom_base = self.frames.update(body_from_camera(T_wc, self.T_bc), before)
        twist = self.engine.body_twist(t_ns, T_wc) if self.engine.status in METRIC_STATUSES else None
        v_b, w_b = twist if twist is not None else (np.zeros(3), np.zeros(3))
        try:
            odometry = pose_to_odometry(self.types, t_ns, T_odom_base, p["odom_frame"], p["base_frame"],
                                        velocity_world=T_odom_base[:3, :3] @ v_b, angular_velocity_body=w_b,
                                        pose_covariance=self.covariance.pose(T_odom_base[:3, 3], self.engine.status),
                                        twist_covariance=self.covariance.twist(twist is not None))
        except ValueError as exc:   # this runs inside the core's frame: an output it refuses must not abort that
            self.status.warn("odometry_out", f"odometry of the frame at {t_ns} ns not published: {exc}")
            return
        self.pub_odom.publish(odometry)
        self.latency_s.append(time.monotonic() - arrived)
        self.status.count("odometry_out")
        if p["publish_tf"]:
            self.pub_tf.publish(tf_message(self.types, [
                StampedTransform(t_ns, p["map_frame"], p["odom_frame"], T_map_odom),
                StampedTransform(t_ns, p["odom_frame"], p["base_frame"], T_odom_base)]))

    def report_estimator(self, out) -> None:
        """The estimator's status on /vigs/status: an error while lost (with the failure's reason), a warning
        when it is metric again."""
        self.status.info["estimator"] = out.status
        if out.failure is not None:
            self.status.count("estimator_failures")
            self.status.set_error("estimator", f"estimator failure at {out.t_ns} ns: {out.failure}; /odometry is "
                                               "not metric until the IMU initialises again")
        if out.status == "reinitialised" and "estimator" in self.status.errors:
            self.status.clear_error("estimator")
            self.status.warn("estimator_reinitialised", f"estimator re-initialised at {out.t_ns} ns: metric again")

    def publish_frame(self, out) -> None:
        """What follows a frame's keyframe work: the path, keyframes and their updates, the state."""
        p = self.p
        self.report_estimator(out)
        if out.T_wc is None:
            return
        if out.realigned:  # IMU initialisation re-expressed the world: map jumps (odom: odom_gravity_aligned)
            self.realigned_at_ns = out.t_ns
            self.get_logger().info("IMU initialised: the world is now metric and gravity-aligned")
        for kf in out.new_keyframes:
            kf.frame_id, kf.camera_frame_id = p["map_frame"], p["camera_frame"]
            self.pub_kf.publish(keyframe_to_msg(self.types, kf))
            self.pub_event.publish(nav_state_to_msg(self.types, self.nav_state(
                kf.id, kf.t_ns, kf.T_wc, out.keyframe_states[kf.id], out.inertial_initialized)))
            self.status.count("keyframes_out")
        if out.updated_keyframes:
            ids = sorted(out.updated_keyframes)
            self.pub_update.publish(pose_update_to_msg(self.types, PoseUpdateData(
                out.t_ns, np.array(ids), np.stack([out.updated_keyframes[i][0] for i in ids]),
                np.array([out.updated_keyframes[i][1] for i in ids]), p["map_frame"])))
        if out.new_keyframes or out.updated_keyframes:
            newest = max(self.engine.odometry.keyframes)
            kf = self.engine.odometry.keyframes[newest]
            self.pub_state.publish(nav_state_to_msg(self.types, self.nav_state(
                newest, kf.t_ns, invert(kf.pose.numpy()), self.engine.keyframe_state(newest),
                out.inertial_initialized)))
        self.path_changed |= bool(out.new_keyframes or out.updated_keyframes or out.realigned)
        if self.path_changed and time.monotonic() - self.path_published >= float(p["path_period_s"]):
            self.publish_path(out.t_ns)

    def publish_path(self, t_ns: int) -> None:
        """The keyframe body poses in the map frame as they are now (module docstring): the poses of the keyframes
        the odometry changed since the last publication are rebuilt, the rest kept (:class:`KeyframePath`)."""
        ids = self.path_changes.take()
        if ids:
            stamps, T_cw = self.engine.odometry.keyframe_poses(ids)
            self.path.set(ids, stamps, np.linalg.inv(T_cw.numpy()) @ np.linalg.inv(self.T_bc))
        self.pub_path.publish(self.path.message(t_ns))
        self.path_changed, self.path_published = False, time.monotonic()

    def stop_tracking(self) -> None:
        """Stop the tracking thread; it finishes the frame it is tracking."""
        self.stop.set()
        self.wake.set()
        if self.worker.is_alive() and self.worker is not threading.current_thread():
            self.worker.join(30.0)

    def destroy_node(self) -> None:
        self.stop_tracking()   # no publishing from the tracking thread after destruction
        super().destroy_node()

    def close(self) -> None:
        """Stop the tracking thread, then write the outputs of the run to ``output_dir`` (module docstring).
        Reports go to stderr: the context (and so /rosout) may already be shut down."""
        self.stop_tracking()
        if not self.p["output_dir"]:
            return
        out = pathlib.Path(self.p["output_dir"])
        latency_ms, wait_ms = np.array(self.latency_s) * 1e3, np.array(self.wait_s) * 1e3
        percentiles = (("p50", lambda x: np.percentile(x, 50)), ("p95", lambda x: np.percentile(x, 95)),
                       ("max", np.max))
        report = {"frames_in": self.status.counters.get("images_in", 0), "frames_tracked":
                  self.status.counters.get("frames_tracked", 0),
                  "frames_skipped": self.status.counters.get("frames_skipped", 0),
                  "frames_lost_before_node": self.status.counters.get("frames_lost_before_node", 0),
                  "frames_pending_at_shutdown": len(self.sync), "queue_max": dict(self.queue_max),
                  "odometry_latency_ms": {k: round(float(f(latency_ms)), 2) for k, f in percentiles}
                  if len(latency_ms) else None,
                  # the part before tracking starts: waiting for the IMU to cover the frame, or for the thread
                  "tracking_wait_ms": {k: round(float(f(wait_ms)), 2) for k, f in percentiles}
                  if len(wait_ms) else None,
                  "counters": dict(sorted(self.status.counters.items())), "info": dict(self.status.info)}
        self.checkpoints.wait()   # no checkpoint may replace the final outputs
        if self.engine is not None:
            report.update(save_trajectories(self.engine, self.T_bc, out))
        report["inertial_initialized_at_s"] = None if self.realigned_at_ns is None else self.realigned_at_ns * 1e-9
        out.mkdir(parents=True, exist_ok=True)
        write_frame_schedule(out / "frames_processed.txt", self.processed)
        (out / "frontend_report.json").write_text(json.dumps(report, indent=2))
        print(f"[frontend] wrote {out}/trajectory.txt ({report.get('frames_posed', 0)} frames), odometry.txt, "
              f"keyframes.txt, frame_status.txt, frames_processed.txt, frontend_report.json", file=sys.stderr)

    def nav_state(self, kf_id: int, t_ns: int, T_wc: np.ndarray, state, inertial: bool) -> NavStateData:
        """The body's navigation state at a keyframe (pose from the camera pose and T_body_camera)."""
        return NavStateData(t_ns, kf_id, body_from_camera(T_wc, self.T_bc), state.velocity, state.bias_gyro,
                            state.bias_acc, inertial, self.p["map_frame"])


def save_trajectories(engine: FrontendEngine, T_bc: np.ndarray, out: pathlib.Path) -> dict:
    """Write the engine's pose outputs as ``vigs run`` does (:func:`vigs_core.system.pipeline.write_pose_outputs`:
    final frame poses, causal poses, keyframes, frame statuses); returns their counts for the report, with what
    the plotted report reads as in ``vigs run``'s report.json: ``frames`` (tracked), ``timings_s`` per stage and,
    visual-inertial, ``vio`` (stage, scale history, biases, per-keyframe states)."""
    odo = engine.odometry
    out.mkdir(parents=True, exist_ok=True)
    poses = pose_outputs(odo, T_bc)
    write_pose_outputs(out, poses, frame_statuses(odo))
    counts = {"frames_posed": len(poses["trajectory"][0]), "odometry_poses": len(poses["odometry"][0]),
              "keyframes": len(odo.keyframes), "frames": len(odo.frames),
              "timings_s": {k: round(v, 3) for k, v in odo.timings.items()}}
    if hasattr(odo, "frame_status"):
        vio = odo.report()
        counts["frame_status"] = vio["frame_status"]
        counts["failures"] = odo.vio.failures
        counts["vio"] = {**vio, "keyframe_states": odo.keyframe_states()}
    return counts


def main(args: list[str] | None = None) -> int:
    return run_nodes([FrontendNode], args)


if __name__ == "__main__":
    sys.exit(main())
