"""Mapper node: keyframes and keyframe pose updates -> Gaussian map deltas; the map file on request and at
shutdown.

Computation: :class:`vigs_core.mapping.GaussianMapper` (VIGS-SLAM 3.3: expansion from each keyframe's depth,
N optimisation steps over a local window plus global keyframes, pruning; keyframe-anchored pose/scale updates,
Eq. 6-7) running on its own worker thread, so the node's callbacks never wait for mapping.

Topics (names are parameters; see params/mapper.yaml):

* in ``keyframe_topic`` (vigs_msgs/Keyframe, transient-local): image + disparity (depth = 1 / disparity where
  disparity > 0) + pose; the mapper is created on the first keyframe, with its (undistorted pinhole) intrinsics.
* in ``pose_update_topics`` (vigs_msgs/KeyframePoseUpdate): the frontend's BA updates and the loop detector's
  PGBA updates; anchored Gaussians follow their keyframes. Updates waiting for the mapper are folded into one
  batch; at most ``mapper.max_backlog`` keyframes are queued (older ones are deferred: mapped when nothing
  else waits, or at shutdown), and with ``mapper.refine_when_idle`` the mapper keeps optimising while nothing
  waits (status: ``keyframes_mapped``, ``keyframes_deferred``, ``steps_per_keyframe``, ``keyframes_cut_short``,
  ``idle_steps``).
* out ``delta_topic`` (vigs_msgs/GaussianDelta, reliable): every ``delta_period_s``, the Gaussians added,
  changed and removed since the previous delta, in activated units (scales in m, opacity in [0, 1]).
* out ``cloud_topic`` (sensor_msgs/PointCloud2, transient-local): every ``cloud_period_s`` when the map changed,
  the means of the Gaussians with opacity >= ``cloud_min_opacity``, RGB-coloured, in ``map_frame`` -- for RViz
  and for consumers that want points rather than Gaussians.
* service ``~/save_map`` (std_srvs/Trigger): writes ``map_path`` (3DGS PLY + JSON sidecar).
* out ``status_topic`` (diagnostics). At shutdown the map is saved to ``map_path`` when ``save_on_shutdown``.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import torch
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from vigs_msgs.msg import GaussianDelta, Keyframe, KeyframePoseUpdate

from msg_adapters.pointcloud import points_to_pointcloud2
from msg_adapters.types import RclpyTypes
from msg_adapters.vigs import GaussianDeltaData, gaussian_delta_to_msg, msg_to_keyframe, msg_to_pose_update
from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.mapper import GaussianMapper, MapperConfig
from vigs_core.ranges import Range
from vigs_ros.diagnostics import StatusReporter
from vigs_ros.params import ParamSpec, build_config, dataclass_specs, declare
from vigs_ros.qos import latched_qos, reliable_qos
from vigs_ros.runtime import VigsNode, process_nice, run_nodes

NODE_NAME = "mapper"

PARAMS = [
    process_nice(10),
    ParamSpec("keyframe_topic", "/vigs/keyframes", "input vigs_msgs/Keyframe"),
    ParamSpec("pose_update_topics", ["/vigs/keyframe_pose_updates", "/vigs/loop_pose_updates"],
              "input vigs_msgs/KeyframePoseUpdate topics (frontend BA, loop closure)"),
    ParamSpec("delta_topic", "/vigs/gaussian_deltas", "output vigs_msgs/GaussianDelta"),
    ParamSpec("status_topic", "/vigs/status", "output diagnostic_msgs/DiagnosticArray"),
    ParamSpec("map_frame", "map", "frame of the Gaussian means"),
    ParamSpec("map_path", "out/ros/map.ply", "where ~/save_map and shutdown write the map (PLY + .json sidecar)"),
    ParamSpec("save_on_shutdown", True, "save the map to map_path at shutdown"),
    ParamSpec("shutdown_drain_s", 20.0, "at shutdown, finish the step in hand and apply queued keyframes / pose "
                                        "updates for at most this long (s; keep it below the launcher's 30 s "
                                        "shutdown timeout)", range=Range(0)),
    ParamSpec("delta_period_s", 1.0, "period of Gaussian delta publication (s)", range=Range(0, lo_open=True)),
    ParamSpec("cloud_topic", "/vigs/map_cloud", "output sensor_msgs/PointCloud2 of the Gaussian means (RGB)"),
    ParamSpec("cloud_period_s", 2.0, "period of the map point cloud (s), sent only when the map changed; <= 0: off"),
    ParamSpec("cloud_min_opacity", 0.3, "Gaussians below this opacity are left out of the point cloud",
              range=Range(0, 1)),
    ParamSpec("device", "cpu", "torch device of the map (cpu, cuda)"),
    ParamSpec("torch_threads", 1, "torch CPU threads of this process", range=Range(1)),
    ParamSpec("status_period_s", 1.0, "period of the diagnostics status (s)", range=Range(0, lo_open=True)),
]
PARAMS += dataclass_specs(MapperConfig, "mapper.")


class MapperNode(VigsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.p = declare(self, PARAMS)
        torch.set_num_threads(int(self.p["torch_threads"]))
        self.config = build_config(MapperConfig(), self.p, "mapper.")
        self.types = RclpyTypes()
        self.status = StatusReporter(self, self.p["status_topic"], self.p["status_period_s"])
        self.mapper: GaussianMapper | None = None
        self.version = 0
        self.pub_delta = self.create_publisher(GaussianDelta, self.p["delta_topic"], reliable_qos(20))
        self.create_subscription(Keyframe, self.p["keyframe_topic"], self.on_keyframe, latched_qos(20))
        for topic in self.p["pose_update_topics"]:
            self.create_subscription(KeyframePoseUpdate, topic, self.on_pose_update, reliable_qos(20))
        self.create_service(Trigger, "~/save_map", self.on_save_map)
        self.create_timer(float(self.p["delta_period_s"]), self.publish_delta)
        self.cloud_version = 0
        if float(self.p["cloud_period_s"]) > 0:
            self.pub_cloud = self.create_publisher(PointCloud2, self.p["cloud_topic"], latched_qos(1))
            self.create_timer(float(self.p["cloud_period_s"]), self.publish_cloud)

    def on_keyframe(self, msg: Keyframe) -> None:
        kf = self.status.decode(msg_to_keyframe, msg, "keyframe", "keyframe")
        if kf is None:
            return
        if kf.disparity is None:
            self.status.warn("keyframe", f"keyframe {kf.id} has no disparity: cannot add Gaussians from it")
            return
        if kf.camera.distortion != "none":
            self.status.warn("keyframe", f"keyframe {kf.id} image is not undistorted ({kf.camera.distortion})")
            return
        if self.mapper is None:
            self.mapper = GaussianMapper(self.config, kf.camera, self.p["device"])
            self.mapper.run_async()
            self.status.info["camera"] = f"{kf.camera.width}x{kf.camera.height}"
        depth = np.where(kf.disparity > 0, 1.0 / np.maximum(kf.disparity, 1e-12), 0.0).astype(np.float32)
        self.mapper.add_keyframe(kf.id, kf.T_wc, kf.image, depth, kf.t_ns)
        self.status.count("keyframes_in")

    def on_pose_update(self, msg: KeyframePoseUpdate) -> None:
        update = self.status.decode(msg_to_pose_update, msg, "pose_update", "keyframe pose update")
        if update is None:
            return
        if self.mapper is None:
            return
        ids = [int(i) for i in update.ids]
        self.mapper.update_keyframe_poses(dict(zip(ids, update.poses)),
                                          {i: float(s) for i, s in zip(ids, update.scales)})
        self.status.count("pose_updates_in")

    def publish_delta(self) -> None:
        if self.mapper is None:
            return
        delta = self.mapper.pop_delta()
        self.status.info["gaussians"] = str(len(self.mapper.map))
        self.status.info["pending_events"] = str(self.mapper.pending())
        self.status.info["keyframes_deferred"] = str(self.mapper.deferred())
        stats = self.mapper.stats
        self.status.info["keyframes_mapped"] = str(stats.keyframes)
        self.status.info["keyframes_released"] = str(stats.released)
        self.status.info["steps_per_keyframe"] = f"{stats.steps / max(stats.keyframes, 1):.1f}"
        self.status.info["keyframes_cut_short"] = str(stats.cut_short)
        self.status.info["idle_steps"] = str(stats.idle_steps)
        if len(delta.added) == 0 and len(delta.changed) == 0 and len(delta.removed_ids) == 0:
            return
        rows = delta.added.concat(delta.changed)
        self.version += 1
        self.pub_delta.publish(gaussian_delta_to_msg(self.types, delta_to_message_data(
            rows, delta.added.ids.numpy(), delta.changed.ids.numpy(), delta.removed_ids.numpy(), self.version,
            self.get_clock().now().nanoseconds, self.p["map_frame"])))
        self.status.count("deltas_out")

    def publish_cloud(self) -> None:
        """The map as coloured points, when deltas went out since the last cloud."""
        if self.mapper is None or self.version == self.cloud_version:
            return
        self.cloud_version = self.version
        g = self.mapper.snapshot().to("cpu")
        keep = g.opacities() >= float(self.p["cloud_min_opacity"])
        self.pub_cloud.publish(points_to_pointcloud2(
            self.types, g.means[keep].numpy(), g.colors[keep].clamp(0, 1).numpy(),
            self.get_clock().now().nanoseconds, self.p["map_frame"]))
        self.status.count("clouds_out")

    def on_save_map(self, request, response):
        try:
            path = self.save_map()
            response.success, response.message = path is not None, str(path) if path else "no map yet"
            if path is not None:
                self.get_logger().info(f"map saved: {path}")
        except OSError as exc:
            response.success, response.message = False, f"cannot write {self.p['map_path']}: {exc}"
        return response

    def save_map(self) -> Path | None:
        """Write the current map to ``map_path``; None when no keyframe arrived yet."""
        if self.mapper is None:
            return None
        path = Path(self.p["map_path"])
        path.parent.mkdir(parents=True, exist_ok=True)
        self.mapper.save(path)
        return path

    def close(self) -> None:
        """Stop the worker, apply what is queued (within ``shutdown_drain_s``, or until ``hurry``: a SIGTERM, the
        launcher's escalation when the node is slow to exit; :meth:`GaussianMapper.drain`), save the map. Reports
        go to stderr: the context (and so /rosout) may already be shut down."""
        if self.mapper is None:
            return
        t0 = time.monotonic()
        deadline = t0 + float(self.p["shutdown_drain_s"])   # the worker's last step counts too
        print(f"[mapper] shutting down: {self.mapper.pending() + self.mapper.deferred()} mapping events queued",
              file=sys.stderr, flush=True)
        self.mapper.stop()
        queued = self.mapper.pending() + self.mapper.deferred()
        t_stop = time.monotonic()
        left = self.mapper.drain(max(deadline - time.monotonic(), 0.0), self.hurry)
        t_drain = time.monotonic()
        if queued:
            print(f"[mapper] at shutdown {queued - left} queued mapping events applied (keyframes inserted without "
                  f"refinement)" + (f", {left} not applied in shutdown_drain_s" if left else "")
                  + (" (SIGTERM: drain cut short)" if self.hurry.is_set() else ""), file=sys.stderr)
        if self.p["save_on_shutdown"]:
            path = self.save_map()
            print(f"[mapper] map saved: {path} ({len(self.mapper.map)} Gaussians; shutdown took "
                  f"{time.monotonic() - t0:.1f} s: worker stop {t_stop - t0:.1f}, drain {t_drain - t_stop:.1f}, "
                  f"save {time.monotonic() - t_drain:.1f})", file=sys.stderr)


def delta_to_message_data(rows: GaussianMap, added_ids, changed_ids, removed_ids, version: int, t_ns: int,
                          frame_id: str) -> GaussianDeltaData:
    """Message form of mapper rows (added then changed), in activated units."""
    g = rows.detached().to("cpu")
    return GaussianDeltaData(
        t_ns=max(int(t_ns), 0), version=version, added_ids=np.asarray(added_ids), changed_ids=np.asarray(changed_ids),
        removed_ids=np.asarray(removed_ids), means=g.means.numpy(), rotations=g.unit_quats().numpy(),
        scales=g.scales().numpy(), opacities=g.opacities().numpy(), colors=g.colors.clamp(0, 1).numpy(),
        anchor_keyframe_ids=g.anchor_ids.numpy(), frame_id=frame_id,
    )


def main(args: list[str] | None = None) -> int:
    return run_nodes([MapperNode], args)


if __name__ == "__main__":
    sys.exit(main())
