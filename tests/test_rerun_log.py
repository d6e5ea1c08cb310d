"""rerun logging: `vigs run --rrd` and the viewer node record files that rerun's own reader reads back with the
documented entity paths, one camera pose per posed frame, the map and the trajectories."""
from __future__ import annotations

import collections
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_bags import SAMPLE_BAG
from ros_helpers import isolated_env, ros_context, spin_until  # noqa: F401  (ros_context is a fixture)


def read_rrd(path) -> tuple[dict[str, int], dict[str, list]]:
    """``({entity path: rows logged}, {entity path: its chunks' record batches})`` of an .rrd file, read with
    rerun's own reader."""
    import warnings

    from rerun.chunk import RrdReader

    rows, batches = collections.Counter(), collections.defaultdict(list)
    with warnings.catch_warnings():   # a recording saved by a server has no footer: read by a whole-file scan
        warnings.simplefilter("ignore")
        chunks = RrdReader(str(path)).stream().to_chunks()
    for chunk in chunks:
        rows[str(chunk.entity_path)] += chunk.num_rows
        batches[str(chunk.entity_path)].append(chunk.to_record_batch())
    return dict(rows), batches


def column_values(batches: list, column: str) -> list:
    """Every row's value of ``column`` over the record batches, in order."""
    return [v for b in batches if column in b.schema.names for v in b.column(column).to_pylist()]


def test_vigs_run_rrd_records_the_run(tmp_path):
    """A short run of the shipped sample with mapping: every posed frame's camera pose and image on the frame
    timeline, keyframes with their points, time series, the map, and at the end the final trajectory and the
    aligned ground truth."""
    params = tmp_path / "p.yaml"
    params.write_text("frontend:\n  ros__parameters:\n    loop: {enabled: false}\n"
                      "    mapping: {keyframe_delay: 0}\n    rerun: {map_period_s: 0.0}\n")
    rrd = tmp_path / "run.rrd"
    out = subprocess.run([sys.executable, "-m", "vigs_cli.main", "run", str(SAMPLE_BAG), "--out", str(tmp_path / "o"),
                          "--max-frames", "150", "--params", str(params), "--rrd", str(rrd), "--no-progress"],
                         capture_output=True, text=True, timeout=600, env=isolated_env())
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads((tmp_path / "o" / "report.json").read_text())
    rows, batches = read_rrd(rrd)
    frames = column_values(batches["/world/camera"], "frame")
    # every frame from the first one posed (the monocular initialisation) to the last
    assert frames == list(range(frames[0], report["frames"])) and frames[0] < 100
    assert rows["/world/camera/image"] == report["frames"] + 1   # and the pinhole
    assert rows["/world/keyframes"] >= report["keyframes"] - 1 and rows["/world/keyframe_points"] >= 1
    assert rows["/metrics/timing_ms/flow"] >= 100 and rows["/metrics/keyframes"] >= 2
    for path in ("/world/trajectory", "/world/trajectory_final", "/world/groundtruth", "/world/map", "/status"):
        assert rows.get(path, 0) >= 1, (path, sorted(rows))
    final = column_values(batches["/world/trajectory_final"], "LineStrips3D:strips")[-1][0]
    assert len(final) == report["frames_posed"]
    gt = np.asarray(column_values(batches["/world/groundtruth"], "LineStrips3D:strips")[-1][0])
    # the ground truth is in the estimate's world: near the final trajectory (a few cm on the sample)
    assert np.linalg.norm(gt - np.asarray(final)[-len(gt):], axis=1).mean() < 0.2
    maps = column_values(batches["/world/map"], "Points3D:positions")
    assert len(maps[-1]) == report["mapping"]["gaussians"] > 1000


def test_vigs_run_viz_streams_to_a_running_viewer(tmp_path):
    """--viz URL streams to a viewer already running elsewhere: here rerun's own server, saving what it receives."""
    import shutil
    import signal
    import socket
    import time

    with socket.socket() as s:   # a free port
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    saved = tmp_path / "received.rrd"
    # SIGINT back to its default in the server: a test run started as a background job inherits it ignored
    server = subprocess.Popen([shutil.which("rerun") or str(Path(sys.executable).parent / "rerun"), "--port",
                               str(port), "--save", str(saved)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                              text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:   # until it listens
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.2)
        out = subprocess.run([sys.executable, "-m", "vigs_cli.main", "run", str(SAMPLE_BAG), "--out",
                              str(tmp_path / "o"), "--max-frames", "60", "--viz", f"rerun+http://127.0.0.1:{port}/proxy", "--no-progress"],
                             capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.communicate(timeout=30)
        finally:
            server.kill()   # no server left behind when it did not stop
    rows, _ = read_rrd(saved)
    assert rows["/world/camera/image"] == 60 + 1 and rows.get("/world/trajectory_final") == 1


def test_without_viz_rerun_is_not_imported(tmp_path):
    """Zero cost when off: a run without --viz / --rrd never imports rerun."""
    code = ("import sys; from vigs_cli.main import main; "
            f"rc = main(['run', {str(SAMPLE_BAG)!r}, '--out', {str(tmp_path)!r}, '--max-frames', '5', "
            "'--no-progress']); print('RERUN', 'rerun' in sys.modules); sys.exit(rc)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "RERUN False" in out.stdout


def test_viewer_node_logs_the_graph_topics(ros_context, tmp_path):
    """The viewer node turns /odometry, keyframes, pose updates, the map cloud and status into the recording."""
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import PointCloud2
    from vigs_msgs.msg import Keyframe, KeyframePoseUpdate

    from msg_adapters.odometry import pose_to_odometry
    from msg_adapters.pointcloud import points_to_pointcloud2
    from msg_adapters.types import RclpyTypes
    from msg_adapters.vigs import KeyframeData, PoseUpdateData, keyframe_to_msg, pose_update_to_msg
    from vigs_core.camera import CameraModel
    from vigs_ros.qos import latched_qos, reliable_qos
    from vigs_ros.viewer_node import ViewerNode

    rrd = tmp_path / "graph.rrd"
    node = ViewerNode(context=ros_context, parameter_overrides=[Parameter("rerun_target", value=str(rrd)),
                                                                Parameter("rerun.trajectory_every", value=1)])
    src = Node("graph_source", context=ros_context)
    pubs = {"odom": src.create_publisher(Odometry, "/odometry", reliable_qos(50)),
            "kf": src.create_publisher(Keyframe, "/vigs/keyframes", latched_qos(20)),
            "loop": src.create_publisher(KeyframePoseUpdate, "/vigs/loop_pose_updates", reliable_qos(20)),
            "cloud": src.create_publisher(PointCloud2, "/vigs/map_cloud", latched_qos(1)),
            "status": src.create_publisher(DiagnosticArray, "/vigs/status", latched_qos(10))}
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    executor.add_node(src)
    assert spin_until(executor, lambda: all(p.get_subscription_count() > 0 for p in pubs.values()))
    types, rng = RclpyTypes(), np.random.default_rng(0)
    camera = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)
    for k in range(2):
        T = np.eye(4)
        T[0, 3] = 0.1 * k
        pubs["kf"].publish(keyframe_to_msg(types, KeyframeData(
            k, 10**9 + k * 10**8, T, rng.integers(0, 255, (48, 64), dtype=np.uint8), "mono8", camera,
            np.full((6, 8), 0.5, np.float32))))
    assert spin_until(executor, lambda: node.received["keyframes"] == 2)
    for n in range(5):
        T = np.eye(4)
        T[:3, 3] = [0.05 * n, 0.0, 1.0]
        pubs["odom"].publish(pose_to_odometry(types, 10**9 + n * 5 * 10**7, T, "odom", "base_link"))
    moved = np.eye(4)
    moved[:3, 3] = [0.2, 0.3, 0.0]
    pubs["loop"].publish(pose_update_to_msg(types, PoseUpdateData(2 * 10**9, np.array([1]), moved[None],
                                                                   np.array([1.0]))))
    pubs["cloud"].publish(points_to_pointcloud2(types, rng.normal(size=(300, 3)), rng.uniform(size=(300, 3)),
                                                2 * 10**9, "map"))
    pubs["status"].publish(DiagnosticArray(status=[DiagnosticStatus(level=DiagnosticStatus.WARN, name="frontend",
                                                                    message="estimator: initialising")]))
    assert spin_until(executor, lambda: node.received["odometry"] == 5 and node.received["updates"] == 1
                      and node.received["map_clouds"] == 1 and "frontend" in node.statuses)
    node.close()
    for n in (node, src):
        n.destroy_node()
    rows, batches = read_rrd(rrd)
    assert rows["/world/body"] == 5 and rows["/world/camera/image"] == 2 + 1   # two images and the pinhole
    assert rows["/world/keyframe_points"] == 2
    assert len(column_values(batches["/world/keyframe_points"], "Points3D:positions")[-1]) == 48   # 6 x 8 grid
    keyframes = column_values(batches["/world/keyframes"], "Points3D:positions")
    np.testing.assert_allclose(sorted(map(tuple, keyframes[-1])), [(0.0, 0.0, 0.0), (0.2, 0.3, 0.0)], atol=1e-6)
    assert len(column_values(batches["/world/map"], "Points3D:positions")[-1]) == 300
    strips = column_values(batches["/world/trajectory"], "LineStrips3D:strips")
    np.testing.assert_allclose(np.asarray(strips[-1][0])[:, 0], [0.0, 0.05, 0.1, 0.15, 0.2], atol=1e-9)
    events = " ".join(t for row in column_values(batches["/status"], "TextLog:text") for t in row)
    assert "loop correction: 1 keyframes moved" in events and "frontend: WARN estimator: initialising" in events


@pytest.mark.parametrize("argv", [["view", "--rrd", "x.rrd", "--connect", "u"]])
def test_vigs_view_rejects_two_targets(argv):
    out = subprocess.run([sys.executable, "-m", "vigs_cli.main", *argv], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "not allowed with" in out.stderr
