"""The node graph in one process on a fresh Context and an isolated domain: a simulated bag (camera + IMU)
replayed --fast through the four nodes; outputs checked against the simulator's ground truth. Plus the
nodes' input validation (wrong encodings, missing camera info, IMU disorder) reported in diagnostics."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from ros_bags import write_sim_bag
from ros_helpers import ros_context, spin_until  # noqa: F401  (ros_context is a fixture)

from msg_adapters.odometry import odometry_to_pose, path_to_trajectory
from msg_adapters.pointcloud import pointcloud2_to_points
from msg_adapters.tf import tf_message_to_transforms
from msg_adapters.vigs import msg_to_gaussian_delta, msg_to_keyframe, msg_to_preintegration
from vigs_ros.qos import latched_qos, reliable_qos
from vigs_ros.replay import BagPlayer, ReplayConfig


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    return write_sim_bag(tmp_path_factory.mktemp("sim") / "bag", duration_s=2.0)


def rotation_angle(R):
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


class Recorder:
    def __init__(self, node, topics):
        self.msgs = {t: [] for t in topics}
        for topic, (cls, qos) in topics.items():
            node.create_subscription(cls, topic, lambda m, t=topic: self.msgs[t].append(m), qos)


def test_graph_replays_simulated_bag(ros_context, sim_bag, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry, Path
    from sensor_msgs.msg import PointCloud2
    from rclpy.executors import MultiThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from std_msgs.msg import Header
    from tf2_msgs.msg import TFMessage
    from vigs_msgs.msg import GaussianDelta, Keyframe, PreintegratedImu

    from vigs_ros.frontend_node import FrontendNode
    from vigs_ros.imu_preintegration_node import ImuPreintegrationNode
    from vigs_ros.loop_detector_node import LoopDetectorNode
    from vigs_ros.mapper_node import MapperNode

    P = Parameter
    T_BS = [float(v) for v in sim_bag.T_BS.reshape(-1)]
    nodes = [
        ImuPreintegrationNode(context=ros_context, parameter_overrides=[P("odometry_before_init", value=True)]),
        FrontendNode(context=ros_context, parameter_overrides=[P("width", value=sim_bag.camera.width),
                                                                P("height", value=sim_bag.camera.height),
                                                                P("T_body_camera", value=T_BS)]),
        MapperNode(context=ros_context, parameter_overrides=[P("mapper.iterations", value=2),
                                                              P("map_path", value=str(tmp_path / "map.ply")),
                                                              P("delta_period_s", value=0.2),
                                                              P("cloud_period_s", value=0.2)]),
        LoopDetectorNode(context=ros_context),
    ]
    probe = Node("probe", context=ros_context)
    rec = Recorder(probe, {
        "/odometry": (Odometry, reliable_qos(1000)), "/path": (Path, latched_qos(1)),
        "/tf": (TFMessage, reliable_qos(1000)), "/tf_static": (TFMessage, latched_qos(1)),
        "/vigs/keyframes": (Keyframe, latched_qos(20)), "/vigs/preintegrated_imu": (PreintegratedImu, reliable_qos(100)),
        "/vigs/imu_odometry": (Odometry, reliable_qos(2000)), "/vigs/gaussian_deltas": (GaussianDelta, reliable_qos(100)),
        "/vigs/map_cloud": (PointCloud2, latched_qos(1)), "/vigs/frame_done": (Header, reliable_qos(1000)), "/vigs/status": (DiagnosticArray, reliable_qos(1000)),
    })
    executor = MultiThreadedExecutor(num_threads=4, context=ros_context)
    for n in [*nodes, probe]:
        executor.add_node(n)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    player = BagPlayer(sim_bag.path, ReplayConfig(
        fast=True, remap={"/cam0/image_raw": "/image", "/cam0/camera_info": "/camera_info", "/imu0": "/imu"},
        wait_for=["/image", "/camera_info", "/imu"], ack_timeout_s=30.0), ros_context)
    try:
        stats = player.play()
        n_frames = len(sim_bag.frame_t_ns)
        assert stats.published["/image"] == n_frames and stats.ack_timeouts == 0
        mapper = nodes[2]
        # the IMU node answers keyframe events asynchronously: wait for one preintegration per keyframe pair too
        done = lambda: (len(rec.msgs["/vigs/frame_done"]) >= n_frames and len(rec.msgs["/vigs/gaussian_deltas"]) > 0
                        and len(rec.msgs["/vigs/map_cloud"]) > 0
                        and mapper.mapper is not None and mapper.mapper.pending() == 0
                        and len(rec.msgs["/vigs/preintegrated_imu"]) >= len(rec.msgs["/vigs/keyframes"]) - 1)  # noqa: E731
        assert spin_until_wall(done, 60.0)
        from std_srvs.srv import Trigger

        saved = mapper.on_save_map(Trigger.Request(), Trigger.Response())
        assert saved.success and (tmp_path / "map.ply").is_file() and (tmp_path / "map.json").is_file()
    finally:
        player.close()
        executor.shutdown(timeout_sec=2.0)
        spinner.join(5.0)
        for n in nodes:
            n.close()
            n.destroy_node()
    # frontend: odometry per tracked frame, in REP-105 frames, rotations consistent with the ground truth
    odom = [odometry_to_pose(m) for m in rec.msgs["/odometry"]]
    # every frame tracked (the first image arrives before the first camera info: held, then processed), one
    # odometry message per frame with a causal pose (those before the monocular initialisation have none;
    # about half of this 2 s sequence)
    counters = nodes[1].status.counters
    assert counters["frames_tracked"] == n_frames and len(odom) == counters["odometry_out"]
    assert len(odom) >= n_frames // 3, counters
    assert {(o["frame_id"], o["child_frame_id"]) for o in odom} == {("odom", "base_link")}
    gt_body = {int(t): T @ np.linalg.inv(sim_bag.T_BS) for t, T in zip(sim_bag.frame_t_ns, sim_bag.T_WC)}
    first, last = odom[0], odom[-1]
    R_est = first["T"][:3, :3].T @ last["T"][:3, :3]
    R_gt = gt_body[first["t_ns"]][:3, :3].T @ gt_body[last["t_ns"]][:3, :3]
    assert rotation_angle(R_est.T @ R_gt) < np.radians(3.0), "body rotation over the run disagrees with truth"
    tf = [t for m in rec.msgs["/tf"] for t in tf_message_to_transforms(m)]
    assert {(t.parent, t.child) for t in tf} == {("map", "odom"), ("odom", "base_link")}
    static = tf_message_to_transforms(rec.msgs["/tf_static"][-1])
    assert (static[0].parent, static[0].child) == ("base_link", "camera")
    np.testing.assert_allclose(static[0].T, sim_bag.T_BS, atol=1e-6)
    # keyframes -> IMU node: one preintegration per consecutive keyframe pair, matching the noise-free truth
    keyframes = [msg_to_keyframe(m) for m in rec.msgs["/vigs/keyframes"]]
    path = path_to_trajectory(rec.msgs["/path"][-1])   # the keyframe poses (at most one path a second)
    assert 2 <= len(path) <= len(keyframes) and set(path.t_ns.tolist()) <= {k.t_ns for k in keyframes}
    assert len(keyframes) >= 2 and keyframes[0].disparity is not None
    pres = [msg_to_preintegration(m) for m in rec.msgs["/vigs/preintegrated_imu"]]
    assert [(p.from_id, p.to_id) for p in pres] == [(k.id, k2.id) for k, k2 in zip(keyframes, keyframes[1:])]
    for p in pres:
        R_gt = gt_body[p.start_ns][:3, :3].T @ gt_body[p.end_ns][:3, :3]
        assert rotation_angle(p.delta_R.T @ R_gt) < 1e-3
    assert len(rec.msgs["/vigs/imu_odometry"]) > 0
    # ... measured inside the node from the samples' DDS reception (the same clock): small and never negative
    lat = np.array(nodes[0].odometry_latency_ms)
    assert len(lat) > 0 and lat.min() >= 0.0 and np.median(lat) < 1000.0
    assert nodes[0].status.info["odometry_latency_ms"].startswith("p50 ")
    # mapper: Gaussians from the keyframes' depth, map saved at close
    delta = msg_to_gaussian_delta(rec.msgs["/vigs/gaussian_deltas"][0])
    assert len(delta.added_ids) > 0 and delta.version == 1
    assert (tmp_path / "map.ply").is_file()
    # ... and as a coloured point cloud in the map frame, in front of the first keyframe's camera
    t_cloud, points, colours = pointcloud2_to_points(rec.msgs["/vigs/map_cloud"][-1])
    assert rec.msgs["/vigs/map_cloud"][-1].header.frame_id == "map" and len(points) > 0
    assert len(points) <= len(mapper.mapper.map) and colours.min() >= 0 and colours.max() <= 1
    in_cam = (np.linalg.inv(keyframes[0].T_wc) @ np.c_[points, np.ones(len(points))].T)[2]
    assert np.median(in_cam) > 0
    names = {s.name for m in rec.msgs["/vigs/status"] for s in m.status}
    assert {"/imu_preintegration", "/frontend", "/mapper", "/loop_detector"} <= names
    assert nodes[3].status.counters["keyframes_in"] == len(keyframes)
    # a loop-closure correction (new pose T' and depth scale c per keyframe) reaches the odometry core exactly
    engine = nodes[1].engine
    G = np.eye(4)
    G[:3, :3] = gt_body[first["t_ns"]][:3, :3]  # any rigid motion of the whole map
    G[:3, 3] = [0.3, -0.2, 0.1]
    ids = sorted(engine.odometry.keyframes)
    before = {k: np.linalg.inv(engine.odometry.keyframes[k].pose.numpy()) for k in ids}
    disp_before = engine.odometry.keyframes[ids[-1]].disp.clone()
    assert engine.apply_corrections({k: G @ before[k] for k in ids}, {k: 1.25 for k in ids}) == len(ids)
    for k in ids:
        np.testing.assert_allclose(np.linalg.inv(engine.odometry.keyframes[k].pose.numpy()), G @ before[k], atol=1e-6)
    np.testing.assert_allclose(engine.odometry.keyframes[ids[-1]].disp.numpy(), disp_before.numpy() / 1.25)


def test_loop_detector_publishes_pgba_corrections(ros_context):
    """Keyframes register with the core loop closure; a PGBA correction becomes one KeyframePoseUpdate with
    the corrected pose and depth scale of every keyframe it covers."""
    import torch
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from vigs_msgs.msg import Keyframe, KeyframePoseUpdate

    from msg_adapters.types import RclpyTypes
    from msg_adapters.vigs import KeyframeData, keyframe_to_msg, msg_to_pose_update
    from vigs_core.camera import CameraModel
    from vigs_core.geometry import sim3_from_srt, so3_exp
    from vigs_core.loop import corrected_pose
    from vigs_ros.loop_detector_node import LoopDetectorNode

    node = LoopDetectorNode(context=ros_context)
    src = Node("kf_source", context=ros_context)
    pub = src.create_publisher(Keyframe, "/vigs/keyframes", latched_qos(20))
    out = []
    src.create_subscription(KeyframePoseUpdate, "/vigs/loop_pose_updates", out.append, reliable_qos(10))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(src)
    types, rng = RclpyTypes(), np.random.default_rng(0)
    camera = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)
    for k in range(3):
        T = np.eye(4)
        T[0, 3] = 0.1 * k
        pub.publish(keyframe_to_msg(types, KeyframeData(k, 10**9 + k * 10**8, T, rng.integers(0, 255, (48, 64),
                                                        dtype=np.uint8), "mono8", camera,
                                                        np.full((6, 8), 0.5, np.float32))))
    assert spin_until(executor, lambda: node.status.counters.get("keyframes_in", 0) == 3)
    C = sim3_from_srt(torch.tensor(1.1, dtype=torch.float64), so3_exp(torch.tensor([0.0, 0.0, 0.2], dtype=torch.float64)),
                      torch.tensor([0.5, 0.0, 0.0], dtype=torch.float64))
    T_before = node.views[2].T_WC.clone()
    node.publish_corrections({1: C, 2: C})
    assert spin_until(executor, lambda: len(out) == 1)
    update = msg_to_pose_update(out[0])
    assert list(update.ids) == [1, 2]
    T_expected, c = corrected_pose(C, T_before)
    np.testing.assert_allclose(update.poses[1], T_expected.numpy(), atol=1e-9)
    np.testing.assert_allclose(update.scales, [1.1, 1.1])
    assert node.closure.unit(2) == pytest.approx(1.1)
    node.close()
    for n in (node, src):
        n.destroy_node()


def spin_until_wall(predicate, timeout_s):
    import time

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not predicate():
        time.sleep(0.05)
    return bool(predicate())


def test_nodes_report_invalid_input(ros_context):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Image, Imu

    from msg_adapters.image import numpy_to_image
    from msg_adapters.imu import sample_to_imu
    from msg_adapters.types import RclpyTypes
    from vigs_ros.frontend_node import FrontendNode
    from vigs_ros.imu_preintegration_node import ImuPreintegrationNode
    from vigs_ros.qos import sensor_qos

    from rclpy.parameter import Parameter

    frontend = FrontendNode(context=ros_context, parameter_overrides=[Parameter("camera_info_timeout_s", value=0.0)])
    imu_node = ImuPreintegrationNode(context=ros_context)
    src = Node("source", context=ros_context)
    pub_img = src.create_publisher(Image, "/image", sensor_qos(10))
    pub_imu = src.create_publisher(Imu, "/imu", sensor_qos(10))
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (frontend, imu_node, src):
        executor.add_node(n)
    assert spin_until(executor, lambda: src.count_subscribers("/image") > 0 and src.count_subscribers("/imu") > 1)
    types = RclpyTypes()
    pub_img.publish(numpy_to_image(types, np.zeros((4, 4), np.uint16), "16UC1", 1, "cam"))
    pub_img.publish(numpy_to_image(types, np.zeros((4, 4), np.uint8), "mono8", 2, "cam"))
    bad = numpy_to_image(types, np.zeros((4, 4), np.uint8), "mono8", 3, "cam")
    bad.step = 2
    pub_img.publish(bad)
    for t in (10_000_000, 15_000_000, 12_000_000, 100_000_000):  # one out of order, then a gap
        pub_imu.publish(sample_to_imu(types, t, [0, 0, 0], [0, 0, 9.81]))
    c_front, c_imu = frontend.status.counters, imu_node.status.counters
    assert spin_until(executor, lambda: c_front.get("images_in", 0) == 3 and c_imu.get("imu_in", 0) == 3)
    assert c_front["warn.encoding"] == 1 and c_front["warn.image"] == 1
    assert c_front["frames_without_camera_info"] == 1
    assert "no camera info" in frontend.status.status().message
    assert c_imu["warn.imu_stream"] == 2  # out-of-order dropped, gap reported
    # a failing core on one frame is reported; the node keeps running and still acknowledges the frame
    from sensor_msgs.msg import CameraInfo
    from std_msgs.msg import Header

    from msg_adapters.camera_info import model_to_camera_info
    from vigs_core.camera import CameraModel

    acks = []
    src.create_subscription(Header, "/vigs/frame_done", acks.append, 10)
    pub_info = src.create_publisher(CameraInfo, "/camera_info", sensor_qos(10))
    assert spin_until(executor, lambda: src.count_subscribers("/camera_info") > 0)
    pub_info.publish(model_to_camera_info(types, CameraModel(32, 24, 30.0, 30.0, 15.5, 11.5), 0, "cam"))
    assert spin_until(executor, lambda: frontend.engine is not None)

    def broken(*args):
        raise RuntimeError("core bug")

    frontend.engine.track = broken
    n_acks = len(acks)
    pub_img.publish(numpy_to_image(types, np.zeros((24, 32), np.uint8), "mono8", 50_000_000, "cam"))
    assert spin_until(executor, lambda: c_front.get("warn.core_error", 0) == 1 and len(acks) > n_acks)
    for n in (frontend, imu_node, src):
        n.destroy_node()


def test_frontend_camera_yaml_and_saved_outputs(ros_context, sim_bag, tmp_path):
    """``camera_yaml`` replaces CameraInfo (bags without it, e.g. ROS 1 EuRoC bags): the engine exists at start,
    T_body_camera comes from the file's T_BS, no CameraInfo subscription; images are tracked; at close the
    trajectories and the report are written to ``output_dir``. A missing file is a clear error."""
    import json

    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import Image

    from msg_adapters.image import numpy_to_image
    from msg_adapters.types import RclpyTypes
    from vigs_core.io import CameraCalibration, read_tum, write_camera_yaml
    from vigs_core.sim.hybrid import SimConfig, SimSequence, euroc_cam0_calibration, synthetic_source
    from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion
    from vigs_core.types import ImuNoise
    from vigs_ros.frontend_node import FrontendNode
    from vigs_ros.qos import sensor_qos

    yaml_path = tmp_path / "sensor.yaml"
    write_camera_yaml(yaml_path, CameraCalibration(sim_bag.camera, sim_bag.T_BS, 20.0))
    P = Parameter
    with pytest.raises(FileNotFoundError, match="missing.yaml"):
        FrontendNode(context=ros_context, parameter_overrides=[P("camera_yaml", value=str(tmp_path / "missing.yaml"))])
    frontend = FrontendNode(context=ros_context, parameter_overrides=[
        P("camera_yaml", value=str(yaml_path)), P("sync_imu", value=False), P("output_dir", value=str(tmp_path / "out")),
        P("width", value=sim_bag.camera.width), P("height", value=sim_bag.camera.height)])
    assert frontend.engine is not None and frontend.camera == sim_bag.camera
    np.testing.assert_allclose(frontend.T_bc, sim_bag.T_BS, atol=1e-9)
    src = Node("yaml_source", context=ros_context)
    pub = src.create_publisher(Image, "/image", sensor_qos(10))
    assert src.count_subscribers("/camera_info") == 0
    executor = SingleThreadedExecutor(context=ros_context)
    for n in (frontend, src):
        executor.add_node(n)
    assert spin_until(executor, lambda: src.count_subscribers("/image") > 0)
    cal = euroc_cam0_calibration()
    motion = ProceduralMotion(0, cal.T_BS[:3, :3], ProceduralConfig(duration_s=3.0))
    seq = SimSequence(synthetic_source(motion, ImuNoise(), noise_free=True), sim_bag.camera, cal.T_BS,
                      SimConfig(duration_s=2.0, with_depth=False))
    types, n_frames = RclpyTypes(), 0
    for frame in seq.frames():
        image = frame.image if frame.image.ndim == 2 else frame.image[..., 0]
        pub.publish(numpy_to_image(types, image, "mono8", frame.t_ns, "cam0"))
        n_frames += 1
        assert spin_until(executor, lambda: frontend.engine.stream.frames_in == n_frames)
    frontend.close()
    report = json.loads((tmp_path / "out" / "frontend_report.json").read_text())
    assert report["frames_in"] == report["frames_tracked"] == report["frames"] == n_frames
    assert report["timings_s"]["tracking"] > 0   # what the plotted report reads, as in vigs run's report.json
    traj = read_tum(tmp_path / "out" / "trajectory.txt")
    assert len(traj) == report["frames_posed"] > 0
    assert set(traj.t_ns) <= set(int(t) for t in seq.frame_t_ns)
    assert (tmp_path / "out" / "keyframes.txt").is_file() and (tmp_path / "out" / "odometry.txt").is_file()
    for n in (frontend, src):
        n.destroy_node()
