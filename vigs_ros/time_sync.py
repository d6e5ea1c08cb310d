"""Time synchronisation of camera and IMU streams, and the count of frames missing from a stream.

Time offset convention (Kalibr's ``timeshift_cam_imu``): an image stamped ``t_cam`` was taken at IMU time
``t_imu = t_cam + time_offset_ns``. Images are released to the estimator in stamp order once the IMU buffer
(:class:`vigs_core.imu.buffer.ImuBuffer`, which validates the IMU stream on arrival) reaches their IMU time, so
every frame sees all IMU samples up to it.
"""
from __future__ import annotations

from collections import deque
from typing import Any

from vigs_core.imu.buffer import ImuBuffer


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

    def push(self, t_cam_ns: int, payload: Any) -> list[tuple[int, Any]]:
        """Queue a frame; returns the frames dropped: this one when it is not newer than the last queued one,
        or the oldest when the queue overflowed (the caller says why: IMU late, or tracking behind)."""
        if self._pending and t_cam_ns <= self._pending[-1][0]:
            return [(int(t_cam_ns), payload)]
        self._pending.append((int(t_cam_ns), payload))
        if len(self._pending) > self.max_pending:
            return [self._pending.popleft()]
        return []

    def release(self, imu: ImuBuffer | None) -> list[tuple[int, Any, bool]]:
        """Frames ready for the estimator: ``(t_imu_ns, payload, imu_complete)`` in stamp order (without an IMU,
        ``imu`` None, every queued frame)."""
        out = []
        newest = self._pending[-1][0] if self._pending else 0
        while self._pending:
            t_cam, payload = self._pending[0]
            t_imu = t_cam + self.time_offset_ns
            complete = imu is None or imu.covers(t_imu)
            if not complete and newest - t_cam < self.max_wait_ns:
                break
            self._pending.popleft()
            out.append((t_imu, payload, complete))
        return out


class StampGaps:
    """Counts the frames missing from a stream between consecutive stamps: an interval of ``r`` typical
    intervals (the median of the last ``window`` ones) with ``r > gap_factor`` lost ``round(r) - 1`` frames
    (images a subscriber's queue or the transport dropped before the node saw them)."""

    def __init__(self, window: int = 50, gap_factor: float = 1.5) -> None:
        self.gap_factor = gap_factor
        self._intervals: deque[int] = deque(maxlen=window)
        self._last: int | None = None

    def add(self, t_ns: int) -> int:
        """The next stamp; returns how many frames are missing before it (0 for a stamp not after the last)."""
        last, self._last = self._last, max(int(t_ns), self._last or int(t_ns))
        if last is None or t_ns <= last:
            return 0
        dt = int(t_ns) - last
        typical = sorted(self._intervals)[len(self._intervals) // 2] if len(self._intervals) >= 5 else None
        self._intervals.append(dt)
        if typical is None or dt <= self.gap_factor * typical:
            return 0
        return max(int(round(dt / typical)) - 1, 0)
