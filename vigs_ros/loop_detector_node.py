"""Loop detector node: keyframes -> keyframe pose/scale corrections after loop closure (VIGS-SLAM 3.1, 3.3).

Computation: :class:`vigs_core.loop.LoopClosure` (on its own worker thread): each new keyframe is registered in
the relative-pose graph and compared with the keyframes at least ``loop.detection.min_keyframe_gap`` older
(orientation gate, thumbnail ranking, dense-flow gate with :class:`vigs_core.frontend.DISFlowEstimator`,
two-view verification, drift plausibility); an accepted loop triggers the Sim(3) pose-graph BA, whose
per-keyframe corrections ``C_k`` give each keyframe its corrected pose ``T'_WC`` and depth scale ``c``
(:func:`vigs_core.loop.apply.corrected_poses`, all keyframes in one batch), published as one KeyframePoseUpdate.

Topics (names are parameters; see params/loop_detector.yaml; ``loop.*`` are :class:`vigs_core.loop.LoopConfig`
fields, ``flow.*`` :class:`vigs_core.frontend.DISFlowConfig` fields):

* in ``keyframe_topic`` (vigs_msgs/Keyframe, transient-local): grey image, grid disparities (depth = 1 /
  disparity), pose; the grid stride is the image width over the disparity width;
* in ``frontend_update_topic`` (vigs_msgs/KeyframePoseUpdate): keeps the stored keyframe poses and depths
  current (the depth scale ``c``: e.g. the IMU initialisation re-expresses the world in metres);
* out ``pose_update_topic`` (vigs_msgs/KeyframePoseUpdate): corrected poses ``T'_WC`` and depth scales ``c``;
* out ``status_topic`` (diagnostics: candidates, loops found / rejected, PGBA runs).
"""
from __future__ import annotations

import dataclasses
import sys

import cv2
import numpy as np
import torch
from vigs_msgs.msg import Keyframe, KeyframePoseUpdate

from msg_adapters.image import to_mono8
from msg_adapters.types import RclpyTypes
from msg_adapters.vigs import PoseUpdateData, msg_to_keyframe, msg_to_pose_update, pose_update_to_msg
from vigs_core.frontend import DISFlowConfig, DISFlowEstimator, PixelGrid
from vigs_core.heap import map_large_blocks
from vigs_core.loop import KeyframeView, LoopClosure, LoopConfig, corrections_for
from vigs_core.loop.apply import corrected_poses
from vigs_core.ranges import Range
from vigs_core.solver import Intrinsics
from vigs_ros.diagnostics import StatusReporter
from vigs_ros.params import ParamSpec, build_config, dataclass_specs, declare
from vigs_ros.qos import latched_qos, reliable_qos
from vigs_ros.runtime import VigsNode, process_nice, run_nodes

NODE_NAME = "loop_detector"
F64 = torch.float64

PARAMS = [
    process_nice(10),
    ParamSpec("keyframe_topic", "/vigs/keyframes", "input vigs_msgs/Keyframe"),
    ParamSpec("frontend_update_topic", "/vigs/keyframe_pose_updates", "input vigs_msgs/KeyframePoseUpdate (BA)"),
    ParamSpec("pose_update_topic", "/vigs/loop_pose_updates", "output vigs_msgs/KeyframePoseUpdate after PGBA"),
    ParamSpec("status_topic", "/vigs/status", "output diagnostic_msgs/DiagnosticArray"),
    ParamSpec("map_frame", "map", "frame of the keyframe poses"),
    ParamSpec("poll_period_s", 0.2, "how often finished PGBA results are collected (s)", range=Range(0, lo_open=True)),
    ParamSpec("status_period_s", 1.0, "period of the diagnostics status (s)", range=Range(0, lo_open=True)),
    ParamSpec("torch_threads", 1, "torch and OpenCV CPU threads of this process", range=Range(1)),
]
PARAMS += dataclass_specs(LoopConfig, "loop.", skip=("enabled", "process", "process_nice"))  # the node is a process
PARAMS += dataclass_specs(DISFlowConfig, "flow.")


class LoopDetectorNode(VigsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.p = declare(self, PARAMS)
        torch.set_num_threads(int(self.p["torch_threads"]))
        cv2.setNumThreads(int(self.p["torch_threads"]))
        self.config = build_config(LoopConfig(), self.p, "loop.")
        self.flow_config = build_config(DISFlowConfig(), self.p, "flow.")
        self.types = RclpyTypes()
        self.status = StatusReporter(self, self.p["status_topic"], self.p["status_period_s"])
        self.closure: LoopClosure | None = None
        self.views: dict[int, KeyframeView] = {}
        self.pub_update = self.create_publisher(KeyframePoseUpdate, self.p["pose_update_topic"], reliable_qos(20))
        self.create_subscription(Keyframe, self.p["keyframe_topic"], self.on_keyframe, latched_qos(20))
        self.create_subscription(KeyframePoseUpdate, self.p["frontend_update_topic"], self.on_pose_update,
                                 reliable_qos(20))
        self.create_timer(float(self.p["poll_period_s"]), self.poll)

    def on_keyframe(self, msg: Keyframe) -> None:
        try:
            kf = msg_to_keyframe(msg)
            grey = to_mono8(kf.image, kf.encoding)
        except ValueError as exc:
            self.status.warn("keyframe", f"keyframe rejected: {exc}")
            return
        if kf.disparity is None:
            self.status.warn("keyframe", f"keyframe {kf.id} has no disparity: not used for loop closure")
            return
        if self.views and kf.id <= max(self.views):
            return  # a repeat (transient-local replay) or out of order
        if self.closure is None:
            stride = grey.shape[1] // kf.disparity.shape[1]
            estimator = DISFlowEstimator(PixelGrid(grey.shape[1], grey.shape[0], stride), self.flow_config)
            cam = kf.camera
            self.closure = LoopClosure(self.config, estimator, Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy))
        grid = self.closure.detector.grid
        if grey.shape != (grid.height, grid.width) or kf.disparity.shape != (grid.rows, grid.cols):
            self.status.warn("keyframe", f"keyframe {kf.id}: image {grey.shape} / disparity {kf.disparity.shape} "
                                         f"differ from the first keyframe's ({grid.height}, {grid.width}) / "
                                         f"({grid.rows}, {grid.cols}): ignored")
            return
        disp = torch.as_tensor(kf.disparity.reshape(-1), dtype=F64)
        view = KeyframeView(kf.id, grey, torch.as_tensor(kf.T_wc, dtype=F64), disp, self.closure.unit(kf.id))
        self.closure.add_keyframe(view, [self.views[k] for k in sorted(self.views)], metric=kf.metric)
        # the detector keeps image and disparities (spilled when old); later scalings go into depth_scale
        self.views[kf.id] = view.bare()
        self.status.count("keyframes_in")
        self.poll()

    def on_pose_update(self, msg: KeyframePoseUpdate) -> None:
        update = self.status.decode(msg_to_pose_update, msg, "pose_update", "keyframe pose update")
        if update is None:
            return
        for kf_id, T, c in zip(update.ids, update.poses, update.scales):
            self._replace_view(int(kf_id), torch.as_tensor(T, dtype=F64), float(c))

    def poll(self) -> None:
        """Publish a finished PGBA's corrections; start PGBA when a loop is pending."""
        if self.closure is None:
            return
        result = self.closure.poll()
        if result is not None:
            self.publish_corrections(result.corrections)
        if self.closure.pending:
            self.closure.start_pgba({k: v.T_WC for k, v in self.views.items()})
        for key, value in self.closure.stats.as_dict().items():
            if isinstance(value, (int, float)):
                self.status.info[f"loop.{key}"] = str(value)

    def publish_corrections(self, corrections: dict[int, torch.Tensor]) -> None:
        """Corrected poses and depth scales of every stored keyframe; stored views follow."""
        per_kf = corrections_for(sorted(self.views), corrections)
        if not per_kf:
            return
        ids = list(per_kf)   # ascending
        T, c = corrected_poses(torch.stack([per_kf[k] for k in ids]),
                               torch.stack([self.views[k].T_WC for k in ids]))
        scales = c.tolist()
        for k, T_k, c_k in zip(ids, T.unbind(0), scales):
            self._replace_view(k, T_k, c_k)
        self.closure.record_applied(dict(zip(ids, scales)))
        self.pub_update.publish(pose_update_to_msg(self.types, PoseUpdateData(
            self.get_clock().now().nanoseconds, np.array(ids), T.numpy(), np.array(scales), self.p["map_frame"])))
        self.status.count("corrections_out")
        self.get_logger().info(f"loop closure: corrected {len(ids)} keyframes")

    def _replace_view(self, kf_id: int, T_WC: torch.Tensor, depth_scale: float) -> None:
        """A new view with pose ``T_WC`` and depths times ``depth_scale`` (views handed to the worker thread
        are snapshots: never edited in place)."""
        view = self.views.get(kf_id)
        if view is not None:
            self.views[kf_id] = dataclasses.replace(view, T_WC=T_WC, depth_scale=view.depth_scale * depth_scale)

    def close(self) -> None:
        """Stop loop closure without searching the keyframes still queued (nothing would receive the result)."""
        if self.closure is not None:
            discarded = self.closure.close(discard_queued=True)
            if discarded:
                print(f"[{NODE_NAME}] at shutdown {discarded} queued loop-closure jobs were discarded", flush=True)


def main(args: list[str] | None = None) -> int:
    # a process of its own, like vigs run's loop-closure child: the same malloc policy (vigs_core.heap); not in
    # __init__, since a composed graph shares its process with the mapper, which wants the opposite one
    map_large_blocks()
    return run_nodes([LoopDetectorNode], args)


if __name__ == "__main__":
    sys.exit(main())
