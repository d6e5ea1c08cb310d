"""A growing, time-ordered IMU record: what the estimator reads while samples stream in.

:class:`ImuBuffer` keeps the samples in growable NumPy arrays; :meth:`ImuBuffer.all` and
:meth:`ImuBuffer.samples` return :class:`~vigs_core.types.ImuSamples` views, so the preintegration code reads a
streamed record exactly as it reads a whole recording. ``add`` validates each sample on arrival: a sample
with a non-finite value (a driver's invalid reading) is rejected before it can reach a preintegration, a sample
that is not newer than the previous one is rejected (never re-sorted into the past), a longer interval than
``gap_factor`` nominal periods is reported as a gap. A sample more than ``max_jump_s`` after the previous one
is held until the next sample tells a gap (it follows the held one: both are kept) from an outlier stamp
(it returns to the old time base: the held sample is rejected), so one sample stamped far in the future cannot
make every later sample look out of order. Views are valid until the next ``add``: one thread
writes and reads (the node's tracking thread, or ``vigs run``'s loop).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vigs_core.imu.samples import ordered_samples
from vigs_core.types import ImuSamples


@dataclass
class ImuBufferConfig:
    """Args:
        nominal_rate_hz: expected IMU rate (Hz), for gap detection.
        gap_factor: an interval longer than ``gap_factor`` nominal periods is reported as a gap.
        max_age_s: samples older than this behind the newest one are dropped (s); None keeps all (an offline
            run that reports every frame's velocity at the end needs the whole record).
        max_jump_s: a sample this much (s) after the previous one is held until the next one confirms it
            (module docstring).
    """

    nominal_rate_hz: float = 200.0
    gap_factor: float = 2.5
    max_age_s: float | None = 30.0
    max_jump_s: float = 0.5


class ImuBuffer:
    """Time-ordered IMU samples (module docstring); O(1) amortised append, O(log N) interval look-up."""

    def __init__(self, config: ImuBufferConfig | None = None, capacity: int = 4096) -> None:
        self.config = config or ImuBufferConfig()
        self._t = np.zeros(capacity, np.int64)
        self._v = np.zeros((capacity, 6), np.float64)  # gyro (rad/s), acc (m/s^2)
        self._lo = 0  # first live row
        self._hi = 0  # one past the last live row
        self._held: tuple[int, np.ndarray, np.ndarray] | None = None   # a sample far ahead, awaiting the next

    @classmethod
    def of(cls, samples: "ImuBuffer | ImuSamples") -> "ImuBuffer":
        """``samples`` when already a buffer, else a buffer holding the whole recording ``samples`` (kept whole:
        ``max_age_s`` None; disordered or repeated stamps are sanitised with a warning,
        :func:`vigs_core.imu.samples.ordered_samples`)."""
        if isinstance(samples, ImuBuffer):
            return samples
        samples = ordered_samples(samples)
        t = np.asarray(samples.t_ns, dtype=np.int64)
        buf = cls(ImuBufferConfig(max_age_s=None), capacity=max(len(t), 16))
        buf._t[:len(t)] = t
        buf._v[:len(t), :3], buf._v[:len(t), 3:] = samples.gyro, samples.acc
        buf._hi = len(t)
        return buf

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
        dropped when not finite, out of order or duplicated, kept when it follows a gap, held when far ahead
        (module docstring)."""
        t_ns = int(t_ns)
        if not (np.isfinite(gyro).all() and np.isfinite(acc).all()):
            return f"IMU sample at {t_ns} ns has a non-finite value: dropped"
        remarks = []
        if self._held is not None:
            held, self._held = self._held, None
            if t_ns > held[0]:    # the stream goes on after the jump: it was a gap
                remarks.append(self._append(*held))
            else:
                remarks.append(f"IMU sample at {held[0]} ns was {(held[0] - self.latest_ns) * 1e-9:.3f} s ahead of "
                               f"the stream, which went on at {t_ns} ns: rejected as an outlier stamp")
        last = self.latest_ns
        if last is not None and t_ns - last > self.config.max_jump_s * 1e9:
            self._held = (t_ns, np.array(gyro, dtype=np.float64), np.array(acc, dtype=np.float64))
            remarks.append(f"IMU sample at {t_ns} ns is {(t_ns - last) * 1e-9:.3f} s after the previous one: held "
                           "until the next sample tells a gap from an outlier stamp")
        else:
            remarks.append(self._append(t_ns, gyro, acc))
        remarks = [r for r in remarks if r]
        return "; ".join(remarks) if remarks else None

    def _append(self, t_ns: int, gyro: np.ndarray, acc: np.ndarray) -> str | None:
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
        if self.config.max_age_s is not None:
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

    def covers_interval(self, start_ns: int, end_ns: int, max_gap_ns: int | None = None) -> bool:
        """True when samples bracket ``[start_ns, end_ns]`` and, with ``max_gap_ns``, no two consecutive samples
        over it (the bracketing ones included) are further apart than that."""
        if len(self) < 2 or self.earliest_ns > start_ns or self.latest_ns < end_ns:
            return False
        return max_gap_ns is None or self.gap_free_from(start_ns, end_ns, max_gap_ns) == start_ns

    def gap_free_from(self, start_ns: int, end_ns: int, max_gap_ns: int) -> int | None:
        """The earliest time ``t >= start_ns`` such that the samples cover ``[t, end_ns]`` with no two consecutive
        samples over it further apart than ``max_gap_ns`` (:meth:`covers_interval`): ``start_ns`` when that
        whole interval is covered, else the stamp of the sample that ends the last gap (or of the oldest sample
        held); None when no sample at or after ``end_ns`` is held yet. A window of keyframes can then keep the
        part after an IMU gap instead of waiting for the gap to leave it."""
        if len(self) < 2 or self.latest_ns < end_ns:
            return None
        t = self.samples(start_ns, end_ns).t_ns
        gaps = np.nonzero(np.diff(t) > max_gap_ns)[0]
        return max(int(t[gaps[-1] + 1]) if len(gaps) else int(t[0]), int(start_ns))

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
