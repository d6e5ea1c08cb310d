"""Bags for the ROS tests, written with rosbags: small hand-made ones and a short simulated camera + IMU
sequence (vigs_core.sim: a room seen by a 188x120 EuRoC-like camera on a smooth random path, noise-free IMU).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msg_adapters.camera_info import model_to_camera_info
from msg_adapters.image import numpy_to_image
from msg_adapters.imu import sample_to_imu
from msg_adapters.types import RosbagsTypes

SAMPLE_BAG = Path(__file__).resolve().parent.parent / "bags" / "v1_01_easy_hybrid_376x240"   # the shipped sample
SAMPLE_GT = SAMPLE_BAG.parent / f"{SAMPLE_BAG.name}_groundtruth_tum.txt"
_TYPES: list = []


def rosbags_types() -> RosbagsTypes:
    if not _TYPES:
        _TYPES.append(RosbagsTypes())
    return _TYPES[0]


def write_ros2_bag(path: Path, messages: list[tuple[str, str, int, object]], storage: str = "mcap") -> Path:
    """Write ``(topic, typename, t_ns, rosbags message)`` tuples to a ROS 2 bag directory at ``path``."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    types = rosbags_types()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {}
        for topic, typename, t_ns, msg in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, typename, typestore=types.typestore)
            writer.write(conns[topic], t_ns, types.serialize(msg, typename))
    return path


@dataclass
class SimBag:
    """A simulated bag: its path, the camera, the frame stamps (ns) and the ground-truth camera poses."""

    path: Path
    camera: object
    frame_t_ns: np.ndarray
    T_WC: np.ndarray
    T_BS: np.ndarray
    imu_count: int


def write_sim_bag(path: Path, duration_s: float = 2.5, seed: int = 0) -> SimBag:
    """Render ``duration_s`` of a simulated sequence into an MCAP bag: ``/cam0/image_raw`` (mono8),
    ``/cam0/camera_info`` (radtan) and ``/imu0`` (200 Hz)."""
    import torch

    from vigs_core.sim.hybrid import SimConfig, SimSequence, euroc_cam0_calibration, synthetic_source
    from vigs_core.sim.trajectory import ProceduralConfig, ProceduralMotion
    from vigs_core.types import ImuNoise

    torch.set_num_threads(1)
    cal = euroc_cam0_calibration()
    camera = cal.camera.scaled(0.25)
    motion = ProceduralMotion(seed, cal.T_BS[:3, :3], ProceduralConfig(duration_s=duration_s + 1.0))
    source = synthetic_source(motion, ImuNoise(), noise_free=True)
    seq = SimSequence(source, camera, cal.T_BS, SimConfig(duration_s=duration_s, with_depth=False))
    types = rosbags_types()
    msgs = []
    for t, g, a in zip(seq.imu.t_ns, seq.imu.gyro, seq.imu.acc):
        msgs.append(("/imu0", "sensor_msgs/msg/Imu", int(t), sample_to_imu(types, int(t), g, a, "imu0")))
    poses = []
    for frame in seq.frames():
        image = frame.image if frame.image.ndim == 2 else frame.image[..., 0]
        msgs.append(("/cam0/image_raw", "sensor_msgs/msg/Image", frame.t_ns,
                     numpy_to_image(types, image, "mono8", frame.t_ns, "cam0")))
        msgs.append(("/cam0/camera_info", "sensor_msgs/msg/CameraInfo", frame.t_ns,
                     model_to_camera_info(types, camera, frame.t_ns, "cam0")))
        poses.append(frame.T_WC)
    msgs.sort(key=lambda m: m[2])
    write_ros2_bag(path, msgs)
    return SimBag(path, camera, seq.frame_t_ns.copy(), np.stack(poses), cal.T_BS, len(seq.imu))


def write_prefix(src: Path, dst: Path, seconds: float) -> int:
    """Copy the first ``seconds`` of every topic of ROS 2 bag ``src`` into ``dst`` (raw CDR, same types);
    returns the number of images copied."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    images = 0
    with AnyReader([src]) as reader, Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        out = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest)
               for c in reader.connections}
        stop = reader.start_time + int(seconds * 1e9)
        for conn, t_ns, raw in reader.messages(stop=stop):
            writer.write(out[conn.id], t_ns, raw)
            images += conn.msgtype == "sensor_msgs/msg/CompressedImage"
    return images
