"""Time synchronisation of camera and IMU streams, with validation of the IMU stream on arrival.

Time offset convention (Kalibr's ``timeshift_cam_imu``): an image stamped ``t_cam`` was taken at IMU time
``t_imu = t_cam + time_offset_ns``. Images are released to the estimator in stamp order once the IMU buffer
reaches their IMU time, so every frame sees all IMU samples up to it.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from vigs_core.types import ImuSamples


@dataclass
class ImuBufferConfig:
    """Args:
        nominal_rate_hz: expected IMU rate (Hz), for gap detection.
        gap_factor: an interval longer than ``gap_factor`` nominal periods is reported as a gap.
        max_age_s: samples older than this behind the newest one are dropped (s).
    """

    nominal_rate_hz: float = 200.0
    gap_factor: float = 2.5
    max_age_s: float = 30.0


class ImuBuffer:
    """Time-ordered IMU samples in growable numpy arrays (slices are views, O(log N) to find).

    ``add`` rejects out-of-order and duplicated stamps (returns why) and reports gaps; ``samples`` returns what
    brackets an interval, for integration exactly to its boundaries.
    """

    def __init__(self, config: ImuBufferConfig | None = None, capacity: int = 4096) -> None:
        self.config = config or ImuBufferConfig()
        self._t = np.zeros(capacity, np.int64)
        self._v = np.zeros((capacity, 6), np.float64)  # gyro (rad/s), acc (m/s^2)
        self._lo = 0  # first live row
        self._hi = 0  # one past the last live row

    def __len__(self) -> int:
        return self._hi - self._lo

    @property
    def latest_ns(self) -> int | None:
        return int(self._t[self._hi - 1]) if len(self) else None

    @property
    def earliest_ns(self) -> int | None:
        return int(self._t[self._lo]) if len(self) else None

    def add(self, t_ns: int, gyro: np.ndarray, acc: np.ndarray) -> str | None:
        """Append one sample. Returns None if accepted without remark, else a warning text: the sample is
        dropped when out of order or duplicated, and kept when it follows a gap."""
        t_ns = int(t_ns)
        remark = None
        last = self.latest_ns
        if last is not None:
            if t_ns < last:
                return f"IMU sample at {t_ns} ns is {(last - t_ns) * 1e-6:.3f} ms older than the previous one: dropped"
            if t_ns == last:
                return f"IMU sample at {t_ns} ns duplicates the previous stamp: dropped"
            period = 1e9 / self.config.nominal_rate_hz
            if t_ns - last > self.config.gap_factor * period:
                remark = (f"IMU gap of {(t_ns - last) * 1e-6:.1f} ms before {t_ns} ns "
                          f"(nominal period {period * 1e-6:.1f} ms)")
        if self._hi == len(self._t):
            self._make_room()
        self._t[self._hi] = t_ns
        self._v[self._hi, :3] = gyro
        self._v[self._hi, 3:] = acc
        self._hi += 1
        horizon = t_ns - int(self.config.max_age_s * 1e9)
        # keep the newest sample at or before the horizon (for interpolation), drop what is older
        self._lo = max(self._lo, int(np.searchsorted(self._t[self._lo:self._hi], horizon, side="right")) - 1
                       + self._lo)
        return remark

    def _make_room(self) -> None:
        n = len(self)
        if n > len(self._t) // 2:  # grow
            t, v = np.zeros(2 * len(self._t), np.int64), np.zeros((2 * len(self._t), 6))
        else:  # compact in place
            t, v = self._t, self._v
        t[:n], v[:n] = self._t[self._lo:self._hi].copy(), self._v[self._lo:self._hi].copy()
        self._t, self._v, self._lo, self._hi = t, v, 0, n

    def covers(self, t_ns: int) -> bool:
        """True when a sample at or after ``t_ns`` has arrived."""
        return len(self) > 0 and self.latest_ns >= t_ns

    def samples(self, start_ns: int, end_ns: int) -> ImuSamples:
        """Samples in ``[start_ns, end_ns]`` plus the last one before and the first one after (when held),
        so integration can interpolate both boundaries."""
        t = self._t[self._lo:self._hi]
        lo = max(int(np.searchsorted(t, start_ns, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(t, end_ns, side="left")) + 1, len(t))
        v = self._v[self._lo + lo:self._lo + hi]
        return ImuSamples(t[lo:hi], v[:, :3], v[:, 3:])

    def all(self) -> ImuSamples:
        """Every held sample (views, valid until the next ``add``)."""
        v = self._v[self._lo:self._hi]
        return ImuSamples(self._t[self._lo:self._hi], v[:, :3], v[:, 3:])


class FrameSynchronizer:
    """Holds frames until the IMU covers them (``t_cam + time_offset_ns``), then releases them in order.

    Args:
        time_offset_ns: camera-to-IMU clock offset (see module doc).
        max_pending: frames held at most; beyond that the oldest is dropped (reported by ``push``).
        max_wait_ns: a frame waiting longer than this (measured in frame time: newest frame stamp minus its
            stamp) is released without full IMU coverage, so a dead IMU does not stall the camera.
    """

    def __init__(self, time_offset_ns: int = 0, max_pending: int = 30, max_wait_ns: int = 500_000_000) -> None:
        self.time_offset_ns = int(time_offset_ns)
        self.max_pending = int(max_pending)
        self.max_wait_ns = int(max_wait_ns)
        self._pending: deque[tuple[int, Any]] = deque()

    def __len__(self) -> int:
        return len(self._pending)

    def push(self, t_cam_ns: int, payload: Any) -> str | None:
        """Queue a frame; returns a warning text if it is out of order (dropped) or the queue overflowed."""
        if self._pending and t_cam_ns <= self._pending[-1][0]:
            return f"image at {t_cam_ns} ns is not newer than the previous one ({self._pending[-1][0]} ns): dropped"
        self._pending.append((int(t_cam_ns), payload))
        if len(self._pending) > self.max_pending:
            t_old, _ = self._pending.popleft()
            return f"{self.max_pending} images wait for IMU data: dropped the oldest ({t_old} ns)"
        return None

    def release(self, imu: ImuBuffer) -> list[tuple[int, Any, bool]]:
        """Frames ready for the estimator: ``(t_imu_ns, payload, imu_complete)`` in stamp order."""
        out = []
        newest = self._pending[-1][0] if self._pending else 0
        while self._pending:
            t_cam, payload = self._pending[0]
            t_imu = t_cam + self.time_offset_ns
            complete = imu.covers(t_imu)
            if not complete and newest - t_cam < self.max_wait_ns:
                break
            self._pending.popleft()
            out.append((t_imu, payload, complete))
        return out
