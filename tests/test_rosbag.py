"""ROS bag round trips: BagWriter -> read_bag (rosbags) and -> the mcap reader; sqlite3, PNG and RGB
variants; byte-identical output; ROS 1 bags read through the same reader."""
from pathlib import Path

import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel
from vigs_core.io.rosbag import BagTopics, BagWriter, read_bag
from vigs_core.sim.hybrid import euroc_cam0_calibration
from vigs_core.types import ImuSamples, Trajectory

torch.set_num_threads(1)

T0 = 1_403_715_283_262_142_976


def _recording(rgb=False, n_frames=4):
    rng = np.random.default_rng(0)
    shape = (30, 40, 3) if rgb else (30, 40)
    frames = [(T0 + k * 50_000_000, rng.integers(0, 256, shape, dtype=np.uint8)) for k in range(n_frames)]
    depths = [rng.uniform(0.5, 8.0, (30, 40)).astype(np.float32) for _ in range(n_frames)]
    t_imu = T0 - 5_000_000 + np.arange(45) * 5_000_000
    imu = ImuSamples(t_imu, rng.normal(size=(45, 3)), rng.normal(size=(45, 3)) + [0, 0, 9.81])
    q = rng.normal(size=(12, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    gt = Trajectory(T0 + np.arange(12) * 20_000_000, rng.normal(size=(12, 3)), q, velocity=rng.normal(size=(12, 3)))
    return frames, depths, imu, gt


def _write(path, camera, frames, depths, imu, gt, **kwargs):
    writer = BagWriter(path, camera, euroc_cam0_calibration().T_BS, imu, gt, with_depth=depths is not None, **kwargs)
    for k, (t, image) in enumerate(frames):
        writer.write_frame(t, image, None if depths is None else depths[k])
    writer.close()


CAMERA = euroc_cam0_calibration().camera.resized(40, 30)


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_bag_round_trip_through_read_bag(tmp_path, storage):
    frames, depths, imu, gt = _recording()
    _write(tmp_path / "bag", CAMERA, frames, depths, imu, gt, storage=storage)
    rec = read_bag(tmp_path / "bag")
    assert rec.image_topic == "/cam0/image_raw" and rec.depth_topic == "/cam0/depth" and rec.image_count == 4
    assert rec.camera == CAMERA
    np.testing.assert_allclose(rec.T_BS, euroc_cam0_calibration().T_BS, atol=1e-12)
    np.testing.assert_array_equal(rec.imu.t_ns, imu.t_ns)
    np.testing.assert_array_equal(rec.imu.gyro, imu.gyro)
    np.testing.assert_array_equal(rec.imu.acc, imu.acc)
    np.testing.assert_array_equal(rec.groundtruth.t_ns, gt.t_ns)
    np.testing.assert_array_equal(rec.groundtruth.position, gt.position)
    np.testing.assert_array_equal(rec.groundtruth.quat_wxyz, gt.quat_wxyz)
    np.testing.assert_array_equal(rec.groundtruth.velocity, gt.velocity)
    images = list(rec.images())
    assert [t for t, _ in images] == [t for t, _ in frames]
    for (_, got), (_, want) in zip(images, frames):
        np.testing.assert_array_equal(got, want)
    for (_, got), want in zip(rec.depths(), depths):
        np.testing.assert_array_equal(got, want)


def test_bag_round_trip_through_the_mcap_reader(tmp_path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    frames, depths, imu, gt = _recording()
    _write(tmp_path / "bag", CAMERA, frames, depths, imu, gt)
    by_topic: dict[str, list] = {}
    stamps = []
    with open(tmp_path / "bag" / "bag.mcap", "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, channel, message, ros_msg in reader.iter_decoded_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append(ros_msg)
            stamps.append(message.log_time)
    assert stamps == sorted(stamps)  # written in stamp order
    topics = BagTopics()
    assert len(by_topic[topics.image]) == 4 and len(by_topic[topics.imu]) == 45 and len(by_topic[topics.odometry]) == 12
    img = by_topic[topics.image][1]
    assert img.encoding == "mono8" and (img.height, img.width, img.step) == (30, 40, 40)
    np.testing.assert_array_equal(np.frombuffer(bytes(img.data), np.uint8).reshape(30, 40), frames[1][1])
    assert img.header.stamp.sec * 10**9 + img.header.stamp.nanosec == frames[1][0]
    info = by_topic[topics.camera_info][0]
    assert info.distortion_model == "plumb_bob" and list(info.k)[0] == pytest.approx(CAMERA.fx)
    m = by_topic[topics.imu][7]
    assert (m.angular_velocity.x, m.linear_acceleration.z) == (imu.gyro[7, 0], imu.acc[7, 2])
    d = by_topic[topics.depth][2]
    assert d.encoding == "32FC1"
    np.testing.assert_array_equal(np.frombuffer(bytes(d.data), "<f4").reshape(30, 40), depths[2])
    tf = by_topic[topics.tf_static][0].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("imu0", "cam0")


def test_png_rgb_and_equidistant_variants_and_byte_identical_output(tmp_path):
    frames, _, imu, gt = _recording(rgb=True)
    fisheye = CameraModel(40, 30, 20.0, 20.0, 19.5, 14.5, "equidistant", (0.01, -0.02, 0.003, -0.001))
    _write(tmp_path / "a" / "bag", fisheye, frames, None, imu, gt, image_format="png")
    _write(tmp_path / "b" / "bag", fisheye, frames, None, imu, gt, image_format="png")
    files = lambda root: {p.name: p.read_bytes() for p in Path(root).iterdir()}  # noqa: E731
    assert files(tmp_path / "a" / "bag") == files(tmp_path / "b" / "bag")
    assert len(files(tmp_path / "a" / "bag")) == 2
    rec = read_bag(tmp_path / "a" / "bag")
    assert rec.image_topic == "/cam0/image_raw/compressed" and rec.depth_topic is None
    assert rec.camera == fisheye
    for (_, got), (_, want) in zip(rec.images(), frames):
        np.testing.assert_array_equal(got, want)  # lossless, RGB order kept


def test_ros1_bags_read_through_the_same_reader(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    T = store.types
    frames, _, imu, _ = _recording(n_frames=2)
    path = tmp_path / "euroc_like.bag"
    with Writer(path) as writer:
        conn_img = writer.add_connection("/cam0/image_raw", "sensor_msgs/msg/Image", typestore=store)
        conn_imu = writer.add_connection("/imu0", "sensor_msgs/msg/Imu", typestore=store)

        def header(t, frame):
            stamp = T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9)
            return T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)

        vec = lambda v: T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))  # noqa: E731
        for i, t in enumerate(imu.t_ns[:10]):
            msg = T["sensor_msgs/msg/Imu"](
                header=header(int(t), "imu4"),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=vec(imu.gyro[i]),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=vec(imu.acc[i]), linear_acceleration_covariance=np.zeros(9),
            )
            writer.write(conn_imu, int(t), store.serialize_ros1(msg, "sensor_msgs/msg/Imu"))
        for t, image in frames:
            msg = T["sensor_msgs/msg/Image"](header=header(t, "cam0"), height=30, width=40, encoding="mono8",
                                             is_bigendian=0, step=40, data=image.reshape(-1))
            writer.write(conn_img, t, store.serialize_ros1(msg, "sensor_msgs/msg/Image"))
    rec = read_bag(path)
    np.testing.assert_array_equal(rec.imu.gyro, imu.gyro[:10])
    assert rec.camera is None and rec.groundtruth is None
    got = list(rec.images())
    np.testing.assert_array_equal(got[1][1], frames[1][1])
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_bag(tmp_path / "missing")


def test_an_mcap_bag_cut_short_is_read_up_to_the_damage(tmp_path):
    """The shipped sample's MCAP file cut at 60% (no footer, the last chunk broken): rosbags refuses it; read_bag
    warns and reads what precedes the damage (IMU, camera info, images in order), and ``vigs run`` tracks those
    frames."""
    import json
    import warnings

    from ros_bags import SAMPLE_BAG

    from vigs_cli.main import main as vigs_main
    from vigs_core.io.rosbag import DamagedBagWarning

    whole = read_bag(SAMPLE_BAG)
    (mcap,) = Path(SAMPLE_BAG).glob("*.mcap")
    cut = tmp_path / "cut"
    cut.mkdir()
    data = mcap.read_bytes()
    (cut / mcap.name).write_bytes(data[:len(data) * 6 // 10])
    with pytest.warns(DamagedBagWarning, match="is damaged"):
        rec = read_bag(cut)
    assert rec.camera == whole.camera and 0.4 * len(whole.imu) < len(rec.imu) < 0.7 * len(whole.imu)
    np.testing.assert_array_equal(rec.imu.t_ns, whole.imu.t_ns[:len(rec.imu)])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DamagedBagWarning)
        stamps = [t for t, _ in rec.images()]
        assert len(stamps) == rec.image_count and 0.4 * whole.image_count < len(stamps) < 0.7 * whole.image_count
        assert stamps == sorted(stamps)
        params = tmp_path / "p.yaml"
        params.write_text("frontend:\n  ros__parameters:\n    mapping: {enabled: false}\n    loop: {enabled: false}\n")
        assert vigs_main(["run", str(cut), "--out", str(tmp_path / "out"), "--params", str(params),
                          "--no-progress"]) == 0
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["frames_posed"] == len(stamps) and report["vio"]["metric"]
