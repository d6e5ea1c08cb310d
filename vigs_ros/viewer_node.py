"""Viewer node: the graph's topics logged to rerun, so a laptop can watch a robot (:mod:`vigs_core.viz.rerun_log`).

It only listens: the graph runs the same with or without it, and RViz keeps its topics. Inputs (names are
parameters):

* ``odometry_topic`` (nav_msgs/Odometry): ``world/body`` and ``world/trajectory``, on the ``frame`` timeline
  (one step per odometry message) and the ``time`` timeline (its stamp);
* ``keyframe_topic`` (vigs_msgs/Keyframe): ``world/camera`` with the keyframe image, ``world/keyframes`` and the
  keyframe's points from its disparity (``world/keyframe_points``);
* ``keyframe_update_topics`` (vigs_msgs/KeyframePoseUpdate: BA and loop corrections): ``world/keyframes`` moved;
  loop corrections as ``status`` events;
* ``map_cloud_topic`` (sensor_msgs/PointCloud2, the mapper's Gaussian centres with RGB): ``world/map``;
* ``status_topic`` (diagnostic_msgs/DiagnosticArray): a ``status`` event whenever a node's level or message
  changes.

``rerun_target`` is where the log goes: ``spawn`` (a local viewer), a viewer's ``rerun+http://`` URL, or an
``.rrd`` file path.
"""
from __future__ import annotations

import sys
from collections import deque

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from sensor_msgs.msg import PointCloud2
from vigs_msgs.msg import Keyframe, KeyframePoseUpdate

from msg_adapters.image import to_mono8
from msg_adapters.odometry import odometry_to_pose
from msg_adapters.pointcloud import pointcloud2_to_points
from msg_adapters.vigs import msg_to_keyframe, msg_to_pose_update
from vigs_core.frontend.correspondence import PixelGrid
from vigs_core.viz.rerun_log import RerunConfig, RerunRecorder
from vigs_ros.params import ParamSpec, build_config, dataclass_specs, declare
from vigs_ros.qos import latched_qos, reliable_qos
from vigs_ros.runtime import VigsNode, process_nice, run_nodes

NODE_NAME = "viewer"
LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}

PARAMS = [
    process_nice(10),
    ParamSpec("rerun_target", "spawn", "spawn (a local viewer), a viewer's rerun+http:// URL, or an .rrd path"),
    ParamSpec("odometry_topic", "/odometry", "input nav_msgs/Odometry"),
    ParamSpec("keyframe_topic", "/vigs/keyframes", "input vigs_msgs/Keyframe"),
    ParamSpec("keyframe_update_topics", ["/vigs/keyframe_pose_updates", "/vigs/loop_pose_updates"],
              "input vigs_msgs/KeyframePoseUpdate topics (the last one's updates are logged as loop corrections)"),
    ParamSpec("map_cloud_topic", "/vigs/map_cloud", "input sensor_msgs/PointCloud2 (Gaussian centres, RGB)"),
    ParamSpec("status_topic", "/vigs/status", "input diagnostic_msgs/DiagnosticArray"),
]
PARAMS += dataclass_specs(RerunConfig, "rerun.")


class ViewerNode(VigsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.p = declare(self, PARAMS)
        self.config = build_config(RerunConfig(), self.p, "rerun.")
        self.recorder: RerunRecorder | None = None   # made on the first keyframe (it carries the intrinsics)
        self.pending_odometry: deque[tuple[int, np.ndarray]] = deque(maxlen=1000)   # until the first keyframe
        self.keyframe_poses: dict[int, np.ndarray] = {}
        self.statuses: dict[str, tuple[int, str]] = {}
        self.received = {"odometry": 0, "keyframes": 0, "updates": 0, "map_clouds": 0}
        self.create_subscription(Odometry, self.p["odometry_topic"], self.on_odometry, reliable_qos(50))
        self.create_subscription(Keyframe, self.p["keyframe_topic"], self.on_keyframe, latched_qos(20))
        updates = list(self.p["keyframe_update_topics"])
        for n, topic in enumerate(updates):
            self.create_subscription(KeyframePoseUpdate, topic,
                                     lambda msg, loop=(n == len(updates) - 1): self.on_update(msg, loop),
                                     reliable_qos(20))
        self.create_subscription(PointCloud2, self.p["map_cloud_topic"], self.on_map_cloud, latched_qos(1))
        self.create_subscription(DiagnosticArray, self.p["status_topic"], self.on_status, latched_qos(10))

    def _rejected(self, what: str, exc: Exception) -> None:
        self.get_logger().warn(f"{what} rejected: {exc}", throttle_duration_sec=5.0)

    def on_keyframe(self, msg: Keyframe) -> None:
        try:
            kf = msg_to_keyframe(msg)
            grey = to_mono8(kf.image, kf.encoding)
        except ValueError as exc:
            self._rejected("keyframe", exc)
            return
        if self.recorder is None:
            cam = kf.camera
            self.recorder = RerunRecorder(self.p["rerun_target"], cam.width, cam.height,
                                          (cam.fx, cam.fy, cam.cx, cam.cy), self.config)
            for t_ns, T in self.pending_odometry:
                self._log_odometry(t_ns, T)
            self.pending_odometry.clear()
            for name, (level, text) in self.statuses.items():   # the statuses heard before
                self.recorder.event(f"{name}: {LEVELS.get(level, level)} {text}")
        self.received["keyframes"] += 1
        self.recorder.set_frame(self.received["odometry"], kf.t_ns)
        self.recorder.camera(kf.T_wc, grey, trajectory=False)
        disp, coords = None, None
        if kf.disparity is not None and kf.disparity.shape[1] > 0:   # the grid the frontend publishes
            grid = PixelGrid(grey.shape[1], grey.shape[0], grey.shape[1] // kf.disparity.shape[1])
            if kf.disparity.shape == (grid.rows, grid.cols):
                disp, coords = kf.disparity.reshape(-1), grid.coords()
        self.recorder.keyframe(kf.id, kf.T_wc, grey, disp, coords)
        self.keyframe_poses[kf.id] = kf.T_wc

    def on_odometry(self, msg: Odometry) -> None:
        try:
            odo = odometry_to_pose(msg)
        except ValueError as exc:
            self._rejected("odometry", exc)
            return
        if self.recorder is None:   # before the first keyframe: kept (the newest 1000) until the recorder exists
            self.pending_odometry.append((odo["t_ns"], odo["T"]))
            return
        self._log_odometry(odo["t_ns"], odo["T"])

    def _log_odometry(self, t_ns: int, T: np.ndarray) -> None:
        self.recorder.set_frame(self.received["odometry"], t_ns)
        self.recorder.body(T)
        self.received["odometry"] += 1

    def on_update(self, msg: KeyframePoseUpdate, loop: bool) -> None:
        if self.recorder is None:
            return
        try:
            update = msg_to_pose_update(msg)
        except ValueError as exc:
            self._rejected("keyframe pose update", exc)
            return
        self.received["updates"] += 1
        self.recorder.move_keyframes({int(k): np.asarray(T, dtype=np.float64)
                                      for k, T in zip(update.ids, update.poses)})
        if loop:
            self.recorder.event(f"loop correction: {len(update.ids)} keyframes moved")

    def on_map_cloud(self, msg: PointCloud2) -> None:
        if self.recorder is None:
            return
        try:
            _, xyz, rgb = pointcloud2_to_points(msg)
        except ValueError as exc:
            self._rejected("map cloud", exc)
            return
        self.received["map_clouds"] += 1
        self.recorder.map_points(xyz, rgb if rgb is not None else np.full_like(xyz, 0.7))

    def on_status(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            now = (int.from_bytes(bytes(status.level), "little") if isinstance(status.level, bytes)
                   else int(status.level), str(status.message))
            if self.statuses.get(status.name) != now:
                self.statuses[status.name] = now
                if self.recorder is not None:
                    self.recorder.event(f"{status.name}: {LEVELS.get(now[0], now[0])} {now[1]}")

    def close(self) -> None:
        """Flush the recording (an .rrd file is complete after this) and say what was logged."""
        if self.recorder is not None:
            self.recorder.close()
        print(f"[{NODE_NAME}] logged " + ", ".join(f"{n} {k}" for k, n in self.received.items()), flush=True)


def main(args: list[str] | None = None) -> int:
    return run_nodes([ViewerNode], args)


if __name__ == "__main__":
    sys.exit(main())
