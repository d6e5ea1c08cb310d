"""The VIGS messages (interfaces/vigs_msgs) <-> plain dataclasses of numpy arrays.

Each ``*_to_msg`` builds a message with a :class:`~msg_adapters.types.MessageTypes` provider; each
``msg_to_*`` reads one duck-typed (rclpy or rosbags) and validates sizes, raising ValueError with what
was wrong. See the ``.msg`` files for units and frames.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msg_adapters.camera_info import camera_info_to_model, model_to_camera_info
from msg_adapters.common import (
    field,
    finite_array,
    header_stamp_ns,
    make_header,
    ns_to_stamp,
    numeric,
    pose_msg,
    pose_to_matrix,
    read_vector3,
    stamp_to_ns,
    vector3,
)
from msg_adapters.image import image_to_numpy, numpy_to_image
from msg_adapters.types import MessageTypes
from vigs_core.camera import CameraModel


@dataclass
class KeyframeData:
    """A keyframe: ``T_wc`` (4, 4) camera pose in the world, undistorted ``image`` ((H, W) or (H, W, 3)),
    ``camera`` its pinhole intrinsics, ``disparity`` (h, w) float32 inverse depth (1/m) or None; ``metric``:
    pose and disparity are in metres (the visual-inertial odometry is initialised)."""

    id: int
    t_ns: int
    T_wc: np.ndarray
    image: np.ndarray
    encoding: str
    camera: CameraModel
    disparity: np.ndarray | None = None
    frame_id: str = "map"
    camera_frame_id: str = "camera"
    metric: bool = False


def keyframe_to_msg(types: MessageTypes, kf: KeyframeData):
    if (kf.camera.width, kf.camera.height) != (kf.image.shape[1], kf.image.shape[0]):
        raise ValueError(
            f"Keyframe {kf.id}: image is {kf.image.shape[1]}x{kf.image.shape[0]} but camera is "
            f"{kf.camera.width}x{kf.camera.height}"
        )
    if kf.disparity is not None and kf.disparity.size:
        disparity = numpy_to_image(types, np.asarray(kf.disparity, np.float32), "32FC1", kf.t_ns, kf.camera_frame_id)
    else:
        disparity = types.new("sensor_msgs/msg/Image", header=make_header(types, kf.t_ns, kf.camera_frame_id),
                              height=0, width=0, encoding="32FC1", is_bigendian=0, step=0,
                              data=types.sequence([], np.uint8))
    return types.new(
        "vigs_msgs/msg/Keyframe",
        header=make_header(types, kf.t_ns, kf.frame_id),
        id=int(kf.id),
        pose=pose_msg(types, kf.T_wc),
        metric=bool(kf.metric),
        image=numpy_to_image(types, kf.image, kf.encoding, kf.t_ns, kf.camera_frame_id),
        disparity=disparity,
        camera_info=model_to_camera_info(types, kf.camera, kf.t_ns, kf.camera_frame_id),
    )


def msg_to_keyframe(msg) -> KeyframeData:
    image, encoding = image_to_numpy(field(msg, "image", "Keyframe"))
    camera = camera_info_to_model(field(msg, "camera_info", "Keyframe"))
    if (camera.width, camera.height) != (image.shape[1], image.shape[0]):
        raise ValueError(
            f"Keyframe: image is {image.shape[1]}x{image.shape[0]} but camera_info is {camera.width}x{camera.height}"
        )
    disp_msg = field(msg, "disparity", "Keyframe")
    disparity = None
    if int(disp_msg.width) > 0:
        disparity, disp_enc = image_to_numpy(disp_msg)
        if disp_enc != "32FC1":
            raise ValueError(f"Keyframe: disparity must be 32FC1, got {disp_enc!r}")
    return KeyframeData(
        id=int(field(msg, "id", "Keyframe")),
        t_ns=header_stamp_ns(msg, "Keyframe"),
        T_wc=pose_to_matrix(field(msg, "pose", "Keyframe"), "Keyframe.pose"),
        image=image,
        encoding=encoding,
        camera=camera,
        disparity=disparity,
        frame_id=str(msg.header.frame_id),
        camera_frame_id=str(msg.image.header.frame_id),
        metric=bool(field(msg, "metric", "Keyframe")),
    )


@dataclass
class NavStateData:
    """``T_wb`` (4, 4) body pose, ``velocity`` (3,) m/s in the world, biases (3,) rad/s and m/s^2."""

    t_ns: int
    keyframe_id: int
    T_wb: np.ndarray
    velocity: np.ndarray
    bias_gyro: np.ndarray
    bias_acc: np.ndarray
    inertial_initialized: bool = False
    frame_id: str = "map"


def nav_state_to_msg(types: MessageTypes, s: NavStateData):
    return types.new(
        "vigs_msgs/msg/NavState",
        header=make_header(types, s.t_ns, s.frame_id),
        keyframe_id=int(s.keyframe_id),
        pose=pose_msg(types, s.T_wb),
        velocity=vector3(types, s.velocity),
        gyro_bias=vector3(types, s.bias_gyro),
        acc_bias=vector3(types, s.bias_acc),
        inertial_initialized=bool(s.inertial_initialized),
    )


def msg_to_nav_state(msg) -> NavStateData:
    return NavStateData(
        t_ns=header_stamp_ns(msg, "NavState"),
        keyframe_id=int(field(msg, "keyframe_id", "NavState")),
        T_wb=pose_to_matrix(field(msg, "pose", "NavState"), "NavState.pose"),
        velocity=read_vector3(field(msg, "velocity", "NavState"), "NavState.velocity"),
        bias_gyro=read_vector3(field(msg, "gyro_bias", "NavState"), "NavState.gyro_bias"),
        bias_acc=read_vector3(field(msg, "acc_bias", "NavState"), "NavState.acc_bias"),
        inertial_initialized=bool(field(msg, "inertial_initialized", "NavState")),
        frame_id=str(msg.header.frame_id),
    )


_BIAS_JACOBIANS = ("d_rotation_d_gyro_bias", "d_velocity_d_gyro_bias", "d_velocity_d_acc_bias",
                   "d_position_d_gyro_bias", "d_position_d_acc_bias")


@dataclass
class PreintegrationData:
    """IMU preintegrated from keyframe ``from_id`` (``start_ns``) to ``to_id`` (``end_ns``).

    ``delta_R`` (3, 3), ``delta_v`` (3,) m/s, ``delta_p`` (3,) m, ``covariance`` (9, 9) over (phi, v, p),
    ``jacobians`` maps the five names of the message (``d_rotation_d_gyro_bias`` ...) to (3, 3) arrays,
    ``bias_gyro`` / ``bias_acc`` (3,) the linearisation bias.
    """

    from_id: int
    to_id: int
    start_ns: int
    end_ns: int
    num_samples: int
    delta_R: np.ndarray
    delta_v: np.ndarray
    delta_p: np.ndarray
    covariance: np.ndarray
    jacobians: dict[str, np.ndarray]
    bias_gyro: np.ndarray
    bias_acc: np.ndarray
    frame_id: str = "imu"

    @property
    def dt(self) -> float:
        """Window length (s)."""
        return (self.end_ns - self.start_ns) * 1e-9


def preintegration_to_msg(types: MessageTypes, p: PreintegrationData):
    if p.end_ns < p.start_ns:
        raise ValueError(f"PreintegratedImu: end {p.end_ns} ns before start {p.start_ns} ns")
    missing = set(_BIAS_JACOBIANS) - set(p.jacobians)
    if missing:
        raise ValueError(f"PreintegratedImu: missing bias Jacobians {sorted(missing)}")
    jac = {k: finite_array(p.jacobians[k], (3, 3), k).reshape(-1) for k in _BIAS_JACOBIANS}
    return types.new(
        "vigs_msgs/msg/PreintegratedImu",
        header=make_header(types, p.end_ns, p.frame_id),
        from_keyframe_id=int(p.from_id),
        to_keyframe_id=int(p.to_id),
        start_stamp=ns_to_stamp(types, p.start_ns),
        end_stamp=ns_to_stamp(types, p.end_ns),
        dt=float(p.dt),
        num_samples=int(p.num_samples),
        delta_rotation=finite_array(p.delta_R, (3, 3), "delta_R").reshape(-1),
        delta_velocity=finite_array(p.delta_v, (3,), "delta_v"),
        delta_position=finite_array(p.delta_p, (3,), "delta_p"),
        covariance=finite_array(p.covariance, (9, 9), "covariance").reshape(-1),
        gyro_bias=vector3(types, p.bias_gyro),
        acc_bias=vector3(types, p.bias_acc),
        **jac,
    )


def msg_to_preintegration(msg) -> PreintegrationData:
    what = "PreintegratedImu"

    def mat(name, shape):
        return finite_array(numeric(field(msg, name, what), np.float64, f"{what}.{name}"), shape, f"{what}.{name}")

    start = stamp_to_ns(field(msg, "start_stamp", what))
    end = stamp_to_ns(field(msg, "end_stamp", what))
    if end < start:
        raise ValueError(f"{what}: end_stamp {end} ns before start_stamp {start} ns")
    dt = float(field(msg, "dt", what))
    if abs(dt - (end - start) * 1e-9) > 1e-6:
        raise ValueError(f"{what}: dt {dt} s disagrees with end - start = {(end - start) * 1e-9} s")
    cov = mat("covariance", (9, 9))
    if np.abs(cov - cov.T).max() > 1e-9 * max(1.0, np.abs(cov).max()):
        raise ValueError(f"{what}: covariance is not symmetric")
    return PreintegrationData(
        from_id=int(field(msg, "from_keyframe_id", what)),
        to_id=int(field(msg, "to_keyframe_id", what)),
        start_ns=start,
        end_ns=end,
        num_samples=int(field(msg, "num_samples", what)),
        delta_R=mat("delta_rotation", (3, 3)),
        delta_v=mat("delta_velocity", (3,)),
        delta_p=mat("delta_position", (3,)),
        covariance=cov,
        jacobians={k: mat(k, (3, 3)) for k in _BIAS_JACOBIANS},
        bias_gyro=read_vector3(field(msg, "gyro_bias", what), f"{what}.gyro_bias"),
        bias_acc=read_vector3(field(msg, "acc_bias", what), f"{what}.acc_bias"),
        frame_id=str(msg.header.frame_id),
    )


@dataclass
class PoseUpdateData:
    """New poses ``T_wc`` (K, 4, 4) and Sim(3) ``scales`` (K,) of keyframes ``ids`` (K,)."""

    t_ns: int
    ids: np.ndarray
    poses: np.ndarray
    scales: np.ndarray
    frame_id: str = "map"


def pose_update_to_msg(types: MessageTypes, u: PoseUpdateData):
    ids = np.asarray(u.ids, dtype=np.uint64).reshape(-1)
    poses = np.asarray(u.poses, dtype=np.float64).reshape(-1, 4, 4)
    scales = np.asarray(u.scales, dtype=np.float64).reshape(-1)
    if not (len(ids) == len(poses) == len(scales)):
        raise ValueError(f"KeyframePoseUpdate: {len(ids)} ids, {len(poses)} poses, {len(scales)} scales")
    if np.any(~np.isfinite(scales)) or np.any(scales <= 0):
        raise ValueError(f"KeyframePoseUpdate: scales must be finite and > 0, got {scales.tolist()}")
    return types.new(
        "vigs_msgs/msg/KeyframePoseUpdate",
        header=make_header(types, u.t_ns, u.frame_id),
        ids=types.sequence(ids, np.uint64),
        poses=[pose_msg(types, T) for T in poses],
        scales=types.sequence(scales, np.float64),
    )


def msg_to_pose_update(msg) -> PoseUpdateData:
    what = "KeyframePoseUpdate"
    ids = numeric(field(msg, "ids", what), np.uint64, f"{what}.ids")
    poses = field(msg, "poses", what)
    scales = numeric(field(msg, "scales", what), np.float64, f"{what}.scales")
    if not (len(ids) == len(poses) == len(scales)):
        raise ValueError(f"{what}: {len(ids)} ids, {len(poses)} poses, {len(scales)} scales; expected equal")
    if np.any(~np.isfinite(scales)) or np.any(scales <= 0):
        raise ValueError(f"{what}: scales must be finite and > 0, got {scales.tolist()}")
    mats = np.stack([pose_to_matrix(p, f"{what}.poses[{i}]") for i, p in enumerate(poses)]) if len(poses) else \
        np.zeros((0, 4, 4))
    return PoseUpdateData(header_stamp_ns(msg, what), ids.copy(), mats, scales.copy(), str(msg.header.frame_id))


@dataclass
class GaussianDeltaData:
    """Gaussian map changes; the N = len(added_ids) + len(changed_ids) parameter rows are for added then
    changed Gaussians: ``means`` (N, 3) m, ``rotations`` (N, 4) wxyz, ``scales`` (N, 3) m,
    ``opacities`` (N,) in [0, 1], ``colors`` (N, 3) RGB in [0, 1], ``anchor_keyframe_ids`` (N,)."""

    t_ns: int
    version: int
    added_ids: np.ndarray
    changed_ids: np.ndarray
    removed_ids: np.ndarray
    means: np.ndarray
    rotations: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray
    anchor_keyframe_ids: np.ndarray
    frame_id: str = "map"

    @property
    def num_rows(self) -> int:
        return len(self.added_ids) + len(self.changed_ids)


def _check_gaussian_rows(n: int, means, rotations, scales, opacities, colors, anchors, what):
    shapes = {"means": (means, 3), "rotations": (rotations, 4), "scales": (scales, 3), "opacities": (opacities, 1),
              "colors": (colors, 3), "anchor_keyframe_ids": (anchors, 1)}
    for name, (arr, width) in shapes.items():
        if np.asarray(arr).size != n * width:
            raise ValueError(
                f"{what}: {name} has {np.asarray(arr).size} values, expected {n} rows x {width} = {n * width} "
                "(N = added + changed ids)"
            )
    for name, arr in (("opacities", opacities), ("colors", colors)):
        a = np.asarray(arr, dtype=np.float64)
        if np.any(~np.isfinite(a)) or np.any(a < 0) or np.any(a > 1):
            raise ValueError(f"{what}: {name} must lie in [0, 1]")
    if np.any(np.asarray(scales) < 0):
        raise ValueError(f"{what}: scales must be >= 0 (standard deviations in m)")


def gaussian_delta_to_msg(types: MessageTypes, d: GaussianDeltaData):
    _check_gaussian_rows(d.num_rows, d.means, d.rotations, d.scales, d.opacities, d.colors,
                         d.anchor_keyframe_ids, "GaussianDelta")
    return types.new(
        "vigs_msgs/msg/GaussianDelta",
        header=make_header(types, d.t_ns, d.frame_id),
        version=int(d.version),
        added_ids=types.sequence(d.added_ids, np.uint64),
        changed_ids=types.sequence(d.changed_ids, np.uint64),
        removed_ids=types.sequence(d.removed_ids, np.uint64),
        means=types.sequence(d.means, np.float32),
        rotations=types.sequence(d.rotations, np.float32),
        scales=types.sequence(d.scales, np.float32),
        opacities=types.sequence(d.opacities, np.float32),
        colors=types.sequence(d.colors, np.float32),
        anchor_keyframe_ids=types.sequence(d.anchor_keyframe_ids, np.uint64),
    )


def msg_to_gaussian_delta(msg) -> GaussianDeltaData:
    what = "GaussianDelta"

    def seq(name, dtype):
        return numeric(field(msg, name, what), dtype, f"{what}.{name}").copy()

    added, changed, removed = (seq(n, np.uint64) for n in ("added_ids", "changed_ids", "removed_ids"))
    n = len(added) + len(changed)
    means, rotations, scales, opacities, colors = (seq(k, np.float32) for k in
                                                   ("means", "rotations", "scales", "opacities", "colors"))
    anchors = seq("anchor_keyframe_ids", np.uint64)
    _check_gaussian_rows(n, means, rotations, scales, opacities, colors, anchors, what)
    return GaussianDeltaData(
        t_ns=header_stamp_ns(msg, what),
        version=int(field(msg, "version", what)),
        added_ids=added,
        changed_ids=changed,
        removed_ids=removed,
        means=means.reshape(n, 3),
        rotations=rotations.reshape(n, 4),
        scales=scales.reshape(n, 3),
        opacities=opacities,
        colors=colors.reshape(n, 3),
        anchor_keyframe_ids=anchors,
        frame_id=str(msg.header.frame_id),
    )
