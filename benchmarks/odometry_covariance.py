"""Is /odometry's covariance consistent with its error? NEES of the drift model on whole sequences and clips.

Runs ``vigs run`` (mapping and loop closure off: the node's ``odom`` pose is never loop-corrected) on the whole
hybrid bags of the shared sequences (``out/sim/<SEQ>_bag``, as ``vigs bench tracking``) and on any EuRoC clip
folders given (e.g. the robustness clips ``out/robustness/V1_01_easy@90``), replays the causal odometry
(``odometry.txt``, ``frame_status.txt``) through :class:`~vigs_core.vio.odometry_covariance.OdometryCovariance`
and compares it with the error since the first metric frame
(:func:`~vigs_core.eval.odometry_consistency.drift_errors`). Rows: metric frames, distance travelled, the largest
position error, the rms position / tilt / yaw errors, the mean NEES per degree of freedom of position, tilt,
yaw and all six, and the share of frames whose position error is within the model's 3 sigma per axis.

    vigs bench odometry_covariance [--sequences ...] [--clips DIR ...] [--model NODE_PARAMS.yaml] [--params F]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
SEQUENCES = ("V1_01_easy", "V2_01_easy", "MH_03_medium")
COLUMNS = ("case", "frames", "dist_m", "max_m", "pos_rms", "tilt_rms", "yaw_rms", "nees_pos", "nees_tilt",
           "nees_yaw", "nees_all", "in_3sigma")


def model_config(path: str | None):
    """The ``odometry_covariance`` section of a frontend node parameter file, over the defaults."""
    from vigs_core.system.config import apply_overrides, read_params_yaml
    from vigs_core.vio.odometry_covariance import OdometryCovarianceConfig

    cfg = OdometryCovarianceConfig()
    if path:
        section = (read_params_yaml(path).get("frontend") or {}).get("ros__parameters") or {}
        apply_overrides(cfg, section.get("odometry_covariance") or {}, "odometry_covariance.")
    return cfg


def run(source: Path, out: Path, params: str | None) -> None:
    """``vigs run`` of ``source`` into ``out``, mapping and loop closure off (skipped when already there)."""
    from vigs_core.system import load_config, run_pipeline

    if (out / "odometry.txt").exists() and (out / "frame_status.txt").exists():
        return
    cfg = load_config(params)
    cfg.mapping.enabled = False
    cfg.loop.enabled = False
    run_pipeline(source, cfg, out, progress=False)


def score(out: Path, gt_path: Path, cfg) -> dict:
    from vigs_core.eval.odometry_consistency import drift_errors, nees
    from vigs_core.io import read_frame_status, read_tum
    from vigs_core.vio.odometry import METRIC_STATUSES
    from vigs_core.vio.odometry_covariance import OdometryCovariance

    est = read_tum(out / "odometry.txt")
    status = read_frame_status(out / "frame_status.txt")
    labels = [status.get(int(t), "initialising") for t in est.t_ns]
    errors = drift_errors(read_tum(gt_path), est, np.isin(labels, METRIC_STATUSES))
    model = OdometryCovariance(cfg)
    by_stamp = {}
    for t, p, s in zip(est.t_ns, est.position, labels):   # every published frame, in order, as the node does
        by_stamp[int(t)] = model.pose(p, s)
    C = np.stack([by_stamp[int(t)] for t in errors.t_ns])
    e = np.concatenate((errors.position_error, errors.rotation_error), axis=1)
    var = np.diagonal(C, axis1=1, axis2=2)

    def per_dof(cols):
        return round(float((e[:, cols] ** 2 / var[:, cols]).mean()), 3)

    pos = np.linalg.norm(errors.position_error, axis=1)
    return {"frames": len(e), "dist_m": round(model.distance, 1), "max_m": round(float(pos.max()), 3),
            "pos_rms": round(float(np.sqrt((pos ** 2).mean())), 3),
            "tilt_rms": round(float(np.sqrt((errors.rotation_error[:, :2] ** 2).sum(1).mean())), 4),
            "yaw_rms": round(float(np.sqrt((errors.rotation_error[:, 2] ** 2).mean())), 4),
            "nees_pos": per_dof([0, 1, 2]), "nees_tilt": per_dof([3, 4]), "nees_yaw": per_dof([5]),
            "nees_all": round(float(nees(errors, C).mean() / 6), 3),
            "in_3sigma": round(float((np.abs(e[:, :3]) <= 3 * np.sqrt(var[:, :3])).all(1).mean()), 3)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench odometry_covariance", description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", nargs="*", default=list(SEQUENCES), help="whole hybrid bags out/sim/<SEQ>_bag")
    p.add_argument("--bags", default=str(ROOT / "out" / "sim"))
    p.add_argument("--clips", nargs="*", default=[], help="EuRoC clip folders with groundtruth_tum.txt")
    p.add_argument("--model", help="frontend node parameter file whose odometry_covariance section is the model")
    p.add_argument("--params", help="vigs run settings (mapping and loop closure are off regardless)")
    p.add_argument("--out", default=str(ROOT / "out" / "odometry_covariance"), help="run outputs (reused)")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    cfg = model_config(args.model)
    cases = [(s, Path(args.bags) / f"{s}_bag", Path(args.bags) / f"{s}_bag_groundtruth_tum.txt")
             for s in args.sequences]
    cases += [(Path(c).name, Path(c), Path(c) / "groundtruth_tum.txt") for c in args.clips]
    print(" ".join(f"{c:>20}" if c == "case" else f"{c:>9}" for c in COLUMNS), flush=True)
    rows = []
    for name, source, gt in cases:
        out = Path(args.out) / name
        try:
            run(source, out, args.params)
            row = {"case": name, **score(out, gt, cfg)}
        except Exception as err:   # noqa: BLE001 - a failed case is a row of the table, not the end of it
            row = {"case": name, "error": f"{type(err).__name__}: {err}"}
        rows.append(row)
        print(" ".join(f"{str(row.get(c, '-')):>20}" if c == "case" else f"{str(row.get(c, '-')):>9}"
                       for c in COLUMNS) + (f"  {row['error']}" if "error" in row else ""), flush=True)
    ok = [r for r in rows if "nees_all" in r]
    if ok:
        print(f"\n{len(ok)} cases; NEES per dof, median over cases: position "
              f"{np.median([r['nees_pos'] for r in ok]):.3f}, tilt {np.median([r['nees_tilt'] for r in ok]):.3f}, "
              f"yaw {np.median([r['nees_yaw'] for r in ok]):.3f}, all {np.median([r['nees_all'] for r in ok]):.3f}; "
              f"over 2 in {sum(r['nees_all'] > 2 for r in ok)}; load {os.getloadavg()[0]:.2f}")
    return 0 if len(ok) == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
