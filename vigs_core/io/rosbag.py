"""ROS bag writing (ROS 2: MCAP or sqlite3) and reading (ROS 2 and ROS 1) with the ``rosbags`` library,
no ROS installation needed. Messages are built directly from the ROS 2 Jazzy type store.

Topics written by :class:`BagWriter` (defaults of :class:`BagTopics`, EuRoC/Kalibr conventions):

| topic | type | content |
| --- | --- | --- |
| ``/cam0/image_raw`` | sensor_msgs/Image | ``mono8`` or ``rgb8`` frames, frame_id ``cam0`` |
| ``/cam0/image_raw/compressed`` | sensor_msgs/CompressedImage | with ``image_format="png"``: lossless PNG |
| ``/cam0/camera_info`` | sensor_msgs/CameraInfo | one per frame; ``plumb_bob`` (radtan), ``equidistant`` or none |
| ``/cam0/depth`` | sensor_msgs/Image | ``32FC1`` depth Z (m), same stamps (optional) |
| ``/imu0`` | sensor_msgs/Imu | angular velocity (rad/s), linear acceleration (m/s^2), frame_id ``imu0`` |
| ``/groundtruth/odometry`` | nav_msgs/Odometry | body (IMU) pose and world velocity, frame ``world`` -> ``imu0`` |
| ``/groundtruth/pose`` | geometry_msgs/PoseStamped | body pose in ``world`` |
| ``/tf_static`` | tf2_msgs/TFMessage | camera-IMU extrinsic ``T_BS``: ``imu0`` -> ``cam0`` |

Messages are written in stamp order (bag time = header stamp). MCAP chunks are zstd-compressed.
:func:`read_bag` finds topics by message type (and name when several match), so EuRoC ROS 1 bags and
other recordings with the same message types read too.
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from vigs_core.camera import CameraModel
from vigs_core.geometry import matrix_to_quat, quat_to_matrix
from vigs_core.types import BadFrame, ImuSamples, Trajectory

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
IMU = "sensor_msgs/msg/Imu"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


@dataclass(frozen=True)
class BagTopics:
    """Topic and frame names.

    Args:
        image: camera images.
        camera_info: camera calibration, one message per image.
        depth: 32FC1 depth images.
        imu: IMU samples.
        odometry: ground-truth body odometry.
        pose: ground-truth body poses.
        tf_static: static transforms (camera-IMU extrinsic).
        world_frame: frame of the ground truth.
        body_frame: IMU/body frame id.
        camera_frame: camera frame id.
    """

    image: str = "/cam0/image_raw"
    camera_info: str = "/cam0/camera_info"
    depth: str = "/cam0/depth"
    imu: str = "/imu0"
    odometry: str = "/groundtruth/odometry"
    pose: str = "/groundtruth/pose"
    tf_static: str = "/tf_static"
    world_frame: str = "world"
    body_frame: str = "imu0"
    camera_frame: str = "cam0"


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


class BagWriter:
    """Streams a visual-inertial recording into a ROS 2 bag.

    IMU and ground-truth messages are held in memory (small) and interleaved in stamp order with the
    frames given to :meth:`write_frame`, which must come in increasing stamp order.

    Args:
        path: bag directory to create (must not exist).
        camera: camera model (CameraInfo).
        T_BS: (4, 4) camera pose in the body frame (``/tf_static``), or None to omit it.
        imu: IMU samples.
        groundtruth: body trajectory (Odometry and PoseStamped), or None.
        storage: "mcap" (default, zstd-compressed chunks) or "sqlite3".
        topics: topic and frame names.
        with_depth: create the depth topic.
        image_format: "raw" (sensor_msgs/Image) or "png" (sensor_msgs/CompressedImage, lossless, on
            ``<image topic>/compressed`` as image_transport names it).
    """

    def __init__(
        self,
        path: str | Path,
        camera: CameraModel,
        T_BS: np.ndarray | None,
        imu: ImuSamples,
        groundtruth: Trajectory | None = None,
        storage: str = "mcap",
        topics: BagTopics = BagTopics(),
        with_depth: bool = False,
        image_format: str = "raw",
    ) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

        plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise ValueError(f"BagWriter: storage must be one of {sorted(plugins)}, got {storage!r}")
        if image_format not in ("raw", "png"):
            raise ValueError(f"BagWriter: image_format must be 'raw' or 'png', got {image_format!r}")
        self.image_format = image_format
        self.store = _typestore()
        self.camera = camera
        self.topics = topics
        self.writer = Writer(Path(path), version=9, storage_plugin=plugins[storage])
        if storage == "mcap":
            self.writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self.writer.open()
        add = lambda topic, msgtype: self.writer.add_connection(topic, msgtype, typestore=self.store)  # noqa: E731
        self.conn_image = (
            add(topics.image, IMAGE) if image_format == "raw" else add(topics.image + "/compressed", COMPRESSED_IMAGE)
        )
        self.conn_info = add(topics.camera_info, CAMERA_INFO)
        self.conn_depth = add(topics.depth, IMAGE) if with_depth else None
        self.conn_imu = add(topics.imu, IMU)
        imu_msgs = [(int(t), 0, i) for i, t in enumerate(imu.t_ns)]
        self.imu = imu
        self.groundtruth = groundtruth
        self.queue: list[tuple[int, int, int]] = imu_msgs  # (stamp, kind 0 imu / 1 gt, index)
        if groundtruth is not None:
            self.conn_odom = add(topics.odometry, ODOMETRY)
            self.conn_pose = add(topics.pose, POSE_STAMPED)
            self.queue += [(int(t), 1, i) for i, t in enumerate(groundtruth.t_ns)]
        self.queue.sort()
        self.next_item = 0
        self.frames_written = 0
        if T_BS is not None:
            conn_tf = add(topics.tf_static, TF_MESSAGE)
            first = int(min(imu.t_ns[0] if len(imu) else 2**62, self.queue[0][0] if self.queue else 2**62))
            self._write(conn_tf, first, self._tf_static(first, np.asarray(T_BS, dtype=np.float64)), TF_MESSAGE)

    # ------------------------------------------------------------------ message builders
    def _header(self, t_ns: int, frame_id: str):
        T = self.store.types
        return T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(t_ns // 10**9), nanosec=int(t_ns % 10**9)), frame_id=frame_id
        )

    def _write(self, connection, t_ns: int, msg, msgtype: str) -> None:
        self.writer.write(connection, int(t_ns), self.store.serialize_cdr(msg, msgtype))

    def _pose(self, position: np.ndarray, quat_wxyz: np.ndarray):
        T = self.store.types
        return T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2])),
            orientation=T["geometry_msgs/msg/Quaternion"](
                x=float(quat_wxyz[1]), y=float(quat_wxyz[2]), z=float(quat_wxyz[3]), w=float(quat_wxyz[0])
            ),
        )

    def _tf_static(self, t_ns: int, T_BS: np.ndarray):
        T = self.store.types
        q = matrix_to_quat(torch.from_numpy(T_BS[:3, :3].copy())).numpy()
        tr = T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(T_BS[0, 3]), y=float(T_BS[1, 3]), z=float(T_BS[2, 3])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
        )
        stamped = T["geometry_msgs/msg/TransformStamped"](
            header=self._header(t_ns, self.topics.body_frame), child_frame_id=self.topics.camera_frame, transform=tr
        )
        return T["tf2_msgs/msg/TFMessage"](transforms=[stamped])

    def _camera_info(self, t_ns: int):
        cam = self.camera
        model = {"none": "", "radtan": "plumb_bob", "equidistant": "equidistant"}[cam.distortion]
        d = list(cam.coeffs)
        if cam.distortion == "radtan" and len(d) == 4:
            d.append(0.0)
        k = np.array([cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0])
        p = np.array([cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        T = self.store.types
        return T[CAMERA_INFO](
            header=self._header(t_ns, self.topics.camera_frame),
            height=cam.height,
            width=cam.width,
            distortion_model=model,
            d=np.array(d, dtype=np.float64),
            k=k,
            r=np.eye(3).reshape(-1),
            p=p,
            binning_x=0,
            binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )

    def _image(self, t_ns: int, array: np.ndarray, encoding: str, bytes_per_pixel: int):
        h, w = array.shape[:2]
        return self.store.types[IMAGE](
            header=self._header(t_ns, self.topics.camera_frame),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=w * bytes_per_pixel,
            data=np.ascontiguousarray(array).view(np.uint8).reshape(-1),
        )

    def _flush_until(self, t_ns: int | None) -> None:
        """Write queued IMU / ground-truth messages with stamp <= t_ns (all if None)."""
        T = self.store.types
        zero9 = np.zeros(9)
        while self.next_item < len(self.queue) and (t_ns is None or self.queue[self.next_item][0] <= t_ns):
            stamp, kind, i = self.queue[self.next_item]
            self.next_item += 1
            if kind == 0:
                g, a = self.imu.gyro[i], self.imu.acc[i]
                msg = T[IMU](
                    header=self._header(stamp, self.topics.body_frame),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.array([-1.0] + [0.0] * 8),  # -1: no orientation estimate
                    angular_velocity=T["geometry_msgs/msg/Vector3"](x=float(g[0]), y=float(g[1]), z=float(g[2])),
                    angular_velocity_covariance=zero9,
                    linear_acceleration=T["geometry_msgs/msg/Vector3"](x=float(a[0]), y=float(a[1]), z=float(a[2])),
                    linear_acceleration_covariance=zero9,
                )
                self._write(self.conn_imu, stamp, msg, IMU)
                continue
            gt = self.groundtruth
            pose = self._pose(gt.position[i], gt.quat_wxyz[i])
            vel = np.zeros(3) if gt.velocity is None else gt.velocity[i]
            twist = T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=float(vel[0]), y=float(vel[1]), z=float(vel[2])),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
            )
            odom = T[ODOMETRY](
                header=self._header(stamp, self.topics.world_frame),
                child_frame_id=self.topics.body_frame,
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
            )
            self._write(self.conn_odom, stamp, odom, ODOMETRY)
            ps = T[POSE_STAMPED](header=self._header(stamp, self.topics.world_frame), pose=pose)
            self._write(self.conn_pose, stamp, ps, POSE_STAMPED)

    # ------------------------------------------------------------------ public
    def write_frame(self, t_ns: int, image: np.ndarray, depth: np.ndarray | None = None) -> None:
        """Write one frame (and the IMU / ground truth up to its stamp).

        Args:
            t_ns: stamp (ns), larger than the previous frame's.
            image: (H, W) uint8 grey or (H, W, 3) uint8 RGB.
            depth: (H, W) float32 depth (m); written only when the bag has a depth topic.
        """
        t_ns = int(t_ns)
        self._flush_until(t_ns)
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise ValueError(
                f"BagWriter.write_frame: expected a uint8 (H, W) or (H, W, 3) image, got {image.dtype} {image.shape}"
            )
        rgb = image.ndim == 3
        if self.image_format == "raw":
            msg = self._image(t_ns, image, "rgb8" if rgb else "mono8", 3 if rgb else 1)
            self._write(self.conn_image, t_ns, msg, IMAGE)
        else:
            import cv2

            ok, png = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if rgb else image)
            if not ok:
                raise ValueError(f"BagWriter.write_frame: PNG encoding failed for an image of shape {image.shape}")
            msg = self.store.types[COMPRESSED_IMAGE](
                header=self._header(t_ns, self.topics.camera_frame),
                format="rgb8; png compressed bgr8" if rgb else "mono8; png compressed mono8",
                data=png.reshape(-1),
            )
            self._write(self.conn_image, t_ns, msg, COMPRESSED_IMAGE)
        self._write(self.conn_info, t_ns, self._camera_info(t_ns), CAMERA_INFO)
        if self.conn_depth is not None and depth is not None:
            d = np.ascontiguousarray(depth, dtype="<f4")
            self._write(self.conn_depth, t_ns, self._image(t_ns, d, "32FC1", 4), IMAGE)
        self.frames_written += 1

    def close(self) -> None:
        """Write the remaining IMU / ground truth and close the bag."""
        self._flush_until(None)
        self.writer.close()


# ---------------------------------------------------------------------------------------------- reading
@dataclass
class BagRecording:
    """What :func:`read_bag` found in a bag.

    Attributes:
        path: the bag.
        image_topic: topic of the camera images (None if the bag has none).
        depth_topic: topic of 32FC1 depth images, if any.
        imu: all IMU samples (sorted by stamp; empty if no IMU topic).
        camera: camera model from the first CameraInfo, or None.
        T_BS: (4, 4) camera pose in the body frame from ``/tf_static`` (body -> camera), or None.
        groundtruth: body trajectory from Odometry (preferred) or PoseStamped, or None.
        image_count: number of image messages.
    """

    path: Path
    image_topic: str | None
    depth_topic: str | None
    imu: ImuSamples
    camera: CameraModel | None
    T_BS: np.ndarray | None
    groundtruth: Trajectory | None
    image_count: int

    def images(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(t_ns, image)`` in stamp order: (H, W) uint8 grey or (H, W, 3) uint8 RGB (header stamps), or a
        :class:`~vigs_core.types.BadFrame` for a message that cannot be decoded."""
        if self.image_topic is None:
            return iter(())
        return _iter_images(self.path, self.image_topic)

    def depths(self) -> Iterator[tuple[int, np.ndarray]]:
        """``(t_ns, depth (H, W) float32 m)`` in stamp order (empty without a depth topic)."""
        if self.depth_topic is None:
            return iter(())
        return _iter_images(self.path, self.depth_topic)


class DamagedBagWarning(UserWarning):
    """A bag could only be read up to damage in it (e.g. an MCAP file cut short)."""


def open_bag_reader(path: str | Path):
    """An opened reader over a ROS 2 bag directory, a bare ``.mcap`` / ``.db3`` file or a ROS 1 ``.bag``: a rosbags
    ``AnyReader``, or for an MCAP file rosbags cannot open (cut short: no footer) its readable part
    (:class:`~vigs_core.io.mcap_salvage.SalvagedMcap`, with a :class:`DamagedBagWarning`). ValueError names the
    path when it is none of those."""
    import warnings

    from rosbags.highlevel import AnyReader

    from vigs_core.io.mcap_salvage import SalvagedMcap

    path = Path(path)
    if not path.exists():
        raise ValueError(f"bag {path} does not exist")
    try:
        reader = AnyReader([path], default_typestore=_typestore())
        reader.open()
        return reader
    except Exception as exc:   # noqa: BLE001 - rosbags raises several reader-specific errors
        mcaps = [path] if path.suffix == ".mcap" else sorted(path.glob("*.mcap")) if path.is_dir() else []
        if len(mcaps) != 1:
            raise ValueError(f"cannot open {path} as a ROS 1 or ROS 2 bag: {exc}") from None
        salvaged = SalvagedMcap(mcaps[0], _typestore())
        warnings.warn(f"{mcaps[0]} is damaged ({exc}); reading its {salvaged.message_count} messages up to the "
                      f"damage ({salvaged.damage})", DamagedBagWarning, stacklevel=2)
        return salvaged


@contextmanager
def _reader(path: Path):
    reader = open_bag_reader(path)
    try:
        yield reader
    finally:
        reader.close()


def _messages(reader, connections: list) -> Iterator:
    """``(connection, bag time, raw)`` of the given connections only (rosbags reads all for an empty list)."""
    return reader.messages(connections=connections) if connections else iter(())


def _stamp(header) -> int:
    return int(header.stamp.sec) * 10**9 + int(header.stamp.nanosec)


def decode_image(msg) -> np.ndarray:
    """A sensor_msgs Image or CompressedImage message as an array.

    mono8 -> (H, W) uint8; rgb8 / bgr8 -> (H, W, 3) uint8 RGB; mono16 -> (H, W) uint16;
    32FC1 -> (H, W) float32. Raises ValueError for other encodings.
    """
    import cv2

    if not hasattr(msg, "encoding"):  # CompressedImage
        image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"decode_image: cannot decode a CompressedImage of format {msg.format!r}")
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if image.ndim == 3 else image
    dtypes = {"mono8": (np.uint8, 1), "8UC1": (np.uint8, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3),
              "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}
    if msg.encoding not in dtypes:
        raise ValueError(f"decode_image: unsupported encoding {msg.encoding!r}; expected one of {sorted(dtypes)}")
    dtype, channels = dtypes[msg.encoding]
    dt = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    rows = np.asarray(msg.data, dtype=np.uint8).reshape(msg.height, msg.step)
    width_bytes = msg.width * channels * dt.itemsize
    image = rows[:, :width_bytes].copy().view(dt).reshape(msg.height, msg.width, channels).astype(dtype)
    if msg.encoding == "bgr8":
        image = image[..., ::-1].copy()
    return image[..., 0] if channels == 1 else image


def _iter_images(path: Path, topic: str) -> Iterator[tuple[int, np.ndarray]]:
    with _reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in _messages(reader, conns):
            msg = reader.deserialize(raw, conn.msgtype)
            try:
                image = decode_image(msg)
            except ValueError as err:   # one bad message: the caller skips the frame
                image = BadFrame(str(err))
            yield _stamp(msg.header), image


def camera_from_info(msg) -> CameraModel:
    """:class:`CameraModel` of a sensor_msgs/CameraInfo (plumb_bob / rational_polynomial -> radtan with
    ``(k1, k2, p1, p2[, k3])``, k3 dropped when 0; equidistant -> ``(k1, k2, k3, k4)``; empty / none -> pinhole)."""
    k = np.asarray(msg.k, dtype=np.float64)
    d = [float(x) for x in np.asarray(msg.d, dtype=np.float64)]
    model = msg.distortion_model
    if model in ("plumb_bob", "rational_polynomial") and any(d):
        coeffs5 = (d + [0.0] * 5)[:5]
        distortion, coeffs = "radtan", tuple(coeffs5 if coeffs5[4] != 0.0 else coeffs5[:4])
    elif model == "equidistant":
        distortion, coeffs = "equidistant", tuple((d + [0.0] * 4)[:4])
    elif model in ("", "none") or not any(d):
        distortion, coeffs = "none", ()
    else:
        raise ValueError(
            f"camera_from_info: unsupported distortion_model {model!r}; expected plumb_bob, rational_polynomial, "
            "equidistant or none"
        )
    return CameraModel(int(msg.width), int(msg.height), k[0], k[4], k[2], k[5], distortion, coeffs)


def _pick(conns, msgtypes: tuple[str, ...], preferred: str | None, exclude: str | None = None):
    """The connection topic of one of ``msgtypes``: ``preferred`` if present, else the first by name."""
    matches = sorted({c.topic for c in conns if c.msgtype in msgtypes and (exclude is None or exclude not in c.topic)})
    if preferred in matches:
        return preferred
    return matches[0] if matches else None


def read_bag(
    path: str | Path,
    image_topic: str | None = None,
    imu_topic: str | None = None,
    groundtruth_topic: str | None = None,
) -> BagRecording:
    """Read a ROS 2 (MCAP / sqlite3) or ROS 1 bag: IMU, calibration and ground truth now, images lazily.

    Topics not given are found by type: images (Image / CompressedImage whose name does not contain
    "depth"; ``/cam0/image_raw`` preferred), 32FC1 depth (an Image topic containing "depth"), Imu
    (``/imu0`` preferred), ground truth (Odometry, else PoseStamped), CameraInfo, ``/tf_static``.

    Args:
        path: bag directory (ROS 2) or ``.bag`` file (ROS 1).
        image_topic: camera image topic.
        imu_topic: IMU topic.
        groundtruth_topic: ground-truth Odometry or PoseStamped topic.

    Returns:
        :class:`BagRecording`; iterate images with ``recording.images()``.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"read_bag: {path} does not exist (expected a ROS 2 bag directory or a ROS 1 .bag)")
    defaults = BagTopics()
    with _reader(path) as reader:
        conns = reader.connections
        image_topic = image_topic or _pick(conns, (IMAGE, COMPRESSED_IMAGE), defaults.image, exclude="depth")
        depth_topic = next(
            (c.topic for c in conns if c.msgtype == IMAGE and "depth" in c.topic and c.topic != image_topic), None
        )
        imu_topic = imu_topic or _pick(conns, (IMU,), defaults.imu)
        gt_topic = groundtruth_topic or _pick(conns, (ODOMETRY,), defaults.odometry) or _pick(
            conns, (POSE_STAMPED,), defaults.pose
        )
        info_conns = [c for c in conns if c.msgtype == CAMERA_INFO]
        if image_topic is not None and len(info_conns) > 1:
            ns = image_topic.rsplit("/", 1)[0]
            info_conns = [c for c in info_conns if c.topic.startswith(ns + "/")] or info_conns[:1]
        camera = None
        for conn, _, raw in _messages(reader, info_conns[:1]):
            camera = camera_from_info(reader.deserialize(raw, conn.msgtype))
            break
        # camera-IMU extrinsic: the static transform to the camera frame (else the first static transform)
        transforms = []
        tf_conns = [c for c in conns if c.msgtype == TF_MESSAGE and c.topic == "/tf_static"]
        for conn, _, raw in _messages(reader, tf_conns):
            transforms += list(reader.deserialize(raw, conn.msgtype).transforms)
        chosen = [tr for tr in transforms if tr.child_frame_id == defaults.camera_frame] or transforms[:1]
        T_BS = None
        if chosen:
            q, t = chosen[0].transform.rotation, chosen[0].transform.translation
            T_BS = np.eye(4)
            T_BS[:3, :3] = quat_to_matrix(torch.tensor([q.w, q.x, q.y, q.z], dtype=torch.float64)).numpy()
            T_BS[:3, 3] = [t.x, t.y, t.z]
        imu_rows = []
        if imu_topic is not None:
            imu_conns = [c for c in conns if c.topic == imu_topic]
            for conn, _, raw in _messages(reader, imu_conns):
                m = reader.deserialize(raw, conn.msgtype)
                w, a = m.angular_velocity, m.linear_acceleration
                imu_rows.append((_stamp(m.header), w.x, w.y, w.z, a.x, a.y, a.z))
        groundtruth = None
        if gt_topic is not None:
            gt_conns = [c for c in conns if c.topic == gt_topic]
            rows, vel = [], []
            for conn, _, raw in _messages(reader, gt_conns):
                m = reader.deserialize(raw, conn.msgtype)
                pose = m.pose.pose if conn.msgtype == ODOMETRY else m.pose
                p, q = pose.position, pose.orientation
                rows.append((_stamp(m.header), p.x, p.y, p.z, q.w, q.x, q.y, q.z))
                if conn.msgtype == ODOMETRY:
                    v = m.twist.twist.linear
                    vel.append((v.x, v.y, v.z))
            if rows:
                order = np.argsort(np.array([r[0] for r in rows]), kind="stable")
                arr = np.array([r[1:] for r in rows], dtype=np.float64)[order]
                t_gt = np.array([r[0] for r in rows], dtype=np.int64)[order]
                velocity = np.array(vel, dtype=np.float64)[order] if vel else None
                groundtruth = Trajectory(t_gt, arr[:, :3], arr[:, 3:7], velocity=velocity)
        image_count = sum(c.msgcount for c in conns if c.topic == image_topic)
    if imu_rows:
        arr = np.array(imu_rows, dtype=np.float64)
        t_imu = np.array([r[0] for r in imu_rows], dtype=np.int64)
        order = np.argsort(t_imu, kind="stable")
        imu = ImuSamples(t_imu[order], arr[order, 1:4], arr[order, 4:7])
    else:
        imu = ImuSamples(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    return BagRecording(path, image_topic, depth_topic, imu, camera, T_BS, groundtruth, image_count)
