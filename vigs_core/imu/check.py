"""The analysis behind ``vigs imu-check``: what to verify about an IMU stream before blaming an estimator.

Reports: sample rate and timestamp jitter; gaps, out-of-order and duplicated stamps; saturation
(samples pinned at the extreme value of an axis, repeated); static segments (found in the IMU, else where the
ground truth stands still) with their gyro bias,
noise level and the noise density it implies (``std / sqrt(rate)``, to compare with the configured
white-noise density; vibration inflates it); gravity magnitude on the longest static segment (without one,
fitted to the ground-truth motion when the ground truth has biases, ``gravity_magnitude_fit``). With ground
truth: preintegration consistency, the mean normalised estimation error squared over windows,
``NEES = r^T Cov^-1 r`` of the inertial residual (rotation, velocity, position; 9 dof) evaluated at
the ground-truth states, reported as ``mean NEES / dof`` (1 for a consistent noise model). Biases come
from the ground truth when it has them, else one constant bias fitted to all windows by Gauss-Newton.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from vigs_core.geometry import quat_to_matrix, se3_from_rt
from vigs_core.imu.preintegration import preintegrate, stack_preintegrated
from vigs_core.imu.residual import GRAVITY as GRAVITY_MAGNITUDE, inertial_residual
from vigs_core.imu.samples import find_stream_defects, sanitize_samples
from vigs_core.imu.static_init import (
    MotionStillConfig,
    StaticDetectorConfig,
    detect_static_segments,
    static_initialize,
    still_segments_from_motion,
)
from vigs_core.types import ImuNoise, ImuSamples, Trajectory

NEES_CONSISTENT = (0.5, 2.0)
"""Mean NEES per degree of freedom taken as consistent: a practical band around 1 (a factor 1.4 on the standard
deviations either way), wider than the chi-square spread of a mean over tens of windows."""


@dataclass
class ImuCheckConfig:
    """Settings of :func:`check_imu`.

    Args:
        gap_factor: an interval longer than this many nominal periods is a gap.
        saturation_min_repeats: an axis extreme value counts as saturation when at least this many
            samples sit exactly on it.
        static: static-segment detector settings.
        still_from_ground_truth: with ground truth and no static segment found in the IMU, the segments where the
            ground truth stands still (:func:`~vigs_core.imu.static_init.still_segments_from_motion`).
        nees_window_s: length of the consistency windows (s).
        nees_max_windows: at most this many windows, evenly spread over the ground truth.
    """

    gap_factor: float = 1.5
    saturation_min_repeats: int = 5
    static: StaticDetectorConfig = field(default_factory=StaticDetectorConfig)
    still_from_ground_truth: MotionStillConfig = field(default_factory=MotionStillConfig)
    nees_window_s: float = 1.0
    nees_max_windows: int = 100


def _saturation(values: np.ndarray, min_repeats: int) -> dict:
    """Samples pinned at each axis' min or max (only counted when the extreme repeats >= min_repeats)."""
    pinned = np.zeros(len(values), bool)
    for axis in range(values.shape[1]):
        for extreme in (values[:, axis].max(), values[:, axis].min()):
            hit = values[:, axis] == extreme
            if hit.sum() >= min_repeats:
                pinned |= hit
    return {"samples": int(pinned.sum()), "max_abs": float(np.abs(values).max())}


def _gt_states(gt: Trajectory) -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Body poses (N,4,4) and world velocities (N,3) of a trajectory (finite differences if absent)."""
    R = quat_to_matrix(torch.as_tensor(gt.quat_wxyz))
    T = se3_from_rt(R, torch.as_tensor(gt.position))
    if gt.velocity is not None:
        vel = gt.velocity
    else:
        vel = np.gradient(gt.position, gt.t_s, axis=0)
    return T, torch.as_tensor(vel), gt.t_ns


def preintegration_consistency(
    imu: ImuSamples, gt: Trajectory, noise: ImuNoise, window_s: float = 1.0, max_windows: int = 100
) -> dict:
    """Mean NEES/dof of the inertial residual at ground-truth states over windows (see module doc)."""
    T, vel, t_ns = _gt_states(gt)
    inside = (t_ns >= imu.t_ns[0]) & (t_ns <= imu.t_ns[-1])
    idx_all = np.flatnonzero(inside)
    if len(idx_all) < 2:
        raise ValueError("ground truth and IMU do not overlap in time")
    period = float(np.median(np.diff(t_ns[idx_all])))
    step = max(int(round(window_s * 1e9 / period)), 1)
    starts = idx_all[::step]  # consecutive windows of `step` ground-truth samples
    starts = starts[starts + step <= idx_all[-1]]
    if len(starts) == 0:
        raise ValueError(f"ground truth spans less than one {window_s} s window inside the IMU data")
    if len(starts) > max_windows:
        starts = starts[np.linspace(0, len(starts) - 1, max_windows).round().astype(int)]
    i, j = starts, starts + step
    stamps = np.stack((t_ns[i], t_ns[j]), 1)
    pre = stack_preintegrated([preintegrate(imu, a, b, noise) for a, b in stamps])
    f = dict(dtype=torch.float64)
    eye4 = torch.eye(4, **f)
    if gt.bias_gyro is not None and gt.bias_acc is not None:
        b_i = torch.as_tensor(np.concatenate((gt.bias_gyro[i], gt.bias_acc[i]), 1))
        bias_source = "ground truth"
    else:
        b_i = torch.zeros(len(i), 6, **f)
        bias_source = "fitted constant"
    W = torch.linalg.inv(pre.cov[:, :9, :9])

    def evaluate(b, gravity=GRAVITY_MAGNITUDE, jacobians=True):
        return inertial_residual(pre, T[i], vel[i], b, T[j], vel[j], b, torch.eye(3, **f), torch.zeros((), **f),
                                 eye4, gravity, jacobians=jacobians)

    res = evaluate(b_i)
    if bias_source == "fitted constant":
        b = torch.zeros(6, **f)
        for _ in range(3):
            J, r = res.jacobians["bias_i"][:, :9], res.residual[:, :9]
            H = (J.transpose(-1, -2) @ W @ J).sum(0)
            g = (J.transpose(-1, -2) @ W @ r[..., None]).sum(0)[:, 0]
            b = b - torch.linalg.solve(H, g)
            b_i = b.expand(len(i), 6)
            res = evaluate(b_i)
    r = res.residual[:, :9]
    # with the ground truth's biases: the gravity magnitude that best explains the ground-truth motion (weighted
    # least squares; the residual is affine in it, so one step from a finite difference is exact up to rounding).
    # A fitted constant bias absorbs it (an accelerometer bias along a mostly level body's z is gravity).
    gravity_fit = None
    if bias_source == "ground truth":
        step = 1e-3
        d = (evaluate(b_i, GRAVITY_MAGNITUDE + step, False).residual[:, :9] - r) / step
        gravity_fit = GRAVITY_MAGNITUDE - float((d[:, None, :] @ W @ r[:, :, None]).sum()
                                                / (d[:, None, :] @ W @ d[:, :, None]).sum())
    nees = (r[:, None, :] @ W @ r[:, :, None])[:, 0, 0]
    parts = {}
    for name, sl in (("rotation", slice(0, 3)), ("velocity", slice(3, 6)), ("position", slice(6, 9))):
        Wp = torch.linalg.inv(pre.cov[:, sl, sl])
        parts[name] = float(((r[:, None, sl] @ Wp @ r[:, sl, None])[:, 0, 0] / 3).mean())
    mean = float((nees / 9).mean())
    return {
        "windows": int(len(i)),
        "window_s": float(np.median((t_ns[j] - t_ns[i]) * 1e-9)),
        "mean_nees_per_dof": mean,
        "verdict": nees_verdict(mean),
        "median_nees_per_dof": float((nees / 9).median()),
        "per_block_nees_per_dof": parts,
        "bias_source": bias_source,
        "gravity_magnitude_fit": gravity_fit,
        "bias_gyro": b_i[0, :3].tolist(),
        "bias_acc": b_i[0, 3:].tolist(),
    }


def nees_verdict(nees_per_dof: float, band: tuple[float, float] = NEES_CONSISTENT) -> str:
    """What a mean NEES per degree of freedom says about the configured noise densities: about 1 when the
    preintegration covariance matches the actual errors (within ``band``); above, the errors are
    ``sqrt(NEES/dof)`` times what the densities predict (vibration, unmodelled errors: inflate them, or the
    estimator will trust the IMU too much); below, the densities are pessimistic."""
    factor = float(np.sqrt(nees_per_dof))
    if nees_per_dof > band[1]:
        return (f"optimistic: the errors are {factor:.1f}x what the configured noise densities predict "
                "(vibration, unmodelled errors); inflate the densities by about that factor")
    if nees_per_dof < band[0]:
        return f"pessimistic: the errors are {factor:.2f}x what the configured noise densities predict"
    return "consistent with the configured noise densities"


def check_imu(
    imu: ImuSamples, noise: ImuNoise | None = None, gt: Trajectory | None = None,
    config: ImuCheckConfig | None = None,
) -> dict:
    """Run every check; returns a JSON-serialisable dict (see the module docstring)."""
    cfg = config or ImuCheckConfig()
    if len(imu) < 3:
        raise ValueError(f"imu-check needs at least 3 IMU samples, got {len(imu)}")
    defects = find_stream_defects(imu.t_ns, None, cfg.gap_factor)
    with warnings.catch_warnings():  # the defects are reported below, not warned about
        warnings.simplefilter("ignore")
        clean = sanitize_samples(imu, None, cfg.gap_factor)
    dt = np.diff(clean.t_ns) * 1e-9
    median_dt = float(np.median(dt))
    regular = dt[dt <= cfg.gap_factor * median_dt]
    report = {
        "samples": len(imu),
        "duration_s": float((clean.t_ns[-1] - clean.t_ns[0]) * 1e-9),
        "rate_hz": 1.0 / median_dt,
        "nominal_rate_hz": None if noise is None else noise.rate_hz,
        "jitter_std_ms": float(regular.std() * 1e3),
        "jitter_max_ms": float(np.abs(regular - median_dt).max() * 1e3),
        "out_of_order": defects.out_of_order,
        "duplicates": defects.duplicates,
        "gaps": {
            "count": int(len(defects.gaps)),
            "longest_ms": float((defects.gaps[:, 1] - defects.gaps[:, 0]).max() * 1e-6) if len(defects.gaps) else 0.0,
            "first_s": [float((g[0] - clean.t_ns[0]) * 1e-9) for g in defects.gaps[:5]],
        },
        "saturation": {
            "gyro": _saturation(clean.gyro, cfg.saturation_min_repeats),
            "acc": _saturation(clean.acc, cfg.saturation_min_repeats),
        },
    }
    segments = detect_static_segments(clean, cfg.static)
    source = "IMU"
    if len(segments) == 0 and gt is not None:
        segments = still_segments_from_motion(gt, cfg.still_from_ground_truth)
        source = "ground-truth motion"
    static = []
    rate = 1.0 / median_dt
    for t0, t1 in segments:
        try:
            s = static_initialize(clean, t0, t1)
        except ValueError:   # a still stretch of the ground truth with too few IMU samples in it
            continue
        entry = {
            "start_s": float((t0 - clean.t_ns[0]) * 1e-9),
            "found_by": source,
            "duration_s": float((t1 - t0) * 1e-9),
            "gyro_bias": s.bias_gyro.tolist(),
            "gyro_std": s.gyro_std.tolist(),
            "acc_std": s.acc_std.tolist(),
            "gravity_magnitude": s.gravity_magnitude,
            "implied_gyro_noise_density": float(np.mean(s.gyro_std) / np.sqrt(rate)),
            "implied_acc_noise_density": float(np.mean(s.acc_std) / np.sqrt(rate)),
        }
        if noise is not None:
            entry["gyro_density_ratio"] = entry["implied_gyro_noise_density"] / noise.gyro_noise_density
            entry["acc_density_ratio"] = entry["implied_acc_noise_density"] / noise.acc_noise_density
        static.append(entry)
    report["static_segments"] = static
    longest = max(static, key=lambda e: e["duration_s"]) if static else None
    report["gravity_magnitude"] = None if longest is None else longest["gravity_magnitude"]
    report["gravity_source"] = None if longest is None else f"longest static segment (found by the {source})"
    if gt is not None:
        c = preintegration_consistency(clean, gt, noise or ImuNoise(), cfg.nees_window_s, cfg.nees_max_windows)
        report["preintegration_consistency"] = c
        if longest is None and c["gravity_magnitude_fit"] is not None:
            report["gravity_magnitude"] = c["gravity_magnitude_fit"]
            report["gravity_source"] = "fitted to the ground-truth motion and biases"
    return report


def format_report(report: dict) -> str:
    """Human-readable text of a :func:`check_imu` report."""
    lines = [
        f"samples          {report['samples']} over {report['duration_s']:.2f} s",
        f"rate             {report['rate_hz']:.2f} Hz (configured {report['nominal_rate_hz']})",
        f"jitter           std {report['jitter_std_ms']:.4f} ms, max {report['jitter_max_ms']:.4f} ms",
        f"out-of-order     {report['out_of_order']}",
        f"duplicates       {report['duplicates']}",
        f"gaps             {report['gaps']['count']} (longest {report['gaps']['longest_ms']:.2f} ms)",
        f"saturation       gyro {report['saturation']['gyro']['samples']} samples "
        f"(max |w| {report['saturation']['gyro']['max_abs']:.3f} rad/s), acc {report['saturation']['acc']['samples']} "
        f"samples (max |a| {report['saturation']['acc']['max_abs']:.3f} m/s^2)",
        f"static segments  {len(report['static_segments'])}",
    ]
    for s in report["static_segments"]:
        ratio = f", {s['gyro_density_ratio']:.1f}x configured" if "gyro_density_ratio" in s else ""
        lines.append(
            f"  at {s['start_s']:.2f} s for {s['duration_s']:.2f} s (found by the {s['found_by']}): gyro bias "
            f"[{', '.join(f'{x:+.4f}' for x in s['gyro_bias'])}] rad/s, |g| {s['gravity_magnitude']:.3f} m/s^2, "
            f"gyro noise density {s['implied_gyro_noise_density']:.2e}{ratio}"
        )
    if report["gravity_magnitude"] is not None:
        lines.append(f"gravity          {report['gravity_magnitude']:.4f} m/s^2 ({report['gravity_source']})")
    c = report.get("preintegration_consistency")
    if c is not None:
        parts = ", ".join(f"{k} {v:.2f}" for k, v in c["per_block_nees_per_dof"].items())
        lines.append(
            f"consistency      mean NEES/dof {c['mean_nees_per_dof']:.2f} (median {c['median_nees_per_dof']:.2f}) "
            f"over {c['windows']} windows of {c['window_s']:.2f} s; {parts}; biases: {c['bias_source']}"
        )
        lines.append(f"                 {c['verdict']}")
    return "\n".join(lines)
