"""Bag replay: MCAP, sqlite3 and ROS 1 bags written here are published (with /clock and remapping) and
received by a subscriber byte-for-byte; --fast paces on acknowledgements; the CLI reports bad input."""
from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest
from ros_bags import rosbags_types, write_ros2_bag
from ros_helpers import isolated_env, ros_context, spin_until  # noqa: F401  (ros_context is a fixture)

from msg_adapters.imu import imu_to_sample, sample_to_imu
from msg_adapters.image import image_to_numpy, numpy_to_image
from vigs_ros.replay import BagPlayer, ReplayConfig

T0 = 1_700_000_000_000_000_000
N_IMU, N_IMG = 20, 4


def small_messages():
    types = rosbags_types()
    msgs = [("/imu0", "sensor_msgs/msg/Imu", T0 + k * 5_000_000,
             sample_to_imu(types, T0 + k * 5_000_000, [0.01 * k, 0, 0], [0, 0, 9.81])) for k in range(N_IMU)]
    for k in range(N_IMG):
        img = np.full((6, 8), 10 * k, np.uint8)
        msgs.append(("/cam0/image_raw", "sensor_msgs/msg/Image", T0 + k * 25_000_000,
                     numpy_to_image(types, img, "mono8", T0 + k * 25_000_000, "cam0")))
    return sorted(msgs, key=lambda m: m[2])


def write_ros1_bag(path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    Imu, Header, Time = (store.types[n] for n in ("sensor_msgs/msg/Imu", "std_msgs/msg/Header",
                                                  "builtin_interfaces/msg/Time"))
    Vector3, Quaternion = store.types["geometry_msgs/msg/Vector3"], store.types["geometry_msgs/msg/Quaternion"]
    with Writer(path) as writer:
        conn = writer.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=store)
        for k in range(N_IMU):
            t = T0 + k * 5_000_000
            msg = Imu(header=Header(seq=k, stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id="imu0"),
                      orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
                      angular_velocity=Vector3(x=0.01 * k, y=0.0, z=0.0), angular_velocity_covariance=np.zeros(9),
                      linear_acceleration=Vector3(x=0.0, y=0.0, z=9.81),
                      linear_acceleration_covariance=np.zeros(9))
            writer.write(conn, t, store.serialize_ros1(msg, "sensor_msgs/msg/Imu"))
    return path


class Recorder:
    """Subscribes to topics (reliable, deep queue) and keeps every message."""

    def __init__(self, node, topics: dict[str, type]):
        from vigs_ros.qos import reliable_qos

        self.msgs = {t: [] for t in topics}
        for topic, cls in topics.items():
            node.create_subscription(cls, topic, lambda m, t=topic: self.msgs[t].append(m), reliable_qos(1000))


def play_in_thread(player: BagPlayer):
    result = {}
    thread = threading.Thread(target=lambda: result.update(stats=player.play()))
    thread.start()
    return thread, result


@pytest.mark.parametrize("storage", ["mcap", "sqlite3", "ros1"])
def test_replay_publishes_every_message_with_remap_and_clock(ros_context, tmp_path, storage):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, Imu

    if storage == "ros1":
        bag = write_ros1_bag(tmp_path / "small.bag")
        expected = {"/imu": N_IMU}
    else:
        bag = write_ros2_bag(tmp_path / "bag", small_messages(), storage)
        expected = {"/imu": N_IMU, "/image": N_IMG}
    node = Node("recorder", context=ros_context)
    rec = Recorder(node, {"/imu": Imu, "/image": Image, "/clock": Clock})
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    player = BagPlayer(bag, ReplayConfig(rate=5.0, remap={"/imu0": "/imu", "/cam0/image_raw": "/image"},
                                         wait_for=list(expected), wait_timeout_s=10.0), ros_context)
    thread, result = play_in_thread(player)
    assert spin_until(executor, lambda: all(len(rec.msgs[t]) >= n for t, n in expected.items()), 20.0)
    thread.join(10.0)
    player.close()
    assert result["stats"].published == expected
    stamps = [imu_to_sample(m)[0] for m in rec.msgs["/imu"]]
    assert stamps == [T0 + k * 5_000_000 for k in range(N_IMU)]
    np.testing.assert_allclose(imu_to_sample(rec.msgs["/imu"][3])[1], [0.03, 0, 0])
    if "/image" in expected:
        np.testing.assert_array_equal(image_to_numpy(rec.msgs["/image"][2])[0], np.full((6, 8), 20, np.uint8))
    assert spin_until(executor, lambda: len(rec.msgs["/clock"]) >= 1, 2.0)
    clock_ns = [m.clock.sec * 10**9 + m.clock.nanosec for m in rec.msgs["/clock"]]
    assert clock_ns == sorted(clock_ns) and clock_ns[0] >= T0
    # 95 ms of recorded time at x5: at least 19 ms of pacing
    assert result["stats"].bag_s == pytest.approx((N_IMU - 1) * 0.005, abs=1e-9)
    assert result["stats"].wall_s >= result["stats"].bag_s / 5.0


def test_fast_replay_waits_for_acknowledgements(ros_context, tmp_path):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import Image
    from std_msgs.msg import Header

    from vigs_ros.qos import reliable_qos

    bag = write_ros2_bag(tmp_path / "bag", small_messages())
    node = Node("consumer", context=ros_context)
    ack = node.create_publisher(Header, "/vigs/frame_done", reliable_qos(10))
    seen = []

    def consume(msg):  # acknowledge every other image only: the rest must time out
        seen.append(msg)
        if len(seen) % 2 == 1:
            ack.publish(Header(stamp=msg.header.stamp))

    node.create_subscription(Image, "/image", consume, reliable_qos(10))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)
    player = BagPlayer(bag, ReplayConfig(fast=True, remap={"/cam0/image_raw": "/image"}, ack_timeout_s=0.3,
                                         wait_for=["/image"]), ros_context)
    thread, result = play_in_thread(player)
    spin_until(executor, lambda: not thread.is_alive(), 20.0)
    thread.join(5.0)
    player.close()
    assert len(seen) == N_IMG
    assert result["stats"].ack_timeouts == N_IMG // 2


def test_replay_cli_errors(tmp_path):
    env = isolated_env()
    out = subprocess.run([sys.executable, "-m", "vigs_cli.main", "replay", str(tmp_path / "missing")],
                         capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 2 and "does not exist" in out.stdout
    bag = write_ros2_bag(tmp_path / "bag", small_messages())
    out = subprocess.run([sys.executable, "-m", "vigs_cli.main", "replay", str(bag), "--remap", "/imu0=/imu"],
                         capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 2 and "must look like" in out.stdout
    out = subprocess.run([sys.executable, "-m", "vigs_cli.main", "replay", str(bag), "--fast", "--ack-timeout",
                          "0.05"], capture_output=True, text=True, env=env, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"{N_IMU + N_IMG} messages on 2 topics" in out.stdout and "4 ack timeouts" in out.stdout


@pytest.mark.parametrize("after_s", [0.3, 4.0])
def test_an_interrupted_replay_stops_cleanly_during_start_up_and_mid_bag(tmp_path, after_s):
    """SIGINT while the process is still starting (before its node exists) or while it publishes: exit 0 within
    seconds, reported as interrupted, no traceback (rclpy's own handlers raced the publishing thread)."""
    import signal
    import time

    # the 20 IMU samples again every 0.1 s of bag time: about 10 s of bag played in real time
    long_msgs = [(topic, typ, t + rep * 100_000_000, msg) for rep in range(100)
                 for topic, typ, t, msg in small_messages() if topic == "/imu0"]
    bag = write_ros2_bag(tmp_path / "bag", sorted(long_msgs, key=lambda m: m[2]))
    proc = subprocess.Popen([sys.executable, "-m", "vigs_cli.main", "replay", str(bag)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=isolated_env())
    time.sleep(after_s)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert time.monotonic() - t0 < 5.0
    assert "[replay] interrupted" in out and "Traceback" not in out, out
