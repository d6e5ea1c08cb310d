"""Simulated visual-inertial sequences: a motion, an IMU stream, a scene around the motion, rendered
and degraded camera frames with exact depth.

Motion sources (see :func:`hybrid_source`, :func:`synthetic_source`):

* *hybrid*: recorded ground truth + the recorded IMU (e.g. EuRoC). Image poses are the ground truth
  interpolated at the image stamps (SLERP / linear), camera poses ``T_WC = T_WB T_BS``. Position jumps of the
  tracking system are removed first (:func:`repair_position_jumps`): the images would show a jump the IMU never
  felt (EuRoC MH_03: 2-8.5 cm steps within 5 ms, i.e. 9-17 m/s in a 1-2 m/s flight).
* *synthetic*: a differentiable motion (a spline through a recorded trajectory, or a procedural one)
  with IMU synthesised from it (:mod:`vigs_core.sim.imu_synthesis`); the ground truth is sampled from
  the same motion at the IMU stamps, with velocities and the synthesised biases.

Frame ``k`` has stamp ``t_0 + round(k * 1e9 / rate)``; degradations select and alter frames
(:mod:`vigs_core.sim.degrade`). Everything is a deterministic function of the inputs and seeds.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import warnings

import numpy as np
import torch
from numpy.lib.stride_tricks import sliding_window_view

from vigs_core.camera import CameraModel
from vigs_core.geometry import matrix_to_quat
from vigs_core.sim.degrade import DegradeConfig, degrade_image, select_frames, subframe_offsets_ns
from vigs_core.sim.imu_synthesis import imu_stamps, synthesize_imu
from vigs_core.sim.render import RenderConfig, Renderer
from vigs_core.sim.scene import Scene, SceneConfig, build_room_scene
from vigs_core.sim.trajectory import ProceduralMotion, SampledMotion, SplineMotion
from vigs_core.types import ImuNoise, ImuSamples, Trajectory


@dataclass
class MotionSource:
    """Where poses, IMU and ground truth come from.

    Attributes:
        motion: object with ``poses(t_ns) -> (R_WB (N, 3, 3), p_WB (N, 3))`` and ``start_ns``/``end_ns``.
        imu: IMU samples covering the motion.
        groundtruth: body trajectory written as ground truth.
        kind: "hybrid" or "synthetic".
    """

    motion: SampledMotion | SplineMotion | ProceduralMotion
    imu: ImuSamples
    groundtruth: Trajectory
    kind: str


def repair_position_jumps(traj: Trajectory, threshold_m: float = 0.01, half_window: int = 5
                          ) -> tuple[Trajectory, np.ndarray]:
    """Remove the jumps of a recorded trajectory's positions (tracker glitches); returns the repaired trajectory
    and the indices ``k`` of the replaced increments ``p[k+1] - p[k]``.

    Increment ``d_k = p_{k+1} - p_k`` is a jump when it differs from the component-wise median ``m_k`` of the
    increments ``d_{k-h} .. d_{k+h}`` by more than ``threshold_m``; it is replaced by ``m_k dt_k / dt_m`` (the
    local median velocity over its own interval, ``dt_m`` the median interval of the window) and the positions
    re-integrated from ``p_0``, so a step leaves no offset and a spike (out and back) disappears. For real
    motion the deviation is about ``a dt h dt``: 1 cm at 200 Hz and h = 5 would need 16,000 m/s^2. Rotations,
    velocities and biases are kept."""
    if len(traj) < 2 * half_window + 2:
        return traj, np.zeros(0, dtype=np.int64)
    d = np.diff(traj.position, axis=0)
    dt = np.diff(traj.t_ns).astype(np.float64)
    h = half_window
    window = sliding_window_view(np.pad(d / dt[:, None], ((h, h), (0, 0)), mode="edge"), 2 * h + 1, axis=0)
    velocity = np.median(window, axis=-1)                                    # (N-1, 3) per ns
    jumps = np.flatnonzero(np.linalg.norm(d - velocity * dt[:, None], axis=1) > threshold_m)
    if len(jumps) == 0:
        return traj, jumps
    d[jumps] = velocity[jumps] * dt[jumps, None]
    position = np.concatenate((traj.position[:1], traj.position[0] + np.cumsum(d, axis=0)))
    return (Trajectory(traj.t_ns, position, traj.quat_wxyz, traj.velocity, traj.bias_gyro, traj.bias_acc),
            jumps)


def hybrid_source(groundtruth: Trajectory, imu: ImuSamples, jump_threshold_m: float | None = 0.01) -> MotionSource:
    """Recorded ground truth (body frame) and recorded IMU on the same clock; ground-truth position jumps above
    ``jump_threshold_m`` are repaired (:func:`repair_position_jumps`, with a warning; None keeps them)."""
    if len(imu) == 0 or len(groundtruth) < 2:
        raise ValueError(f"hybrid_source: needs IMU samples and >= 2 poses, got {len(imu)} and {len(groundtruth)}")
    overlap = min(groundtruth.t_ns[-1], imu.t_ns[-1]) - max(groundtruth.t_ns[0], imu.t_ns[0])
    if overlap <= 0:
        raise ValueError(
            "hybrid_source: the IMU and the ground truth do not overlap in time "
            f"(IMU {imu.t_ns[0]}..{imu.t_ns[-1]} ns, ground truth {groundtruth.t_ns[0]}..{groundtruth.t_ns[-1]} ns)"
        )
    if jump_threshold_m is not None:
        groundtruth, jumps = repair_position_jumps(groundtruth, jump_threshold_m)
        if len(jumps):
            t_s = (groundtruth.t_ns[jumps] - groundtruth.t_ns[0]) * 1e-9
            warnings.warn(f"hybrid_source: repaired {len(jumps)} ground-truth position jumps > {jump_threshold_m} m "
                          f"(at {', '.join(f'{t:.2f}' for t in t_s)} s from the start)", stacklevel=2)
    return MotionSource(SampledMotion(groundtruth), imu, groundtruth, "hybrid")


def synthetic_source(
    motion: SplineMotion | ProceduralMotion,
    noise: ImuNoise,
    imu_rate_hz: float = 200.0,
    seed: int = 0,
    noise_free: bool = False,
) -> MotionSource:
    """A differentiable motion with synthesised IMU (noise and bias walks from ``noise`` unless noise-free)."""
    t_ns = imu_stamps(motion.start_ns, motion.end_ns, imu_rate_hz)
    synth = synthesize_imu(motion, t_ns, None if noise_free else noise, seed)
    state = motion.evaluate(t_ns)
    quat = matrix_to_quat(torch.from_numpy(state.rotation)).numpy()
    gt = Trajectory(t_ns, state.position, quat, state.velocity, synth.bias_gyro, synth.bias_acc)
    return MotionSource(motion, synth.imu, gt, "synthetic")


@dataclass(frozen=True)
class SimConfig:
    """What to render from a motion source.

    Args:
        rate_hz: camera frame rate (Hz).
        start_s: first frame this long after the start of the motion (s).
        duration_s: length of the sequence (s); None = until the motion ends.
        with_depth: produce a depth map per frame.
        scene_seed: seed of the scene layout and textures.
        render: renderer settings.
        scene: scene layout settings.
        degrade: degradations and frame selection.
    """

    rate_hz: float = 20.0
    start_s: float = 0.0
    duration_s: float | None = None
    with_depth: bool = True
    scene_seed: int = 0
    render: RenderConfig = field(default_factory=RenderConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    degrade: DegradeConfig = field(default_factory=DegradeConfig)


@dataclass
class SimFrame:
    """One output frame.

    Attributes:
        index: index in the full (unstrided) frame sequence.
        t_ns: stamp (ns).
        image: (H, W) or (H, W, 3) uint8.
        depth: (H, W) float32 depth Z (m) at the stamp's pose, or None.
        T_WC: (4, 4) camera pose at the stamp.
    """

    index: int
    t_ns: int
    image: np.ndarray
    depth: np.ndarray | None
    T_WC: np.ndarray


class SimSequence:
    """A simulated sequence, rendered lazily frame by frame.

    Args:
        source: motion, IMU and ground truth.
        camera: camera model of the output images.
        T_BS: (4, 4) camera pose in the body (IMU) frame.
        config: frame timing, scene, rendering and degradations.
        scene: a prepared scene; by default a room around the camera path (:func:`build_room_scene`).
        photos: optional grey photographs (H, W) used as textures on some surfaces.
    """

    def __init__(
        self,
        source: MotionSource,
        camera: CameraModel,
        T_BS: np.ndarray,
        config: SimConfig = SimConfig(),
        scene: Scene | None = None,
        photos: list[np.ndarray] | tuple[np.ndarray, ...] = (),
    ) -> None:
        self.source = source
        self.camera = camera
        self.T_BS = np.asarray(T_BS, dtype=np.float64)
        self.config = config
        offsets = subframe_offsets_ns(config.degrade)
        self.subframe_offsets_ns = offsets
        lo = max(source.motion.start_ns, int(source.imu.t_ns[0]))
        hi = min(source.motion.end_ns, int(source.imu.t_ns[-1]))
        first = lo + int(round(config.start_s * 1e9))
        last = hi if config.duration_s is None else min(hi, first + int(round(config.duration_s * 1e9)))
        if last <= first:
            raise ValueError(
                f"SimSequence: empty time range: start {config.start_s} s and duration {config.duration_s} s leave "
                f"nothing of the motion's {(hi - lo) * 1e-9:.3f} s"
            )
        all_stamps = imu_stamps(first, last, config.rate_hz)
        self.all_frame_t_ns = all_stamps
        self.kept = select_frames(len(all_stamps), config.degrade)
        self.frame_t_ns = all_stamps[self.kept]
        # IMU and ground truth from one sample period before the first frame to one after the last
        imu_period = int(np.median(np.diff(source.imu.t_ns))) if len(source.imu) > 1 else 0
        self.imu = source.imu.slice(first - imu_period, last + imu_period + 1)
        gt = source.groundtruth
        gt_period = int(np.median(np.diff(gt.t_ns))) if len(gt) > 1 else 0
        keep_gt = (gt.t_ns >= first - gt_period) & (gt.t_ns <= last + gt_period)
        self.groundtruth = Trajectory(
            gt.t_ns[keep_gt],
            gt.position[keep_gt],
            gt.quat_wxyz[keep_gt],
            *(None if x is None else x[keep_gt] for x in (gt.velocity, gt.bias_gyro, gt.bias_acc)),
        )
        cam_positions = self.camera_poses(all_stamps)[:, :3, 3]
        self.scene = scene if scene is not None else build_room_scene(cam_positions, config.scene_seed, config.scene)
        self.renderer = Renderer(self.scene, camera, config.render, photos)

    def camera_poses(self, t_ns: np.ndarray) -> np.ndarray:
        """(N, 4, 4) camera poses ``T_WC = T_WB T_BS`` at stamps ``t_ns`` (N,)."""
        rot, pos = self.source.motion.poses(np.asarray(t_ns, dtype=np.int64))
        T_WB = np.tile(np.eye(4), (len(rot), 1, 1))
        T_WB[:, :3, :3] = rot
        T_WB[:, :3, 3] = pos
        return T_WB @ self.T_BS

    def __len__(self) -> int:
        return len(self.frame_t_ns)

    @property
    def duration_s(self) -> float:
        return float(self.all_frame_t_ns[-1] - self.all_frame_t_ns[0]) * 1e-9

    def path_length(self) -> float:
        """Length (m) of the body path over the frames' time span (from the ground-truth samples)."""
        t = self.all_frame_t_ns
        _, pos = self.source.motion.poses(np.linspace(t[0], t[-1], max(2, 10 * len(t))).astype(np.int64))
        return float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum())

    def render_frame(self, index: int) -> SimFrame:
        """Render and degrade frame ``index`` of the full (unstrided) sequence."""
        t_ns = int(self.all_frame_t_ns[index])
        T_WC = self.camera_poses(np.array([t_ns]))[0]
        with_depth = self.config.with_depth
        if len(self.subframe_offsets_ns) == 1:
            out = self.renderer.render(T_WC, with_depth=with_depth)
            image, depth = out.image, (out.depth if with_depth else None)
        else:
            # average of sub-frame renders over the exposure; depth at the stamp's pose
            # sub-frame stamps are clamped to the motion's span (frame stamps do not depend on the exposure)
            sub_ns = np.clip(t_ns + self.subframe_offsets_ns, self.source.motion.start_ns, self.source.motion.end_ns)
            poses = self.camera_poses(sub_ns)
            image = sum(self.renderer.render(T, with_depth=False).image for T in poses) / len(poses)
            depth = self.renderer.depth(T_WC) if with_depth else None
        t_rel = (t_ns - int(self.all_frame_t_ns[0])) * 1e-9
        return SimFrame(index, t_ns, degrade_image(image, index, t_rel, self.config.degrade), depth, T_WC)

    def frames(self) -> Iterator[SimFrame]:
        """The kept frames in time order."""
        for index in self.kept:
            yield self.render_frame(int(index))


def euroc_cam0_calibration() -> "CameraCalibration":
    """The EuRoC MAV cam0 calibration (752x480, radtan, 20 Hz, ``T_BS`` of the VI-Sensor; Burri et al.,
    IJRR 2016), the simulator's default camera so that it needs no file from outside the repository."""
    from vigs_core.io import CameraCalibration

    camera = CameraModel(
        752, 480, 458.654, 457.296, 367.215, 248.375, "radtan", (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    )
    T_BS = np.array(
        [
            [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
            [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
            [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    return CameraCalibration(camera, T_BS, 20.0)
