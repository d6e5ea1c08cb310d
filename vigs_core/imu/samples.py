"""IMU sample-stream hygiene and the measurement sequence integrated between two stamps.

Signal model: between two consecutive samples the angular velocity and the specific force vary
linearly. Integration between two arbitrary stamps ``t0 < t1`` (keyframe stamps never coincide with
IMU samples) runs over the grid ``t0, (samples strictly inside (t0, t1)), t1``; the boundary values
are linearly interpolated from the neighbouring samples, and each grid interval ``[t_k, t_k+1]`` is
given the mean of the linear model over it (the average of its two end values). The result is a
piecewise-constant measurement sequence ``(dt_k, w_k, a_k)`` that every integrator in
``vigs_core.imu`` consumes (and that can be fed unchanged to other implementations, e.g. GTSAM).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from vigs_core.types import ImuSamples


class ImuDataWarning(UserWarning):
    """Issued for IMU streams with gaps, out-of-order or duplicated stamps."""


@dataclass
class StreamDefects:
    """Defects of an IMU stamp sequence.

    Attributes:
        out_of_order: number of stamps smaller than their predecessor (recorded order).
        duplicates: number of samples whose stamp another sample already has.
        gaps: (G, 2) int64 ``(start_ns, end_ns)`` of intervals longer than ``gap_factor`` nominal periods.
        nominal_period_ns: the period the gaps were judged against (ns).
    """

    out_of_order: int
    duplicates: int
    gaps: np.ndarray
    nominal_period_ns: float

    @property
    def clean(self) -> bool:
        return self.out_of_order == 0 and self.duplicates == 0 and len(self.gaps) == 0


def find_stream_defects(t_ns: np.ndarray, rate_hz: float | None = None, gap_factor: float = 1.5) -> StreamDefects:
    """Count out-of-order and duplicated stamps (in recorded order) and list gaps (in stamp order).

    Args:
        t_ns: (N,) int64 stamps as recorded.
        rate_hz: nominal rate (Hz); ``None`` uses the median positive stamp difference.
        gap_factor: an interval longer than ``gap_factor`` nominal periods is a gap.
    """
    t_ns = np.asarray(t_ns, dtype=np.int64)
    step = np.diff(t_ns)
    increasing = bool((step > 0).all())
    t_sorted = t_ns if increasing else np.unique(t_ns)  # gaps are judged on the sorted, de-duplicated stamps
    positive = step if increasing else np.diff(t_sorted)
    if rate_hz is not None:
        period = 1e9 / float(rate_hz)
    elif len(positive):
        period = float(np.median(positive))
    else:
        period = float("nan")
    is_gap = positive > gap_factor * period
    gaps = np.stack((t_sorted[:-1][is_gap], t_sorted[1:][is_gap]), axis=1)
    out_of_order = 0 if increasing else int((step < 0).sum())
    return StreamDefects(out_of_order, len(t_ns) - len(t_sorted), gaps.astype(np.int64), period)


def ordered_samples(imu: ImuSamples) -> ImuSamples:
    """``imu`` itself when its stamps increase strictly and its values are finite, else :func:`sanitize_samples` of
    it (with warnings)."""
    finite = np.isfinite(imu.gyro).all() and np.isfinite(imu.acc).all()
    if not finite or (len(imu) > 1 and np.any(np.diff(imu.t_ns) <= 0)):
        return sanitize_samples(imu)
    return imu


def sanitize_samples(imu: ImuSamples, rate_hz: float | None = None, gap_factor: float = 1.5) -> ImuSamples:
    """Return the finite samples sorted by stamp with repeated stamps dropped (first kept), warning on every defect.

    Issues :class:`ImuDataWarning` for samples with a non-finite value (dropped), out-of-order stamps, duplicated
    stamps and gaps longer than ``gap_factor`` nominal periods (integration bridges a gap with the linear signal
    model, which is only as good as the motion is smooth).
    """
    finite = np.isfinite(imu.gyro).all(axis=1) & np.isfinite(imu.acc).all(axis=1)
    if not finite.all():
        warnings.warn(f"IMU stream has {int((~finite).sum())} sample(s) with a non-finite value; dropped",
                      ImuDataWarning, stacklevel=2)
        imu = ImuSamples(imu.t_ns[finite], imu.gyro[finite], imu.acc[finite])
    defects = find_stream_defects(imu.t_ns, rate_hz, gap_factor)
    if defects.out_of_order:
        warnings.warn(f"IMU stream has {defects.out_of_order} out-of-order stamp(s); samples are re-sorted",
                      ImuDataWarning, stacklevel=2)
    order = np.argsort(imu.t_ns, kind="stable")
    t = imu.t_ns[order]
    keep = np.concatenate(([True], np.diff(t) != 0)) if len(t) else np.zeros(0, bool)
    n_dup = int((~keep).sum())
    if n_dup:
        warnings.warn(f"IMU stream has {n_dup} duplicated stamp(s); the first sample of each is kept",
                      ImuDataWarning, stacklevel=2)
    out = ImuSamples(t[keep], imu.gyro[order][keep], imu.acc[order][keep])
    _warn_gaps(out.t_ns, rate_hz, gap_factor)
    return out


def _warn_gaps(t_ns: np.ndarray, rate_hz: float | None, gap_factor: float) -> None:
    defects = find_stream_defects(t_ns, rate_hz, gap_factor)
    if len(defects.gaps):
        longest = int(np.max(defects.gaps[:, 1] - defects.gaps[:, 0]))
        warnings.warn(
            f"IMU stream has {len(defects.gaps)} gap(s) longer than {gap_factor} nominal periods "
            f"({defects.nominal_period_ns * 1e-6:.3f} ms); the longest is {longest * 1e-6:.3f} ms, "
            f"starting at {int(defects.gaps[0, 0])} ns",
            ImuDataWarning, stacklevel=3,
        )


def _interpolate(t_ns: np.ndarray, values: np.ndarray, query_ns: int) -> np.ndarray:
    """Linear interpolation of (N, C) ``values`` at one stamp inside ``[t_ns[0], t_ns[-1]]``."""
    k = int(np.clip(np.searchsorted(t_ns, query_ns, side="right") - 1, 0, len(t_ns) - 2))
    alpha = float(query_ns - t_ns[k]) / float(t_ns[k + 1] - t_ns[k])
    return values[k] + alpha * (values[k + 1] - values[k])


def interval_measurements(
    imu: ImuSamples, t0_ns: int, t1_ns: int, rate_hz: float | None = None, gap_factor: float = 1.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The piecewise-constant measurement sequence integrated from ``t0_ns`` to ``t1_ns`` (see module doc).

    The samples bracketing the interval must be strictly increasing and finite; when they are not, the stream is
    sanitised (:func:`sanitize_samples`, with a warning) and used sorted, without the non-finite samples. Gaps
    inside the bracket warn.

    Args:
        imu: samples covering ``[t0_ns, t1_ns]`` (a sample at or before ``t0`` and at or after ``t1``).
        t0_ns, t1_ns: integration bounds (ns), ``t0_ns < t1_ns``.
        rate_hz: nominal rate for gap detection (``None``: median sample spacing).

    Returns:
        grid_ns (K+1,) int64 grid stamps, dt (K,) seconds, gyro (K, 3) rad/s, acc (K, 3) m/s^2.
    """
    t0_ns, t1_ns = int(t0_ns), int(t1_ns)
    if t1_ns <= t0_ns:
        raise ValueError(f"integration interval must have t1 > t0, got t0={t0_ns} ns, t1={t1_ns} ns")
    if len(imu) < 2:
        raise ValueError(f"need at least 2 IMU samples to integrate, got {len(imu)}")
    t = imu.t_ns
    lo = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
    hi = min(int(np.searchsorted(t, t1_ns, side="left")) + 1, len(t))
    disordered = np.any(np.diff(t[max(lo - 1, 0):hi + 1]) <= 0)   # the bracket and one sample either side
    if disordered or not (np.isfinite(imu.gyro[lo:hi]).all() and np.isfinite(imu.acc[lo:hi]).all()):
        imu = sanitize_samples(imu, rate_hz, gap_factor)
        t = imu.t_ns
        lo = max(int(np.searchsorted(t, t0_ns, side="right")) - 1, 0)
        hi = min(int(np.searchsorted(t, t1_ns, side="left")) + 1, len(t))
    else:
        _warn_gaps(t[lo:hi], rate_hz, gap_factor)
    if t0_ns < t[0] or t1_ns > t[-1]:
        raise ValueError(
            f"IMU samples cover [{int(t[0])}, {int(t[-1])}] ns but integration was asked over "
            f"[{t0_ns}, {t1_ns}] ns; the interval must lie inside the samples"
        )
    sub_t = t[lo:hi]
    sub_v = np.concatenate((imu.gyro[lo:hi], imu.acc[lo:hi]), axis=1)
    inner = (sub_t > t0_ns) & (sub_t < t1_ns)
    grid_ns = np.concatenate(([t0_ns], sub_t[inner], [t1_ns])).astype(np.int64)
    values = np.concatenate(
        (_interpolate(sub_t, sub_v, t0_ns)[None], sub_v[inner], _interpolate(sub_t, sub_v, t1_ns)[None])
    )
    mean = 0.5 * (values[:-1] + values[1:])
    dt = np.diff(grid_ns).astype(np.float64) * 1e-9
    return grid_ns, dt, mean[:, :3], mean[:, 3:]
