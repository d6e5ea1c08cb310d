"""Estimator robustness on hybrid sequences (issue 18): start offsets, frame strides and drops, IMU faults and
image degradations; and on procedural motion of other speeds in other scenes.

Clips are rendered by ``vigs sim --euroc SEQ --width 376 --no-depth --start S --duration D`` (real EuRoC IMU and
motion, rendered images) into ``--cache`` once. Cases:

* ``SEQ@S``: every ``--offset-step`` s start offset of each shared sequence (clean);
* ``SEQ stride10``, ``SEQ drop30``: the offset-0 clip with every 10th frame, or 30% of the frames dropped at
  random (a copy of the clip's frame list; the IMU is kept);
* ``SEQ imu_gap``: the offset-0 clip without 2 s of IMU samples from ``--fault-at`` s;
* ``SEQ imu_gap_init``: the offset-0 clip without 2 s of IMU samples ending 1 s before its clean run's alignment
  (the ``init_s`` of its ``SEQ@0`` row, run first when the table has none): a gap among the keyframes the
  inertial-only initialisation solves over;
* ``SEQ imu_future``: the offset-0 clip with one IMU sample stamped 1000 s in the future at ``--fault-at`` s, fed in
  recorded order (a file reader sorts stamps, so this case drives :class:`~vigs_core.system.stream.OdometryStream`
  sample by sample as the frontend node does; no loop closure);
* ``SEQ acc_step``: the offset-0 clip with the accelerometer's y and z readings 3 m/s^2 higher from ``--fault-at``
  s on (a knocked IMU: the estimator must notice, not publish a divergent metric state);
* ``SEQ blur`` / ``over_exposure`` / ``low_light``: clips rendered with ``vigs sim``'s degradations;
* ``proc sN xV``: ``vigs sim --procedural --seed N --procedural-speed V`` (``--procedural-seeds`` x
  ``--procedural-speeds``, ``--duration`` long): another room and smooth random motion at V times the default
  speeds, its IMU synthesised from the motion with the datasheet's noise (consistent with the images, where the
  hybrid clips' real IMU and ground truth disagree by 1-2 % in scale).

Every other case runs ``vigs run`` (in process: :func:`~vigs_core.system.pipeline.run_pipeline`, loop closure on,
mapping off). Columns, on the final body trajectory against the ground truth at the frames:

* ``ate_cm``: SE(3) ATE RMSE over the frames published as metric (status ``tracking`` / ``reinitialised``);
* ``scale_%``: ``|s - 1|`` of the Sim(3) alignment of those frames;
* ``rec10``: frames published metric and within 10 cm (SE(3)) over all frames;
* ``init_s``: first metric frame after the first frame (s);
* ``fail``, ``reinit``, ``lost``: failures detected, re-initialisations, frames reported lost;
* ``bad``: frames published as metric whose error exceeds 0.5 m (the divergence the estimator must not hide);
* ``bad_odo``: the same on the causal poses as published (``odometry.txt``, its own SE(3) alignment).

    vigs bench robustness [--sequences ...] [--offset-step 10] [--duration 30] [--cases offsets variants faults
                          degradations procedural] [--procedural-seeds 1 2 3] [--procedural-speeds 0.5 1 2 4]
                          [--cache out/robustness] [--params FILE --tag T] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SHARED = Path(os.environ.get("VIGS_SHARED", ROOT.parent / "shared")) / "data" / "euroc"
SEQUENCES = ("V1_01_easy", "V2_01_easy", "MH_03_medium")
DEGRADATIONS = {"blur": ["--blur-kernel", "9"], "over_exposure": ["--over-exposure", "2.0"],
                "low_light": ["--low-light-gamma", "2.5"]}
BAD_M = 0.5
METRIC = ("tracking", "reinitialised")


def sequence_length_s(name: str) -> float:
    """Span (s) of a shared sequence's ground truth."""
    from vigs_core.io import read_euroc_groundtruth, read_tum

    root = SHARED / name
    csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt = read_euroc_groundtruth(csv) if csv.exists() else read_tum(root / "groundtruth_tum.txt")
    return float(gt.t_s[-1] - gt.t_s[0])


def render(name: str, start: float, duration: float, cache: Path, extra: list[str] = (), tag: str = "") -> Path | None:
    """The ASL folder of a clip of a shared sequence (rendered once); None when ``vigs sim`` cannot render it
    (past the end)."""
    return render_clip(cache / f"{name}@{start:g}{tag}", ["--euroc", str(SHARED / name), "--start", str(start),
                                                          "--duration", str(duration), *extra])


def render_procedural(seed: int, speed: float, duration: float, cache: Path) -> Path | None:
    """The ASL folder of a procedural clip (rendered once): scene and motion of ``seed`` at ``speed``."""
    return render_clip(cache / f"procedural_s{seed}_x{speed:g}_{duration:g}s",
                       ["--procedural", "--procedural-duration", str(duration), "--procedural-speed", str(speed),
                        "--seed", str(seed)])


def render_clip(out: Path, source: list[str]) -> Path | None:
    """``vigs sim SOURCE --width 376 --no-depth --asl OUT`` unless ``out`` holds a rendered clip; None when it
    fails or ``out`` is left without ground truth (being rendered by another run, or broken)."""
    if (out / "groundtruth_tum.txt").exists():
        return out
    if out.exists():   # being rendered by another run, or left broken: not ours to remove
        print(f"  {out.name} exists without ground truth: skipped (remove it to render again)", file=sys.stderr)
        return None
    cmd = [sys.executable, "-m", "vigs_cli.main", "sim", *source, "--width", "376", "--no-depth", "--asl", str(out),
           "--no-progress"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if done.returncode != 0:
        print(f"  render {out.name} failed: {done.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
        shutil.rmtree(out, ignore_errors=True)
        return None
    return out


def variant(clip: Path, tag: str, keep_frame=None, imu_edit=None) -> Path:
    """A copy of ``clip`` (images linked) with a filtered frame list and / or edited IMU CSV lines."""
    out = clip.with_name(clip.name + tag)
    shutil.rmtree(out, ignore_errors=True)
    (out / "mav0" / "cam0").mkdir(parents=True)
    (out / "mav0" / "imu0").mkdir(parents=True)
    shutil.copy(clip / "groundtruth_tum.txt", out)
    shutil.copytree(clip / "mav0" / "state_groundtruth_estimate0", out / "mav0" / "state_groundtruth_estimate0")
    for name in ("sensor.yaml",):
        for sensor in ("cam0", "imu0"):
            if (clip / "mav0" / sensor / name).exists():
                shutil.copy(clip / "mav0" / sensor / name, out / "mav0" / sensor / name)
    (out / "mav0" / "cam0" / "data").symlink_to((clip / "mav0" / "cam0" / "data").resolve())
    lines = (clip / "mav0" / "cam0" / "data.csv").read_text().splitlines()
    rows = [ln for k, ln in enumerate(lines[1:]) if keep_frame is None or keep_frame(k)]
    (out / "mav0" / "cam0" / "data.csv").write_text("\n".join([lines[0], *rows]) + "\n")
    imu = (clip / "mav0" / "imu0" / "data.csv").read_text().splitlines()
    imu = [imu[0], *(imu_edit(imu[1:]) if imu_edit else imu[1:])]
    (out / "mav0" / "imu0" / "data.csv").write_text("\n".join(imu) + "\n")
    return out


def imu_gap(at_s: float, length_s: float):
    def edit(lines: list[str]) -> list[str]:
        t0 = int(lines[0].split(",")[0]) + int(at_s * 1e9)
        return [ln for ln in lines if not t0 <= int(ln.split(",")[0]) < t0 + int(length_s * 1e9)]
    return edit


def acc_step(at_s: float, step: float):
    def edit(lines: list[str]) -> list[str]:
        t0 = int(lines[0].split(",")[0]) + int(at_s * 1e9)
        out = []
        for ln in lines:
            f = ln.split(",")
            if int(f[0]) >= t0:
                f[5], f[6] = repr(float(f[5]) + step), repr(float(f[6]) + step)
            out.append(",".join(f))
        return out
    return edit


def gap_before_alignment(base: Path, short: str, rows: list[dict], args) -> Path:
    """The ``SEQ imu_gap_init`` clip: ``base`` (the offset-0 clip) without 2 s of IMU ending 1 s before the clean
    run's alignment, from the table's ``SEQ@0`` row or, without one, a clean run made here."""
    init_s = next((r.get("init_s") for r in rows if r["case"] == f"{short}@0"), None)
    if init_s is None:
        out = Path(args.cache) / "runs" / (f"{short}@0" + args.tag)
        init_s = score(base, out, run_clip(base, out, args.params))["init_s"]
    if init_s is None or init_s < 3.0:
        raise RuntimeError(f"the clean clip aligns at {init_s} s: no room for a 2 s gap before it")
    return variant(base, "_imugapinit", imu_edit=imu_gap(init_s - 3.0, 2.0))


def pipeline_config(params: str | None):
    """The run's settings: defaults or ``--params`` (as ``vigs run --params``), mapping off."""
    from vigs_core.system import load_config

    cfg = load_config(params)
    cfg.mapping.enabled = False
    return cfg


def run_clip(clip: Path, out: Path, params: str | None) -> dict:
    """``vigs run`` on a clip; the report."""
    from vigs_core.system.pipeline import run_pipeline

    return run_pipeline(clip, pipeline_config(params), out_dir=out, progress=False)


def run_future_stamp(clip: Path, out: Path, at_s: float, params: str | None) -> dict:
    """The clip through an OdometryStream, IMU in recorded order with one sample stamped 1000 s ahead at ``at_s``;
    writes trajectory.txt, odometry.txt and frame_status.txt as ``vigs run`` does. Also returns when the IMU was
    back in use."""
    from vigs_core.io import write_frame_status, write_tum
    from vigs_core.system import OdometryStream
    from vigs_core.system.pipeline import poses_to_trajectory
    from vigs_core.system.sources import open_input

    seq = open_input(clip)
    imu = seq.imu
    bad = int(np.searchsorted(imu.t_ns, imu.t_ns[0] + int(at_s * 1e9)))
    t_rec = imu.t_ns.copy()
    t_rec[bad] += int(1000e9)
    stream = OdometryStream(seq.camera, pipeline_config(params), seq.T_BS, seq.imu_noise)
    k, used_after = 0, None
    for t_ns, image in seq.frames():
        while k < len(imu) and not stream.imu.covers(t_ns):
            stream.add_imu(int(t_rec[k]), imu.gyro[k], imu.acc[k])
            if k > bad and used_after is None and stream.imu.latest_ns == int(t_rec[k]):
                used_after = (int(t_rec[k]) - int(imu.t_ns[bad])) * 1e-9
            k += 1
        stream.add_image(t_ns, image)
    odo = stream.odometry
    out.mkdir(parents=True, exist_ok=True)
    for name, (t, T_cw) in (("trajectory.txt", odo.final_frame_poses()), ("odometry.txt", odo.odometry_poses())):
        write_tum(out / name, poses_to_trajectory(t, np.linalg.inv(T_cw.numpy()) @ np.linalg.inv(seq.T_BS)))
    write_frame_status(out / "frame_status.txt", odo.frame_status)
    return {"vio": odo.report(), "imu_back_after_s": used_after}


def score(clip: Path, out: Path, report: dict) -> dict:
    """The table's columns from a run's trajectory.txt, frame_status.txt and the clip's ground truth."""
    from vigs_core.eval import evaluate_trajectory
    from vigs_core.io import read_frame_status, read_tum
    from vigs_core.system.pipeline import groundtruth_at
    from vigs_core.types import Trajectory

    gt = read_tum(clip / "groundtruth_tum.txt")
    est = read_tum(out / "trajectory.txt")
    status = read_frame_status(out / "frame_status.txt")
    frames = np.array([int(ln.split(",")[0]) for ln in (clip / "mav0" / "cam0" / "data.csv").read_text()
                       .splitlines()[1:]], dtype=np.int64)
    vio = report.get("vio", {})
    row = {"frames": len(frames), "posed": len(est.t_ns), "fail": len(vio.get("failures", [])),
           "reinit": vio.get("reinitialisations", 0), "lost": sum(s == "lost" for s in status.values())}
    metric = np.array([status.get(int(t)) in METRIC for t in est.t_ns])
    row["metric"] = int(metric.sum())
    row["init_s"] = round((int(est.t_ns[metric][0]) - int(frames[0])) * 1e-9, 2) if metric.any() else None
    if metric.sum() < 3:
        return {**row, "ate_cm": None, "scale_%": None, "rec10": 0.0, "bad": 0, "bad_odo": 0}

    def metric_errors(traj):   # SE(3)-aligned errors of the metric frames, their reference, the SE(3) evaluation
        on = np.array([status.get(int(t)) in METRIC for t in traj.t_ns])
        ref, inside = groundtruth_at(gt, traj.t_ns[on])
        idx = np.nonzero(on)[0][inside]
        sel = Trajectory(traj.t_ns[idx], traj.position[idx], traj.quat_wxyz[idx])
        se3 = evaluate_trajectory(ref, sel, align="se3", max_diff_s=1e-3)
        A = np.array(se3["alignment"])
        return np.linalg.norm(sel.position @ A[:3, :3].T + A[:3, 3] - ref.position, axis=1), ref, sel, se3

    err, ref, sel, se3 = metric_errors(est)
    sim3 = evaluate_trajectory(ref, sel, align="sim3", max_diff_s=1e-3)
    err_odo = metric_errors(read_tum(out / "odometry.txt"))[0]
    return {**row, "ate_cm": round(100 * se3["ate_rmse"], 2), "scale_%": round(100 * abs(sim3["scale"] - 1), 2),
            "rec10": round(float((err <= 0.10).sum()) / len(frames), 3), "bad": int((err > BAD_M).sum()),
            "bad_odo": int((err_odo > BAD_M).sum())}


def cases(args) -> list[tuple[str, Path | None, str]]:
    """(name, clip folder, kind) of every case; clips rendered as needed."""
    out = []
    cache = Path(args.cache)
    for name in args.sequences:
        short = name.split("_")[0]
        if "offsets" in args.cases:
            last = sequence_length_s(name) - args.duration
            starts = np.arange(0.0, last + 1e-9, args.offset_step) if args.starts is None else args.starts
            for start in starts:
                clip = render(name, float(start), args.duration, cache)
                if clip is not None:
                    out.append((f"{short}@{start:g}", clip, "run"))
        base = render(name, 0.0, args.duration, cache) if {"variants", "faults"} & set(args.cases) else None
        if "variants" in args.cases and base is not None:
            rng = np.random.default_rng(0)
            drop = rng.random(100_000) >= 0.3
            out.append((f"{short} stride10", variant(base, "_stride10", lambda k: k % 10 == 0), "run"))
            out.append((f"{short} drop30", variant(base, "_drop30", lambda k: bool(drop[k])), "run"))
        if "faults" in args.cases and base is not None:
            out.append((f"{short} imu_gap", variant(base, "_imugap", imu_edit=imu_gap(args.fault_at, 2.0)), "run"))
            out.append((f"{short} imu_gap_init", base, "gap_init"))
            out.append((f"{short} imu_future", base, "future"))
            out.append((f"{short} acc_step", variant(base, "_accstep", imu_edit=acc_step(args.fault_at, 3.0)), "run"))
        if "degradations" in args.cases:
            for tag, extra in DEGRADATIONS.items():
                clip = render(name, 0.0, args.duration, cache, extra, "_" + tag)
                if clip is not None:
                    out.append((f"{short} {tag}", clip, "run"))
    if "procedural" in args.cases:
        for seed in args.procedural_seeds:
            for speed in args.procedural_speeds:
                clip = render_procedural(seed, speed, args.duration, cache)
                if clip is not None:
                    out.append((f"proc s{seed} x{speed:g}", clip, "run"))
    return out


COLUMNS = ("case", "frames", "metric", "ate_cm", "scale_%", "rec10", "init_s", "fail", "reinit", "lost", "bad",
           "bad_odo")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench robustness", description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    p.add_argument("--offset-step", type=float, default=10.0, help="start offsets every this many seconds")
    p.add_argument("--starts", type=float, nargs="+", help="only these start offsets (s)")
    p.add_argument("--duration", type=float, default=30.0, help="clip length (s)")
    p.add_argument("--fault-at", type=float, default=15.0, help="IMU faults this long after the clip's start (s)")
    p.add_argument("--cases", nargs="+", default=["offsets", "variants", "faults", "degradations", "procedural"],
                   choices=["offsets", "variants", "faults", "degradations", "procedural"])
    p.add_argument("--procedural-seeds", type=int, nargs="+", default=[1, 2, 3],
                   help="scene and motion seeds of the procedural clips")
    p.add_argument("--procedural-speeds", type=float, nargs="+", default=[0.5, 1.0, 2.0, 4.0],
                   help="speeds of the procedural clips (vigs sim --procedural-speed)")
    p.add_argument("--cache", default=str(ROOT / "out" / "robustness"), help="rendered clips and run outputs")
    p.add_argument("--params", help="settings as for vigs run --params (mapping is off regardless)")
    p.add_argument("--tag", default="", help="suffix of the run folders (compare settings on the same clips)")
    p.add_argument("--json", help="write the rows here")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    rows = []
    print(" ".join(f"{c:>14}" if c == "case" else f"{c:>7}" for c in COLUMNS), flush=True)
    for name, clip, kind in cases(args):
        out = Path(args.cache) / "runs" / (name.replace(" ", "_") + args.tag)
        t0 = time.perf_counter()
        try:
            if kind == "gap_init":
                clip = gap_before_alignment(clip, name.split()[0], rows, args)
            report = (run_future_stamp(clip, out, args.fault_at, args.params) if kind == "future"
                      else run_clip(clip, out, args.params))
            row = {"case": name, **score(clip, out, report)}
            if kind == "future":
                row["imu_back_after_s"] = report["imu_back_after_s"]
        except Exception as err:   # noqa: BLE001 - a crashed run is a row of the table, not the end of it
            row = {"case": name, "error": f"{type(err).__name__}: {err}"}
        row["run_s"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        print(" ".join(f"{str(row.get(c, '-')):>14}" if c == "case" else f"{str(row.get(c, '-')):>7}"
                       for c in COLUMNS) + (f"  {row['error']}" if "error" in row else ""), flush=True)
    clean = [r for r in rows if "@" in r["case"] and r.get("ate_cm") is not None]
    print(f"\n{len(rows)} runs; metric frames off by > {BAD_M} m: {sum(r.get('bad', 0) for r in rows)} final, "
          f"{sum(r.get('bad_odo', 0) for r in rows)} as published; "
          f"errors: {sum('error' in r for r in rows)}; clean offsets ATE median "
          f"{np.median([r['ate_cm'] for r in clean]) if clean else float('nan'):.2f} cm; load {os.getloadavg()[0]:.2f}")
    proc = [r for r in rows if r["case"].startswith("proc ")]
    if proc:
        done = [r["ate_cm"] for r in proc if r.get("ate_cm") is not None]
        print(f"procedural: {len(done)} of {len(proc)} clips metric, ATE median / max "
              f"{np.median(done) if done else float('nan'):.2f} / {max(done, default=float('nan')):.2f} cm")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
