"""The streaming front door of the odometry: IMU samples and images go in as they arrive.

:class:`OdometryStream` is what both ``vigs run`` and the ROS frontend node drive, the same way: ``add_imu`` for
every IMU sample, ``add_image`` for every image the caller decides to process, in stamp order. It owns the
preprocessing (undistortion + resize to the processing resolution, :class:`Preprocessor`), the growing IMU record
(:class:`~vigs_core.imu.buffer.ImuBuffer`, validated on arrival) and the core odometry: visual-inertial
(:class:`~vigs_core.vio.odometry.VisualInertialOdometry`) when the settings and the input have an IMU, else the
vision-only :class:`~vigs_core.frontend.odometry.DenseOdometry`. It never needs the recording up front.

A live caller that falls behind processes the newest frame and skips the rest; it tells the stream with
``skip`` (counted and kept, so a replay can reproduce the same run with the same skips). The estimator bridges a
skipped frame with the IMU: the next frame is predicted from the latest keyframe by preintegration over the whole
gap (once metric), or by constant velocity over time (before).
"""
from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from vigs_core.camera import CameraModel, Undistorter, inner_pinhole
from vigs_core.frontend.odometry import DenseOdometry
from vigs_core.imu.buffer import ImuBuffer, ImuBufferConfig
from vigs_core.solver import Intrinsics
from vigs_core.system.config import PipelineConfig
from vigs_core.types import ImuNoise
from vigs_core.vio.odometry import VisualInertialOdometry

IMU_HISTORY_S = 120.0   # IMU kept behind the newest sample by the streaming callers (OdometryStream), s


class Preprocessor:
    """Undistorts to a pinhole camera and resizes to the processing resolution in one remap.

    Attributes:
        camera: the pinhole camera of the output images.
    """

    def __init__(self, src: CameraModel, width: int, height: int) -> None:
        self._undistorter = None
        if src.distortion != "none":
            self.camera = inner_pinhole(src, width, height)
            self._undistorter = Undistorter(src, self.camera)
        else:
            self.camera = src.resized(width, height) if (src.width, src.height) != (width, height) else src

    def __call__(self, image: np.ndarray) -> np.ndarray:
        if self._undistorter is not None:
            return self._undistorter.remap(image)
        if image.shape != (self.camera.height, self.camera.width):
            return cv2.resize(image, (self.camera.width, self.camera.height), interpolation=cv2.INTER_AREA)
        return image


class OdometryStream:
    """Streaming odometry (module docstring).

    Args:
        camera: the input camera (any distortion model).
        config: pipeline settings (processing size, threads, odometry, IMU fusion).
        T_bc: (4, 4) camera pose in the body (IMU) frame.
        imu_noise: IMU noise densities; None: no IMU, the odometry is vision-only.
        imu_history_s: IMU kept behind the newest sample (s): what the estimator reads lies within the window
            and the initialisation's keyframes, and a frame's velocity increment is kept when its keyframe leaves
            the window (:meth:`VisualInertialOdometry.frame_velocities`); None keeps all.
    """

    def __init__(self, camera: CameraModel, config: PipelineConfig, T_bc: np.ndarray | None = None,
                 imu_noise: ImuNoise | None = None, imu_history_s: float | None = IMU_HISTORY_S) -> None:
        torch.set_num_threads(config.torch_threads)
        cv2.setNumThreads(config.torch_threads)
        self.config = config
        self.pre = Preprocessor(camera, config.width, config.height)
        cam = self.camera = self.pre.camera
        intr = Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy)
        self.imu: ImuBuffer | None = None
        if imu_noise is not None and config.imu.enabled:
            self.imu = ImuBuffer(ImuBufferConfig(imu_noise.rate_hz, max_age_s=imu_history_s))
            self.odometry: DenseOdometry = VisualInertialOdometry(
                intr, cam.width, cam.height, self.imu, imu_noise, np.eye(4) if T_bc is None else T_bc,
                config.odometry, config.imu)
        else:
            self.odometry = DenseOdometry(intr, cam.width, cam.height, config.odometry)
        self.frames_in = 0          # frames given to add_image / add_prepared (strided ones included)
        self.skipped_ns: list[int] = []

    @property
    def inertial(self) -> bool:
        """True when the odometry fuses the IMU."""
        return isinstance(self.odometry, VisualInertialOdometry)

    @property
    def metric(self) -> bool:
        """True once the world is metric and gravity-aligned (IMU initialised)."""
        return self.inertial and self.odometry.vio.metric

    def add_imu(self, t_ns: int, gyro: np.ndarray, acc: np.ndarray) -> str | None:
        """One IMU sample (body frame, rad/s and m/s^2). Returns None when accepted without remark, else the
        reason it was dropped or the gap it follows (:meth:`ImuBuffer.add`). Ignored without IMU fusion."""
        if self.imu is None:
            return None
        return self.imu.add(t_ns, gyro, acc)

    def skip(self, t_ns: int) -> None:
        """Record a frame the caller received but did not process (it fell behind; module docstring)."""
        self.skipped_ns.append(int(t_ns))

    def prepare(self, image: np.ndarray) -> np.ndarray:
        """A grey image of the input camera undistorted and resized to the processing camera."""
        return self.pre(image)

    def add_image(self, t_ns: int, image: np.ndarray,
                  on_pose: Callable[[torch.Tensor], None] | None = None) -> torch.Tensor | None:
        """Process one grey image of the input camera (see :meth:`add_prepared`)."""
        return self.add_prepared(t_ns, self.prepare(image), on_pose)

    def takes_next(self) -> bool:
        """True when the stride lets the next image through (callers skip preparing the others)."""
        return self.frames_in % int(self.config.frame_stride) == 0

    def add_prepared(self, t_ns: int, image: np.ndarray | None,
                     on_pose: Callable[[torch.Tensor], None] | None = None) -> torch.Tensor | None:
        """Process one image already prepared (:meth:`prepare`), after the IMU samples up to its stamp.

        Every ``config.frame_stride``-th image is processed; the others are counted and ignored (``image`` may be
        None for them, :meth:`takes_next`). Returns the frame's causal world->camera pose ``T_cw`` (4, 4) or None
        (not initialised, or strided out).
        ``on_pose(T_cw)`` is called once per posed frame as soon as its tracked pose is known, before the
        keyframe work (:meth:`DenseOdometry.process`)."""
        takes = self.takes_next()
        self.frames_in += 1
        return self.odometry.process(int(t_ns), image, on_pose) if takes else None
