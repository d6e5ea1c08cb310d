"""Dense visual-inertial odometry on hybrid sequences (issue 6 benchmark).

Hybrid sequence: recorded EuRoC ground truth and IMU, images rendered by ``vigs_core.sim`` along the ground
truth at 376x240 (pinhole), from the first frame. Frames are rendered once and cached (``--cache``, npz);
``--stride N`` keeps every N-th frame (the IMU is kept). Each run feeds the frames to
:class:`vigs_core.vio.odometry.VisualInertialOdometry` and evaluates the body trajectory at the fed frames
against the ground truth at the same stamps:

* ATE RMSE with SE(3) alignment (no scale correction) -- the metric claim;
* scale error ``|s - 1|`` of the Sim(3) alignment;
* recall@10cm (fraction of fed frames within 10 cm after the SE(3) alignment);
* frames/s of the odometry alone (rendering excluded), and the stage / estimated scale / final biases.

* CPU seconds of the run (``time.process_time``) and the 1-minute load average at its end (timings on the
  shared 2-core machine are only comparable with both).

Rows: every sequence at each of ``--strides`` (default 1 and 10) with the full system; with ``--ablations``
also the rows of VIGS-SLAM Table 6 (:data:`vigs_core.vio.config.ABLATIONS`) at stride 1.

With ``--asl ROOT`` the frames come from already rendered EuRoC ASL folders ``ROOT/<sequence>`` (``vigs sim
--euroc`` output: images, the IMU slice, ``groundtruth_tum.txt``), undistorted and resized by the pipeline's
:class:`~vigs_core.system.pipeline.Preprocessor` exactly as ``vigs run`` does, instead of rendering here.

    vigs bench vio_hybrid [--sequences V1_01_easy V2_01_easy MH_03_medium] [--duration 30] [--strides 1 10]
                          [--ablations] [--asl ROOT] [--json OUT]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

SHARED = Path(os.environ.get("VIGS_SHARED", "/work/shared")) / "data" / "euroc"
SEQUENCES = ("V1_01_easy", "V2_01_easy", "MH_03_medium")


def _sequence_inputs(name: str):
    """(ground truth Trajectory, ImuSamples) of a shared EuRoC sequence (CSV ground truth when present)."""
    from vigs_core.io import read_euroc_groundtruth, read_euroc_imu, read_tum

    root = SHARED / name
    csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt = read_euroc_groundtruth(csv) if csv.exists() else read_tum(root / "groundtruth_tum.txt")
    return gt, read_euroc_imu(root / "mav0" / "imu0" / "data.csv")


def render_hybrid(name: str, duration_s: float | None, width: int, cache: Path):
    """Frames of the hybrid sequence: dict with stamps (N,), images (N, H, W) uint8, T_WB (N, 4, 4) ground truth
    at the stamps, the simulator's IMU slice, camera and T_BS. Cached as npz."""
    from vigs_core.io import read_camera_yaml, read_imu_yaml
    from vigs_core.sim.hybrid import SimConfig, SimSequence, hybrid_source

    gt, imu = _sequence_inputs(name)
    calib = read_camera_yaml(SHARED / "calib" / "cam0_sensor.yaml")
    camera = calib.camera.pinhole().scaled(width / calib.camera.width)
    sim = SimSequence(hybrid_source(gt, imu), camera, calib.T_BS, SimConfig(duration_s=duration_s, with_depth=False))
    tag = f"{name}_{'full' if duration_s is None else f'{duration_s:g}s'}_{width}.npz"
    path = cache / tag
    # a longer cached render of the same sequence serves a shorter request (same first frame, same stamps)
    longer = sorted(cache.glob(f"{name}_*_{width}.npz")) if duration_s is not None else []
    longer = [p for p in longer if p.stem.split("_")[-2] == "full"
              or float(p.stem.split("_")[-2][:-1]) >= duration_s]
    if path.exists() or longer:
        data = np.load(path if path.exists() else longer[0])
        keep = data["stamps"] <= sim.frame_t_ns[-1]
        stamps, images = data["stamps"][keep], data["images"][keep]
    else:
        cache.mkdir(parents=True, exist_ok=True)
        frames = list(sim.frames())
        stamps = np.array([f.t_ns for f in frames], dtype=np.int64)
        images = np.stack([f.image if f.image.ndim == 2 else f.image.mean(-1).astype(np.uint8) for f in frames])
        np.savez(path, stamps=stamps, images=images)
    T_WC = sim.camera_poses(stamps)
    T_WB = T_WC @ np.linalg.inv(calib.T_BS)
    return {"stamps": stamps, "images": images, "T_WB": T_WB, "imu": sim.imu, "camera": camera,
            "T_BS": calib.T_BS, "noise": read_imu_yaml(SHARED / "calib" / "imu0_sensor.yaml")}


def load_asl(root: Path, duration_s: float | None, width: int, height: int) -> dict:
    """Frames of an already rendered ASL folder (module docstring), in the same dict as :func:`render_hybrid`;
    ground truth interpolated at the frame stamps (frames outside its span are dropped)."""
    from vigs_core.system.pipeline import load_frames

    f = load_frames(root, width, height, duration_s)
    if f.sequence.imu is None:
        raise ValueError(f"{root}: an ASL folder with IMU data is needed")
    return {"stamps": f.t_ns, "images": f.images, "T_WB": f.T_WB, "imu": f.sequence.imu, "camera": f.camera,
            "T_BS": f.sequence.T_BS, "noise": f.sequence.imu_noise}


def run_vio(seq: dict, stride: int, overrides: dict) -> dict:
    """Run the VI odometry on every ``stride``-th frame; returns metrics and the VIO report."""
    from vigs_core.eval import evaluate_trajectory, recall_key
    from vigs_core.geometry import matrix_to_quat, se3_inverse
    from vigs_core.solver import Intrinsics
    from vigs_core.types import Trajectory
    from vigs_core.vio.config import VioConfig
    from vigs_core.vio.odometry import VisualInertialOdometry

    cam = seq["camera"]
    odo = VisualInertialOdometry(Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy), cam.width, cam.height, seq["imu"],
                                 seq["noise"], seq["T_BS"], vio=VioConfig(**overrides))
    idx = np.arange(0, len(seq["stamps"]), stride)
    t0, c0 = time.perf_counter(), time.process_time()
    for k in idx:
        odo.process(int(seq["stamps"][k]), seq["images"][k])
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    t_est, T_cw = odo.final_frame_poses()
    T_wb = (se3_inverse(T_cw) @ odo.vio.T_cb).numpy()
    est = Trajectory(t_est, T_wb[:, :3, 3], matrix_to_quat(torch.from_numpy(T_wb[:, :3, :3])).numpy())
    T_gt = seq["T_WB"][idx]
    gt = Trajectory(seq["stamps"][idx], T_gt[:, :3, 3], matrix_to_quat(torch.from_numpy(T_gt[:, :3, :3])).numpy())
    se3 = evaluate_trajectory(gt, est, align="se3", thresholds=(0.1,), max_diff_s=0.001)
    sim3 = evaluate_trajectory(gt, est, align="sim3", thresholds=(0.1,), max_diff_s=0.001)
    rep = odo.report()
    return {"frames": int(len(idx)), "posed": int(len(t_est)), "keyframes": len(odo.keyframes),
            "ate_se3": se3["ate_rmse"], "ate_sim3": sim3["ate_rmse"], "scale_error": abs(sim3["scale"] - 1.0),
            "recall@10cm": se3[recall_key(0.1)], "fps": len(idx) / elapsed, "cpu_s": cpu,
            "load": os.getloadavg()[0], "stage": rep["stage"], "vio": rep}


def _print_table(title: str, rows: list[tuple[str, dict]]) -> None:
    print(f"\n{title}")
    print(f"{'run':<42} {'frames':>6} {'kf':>4} {'ATE se3 [cm]':>12} {'ATE sim3 [cm]':>13} {'scale err':>9} "
          f"{'rec@10cm':>8} {'fps':>6} {'CPU s':>7} {'load':>5} {'stage':>16}")
    for name, r in rows:
        print(f"{name:<42} {r['frames']:>6d} {r['keyframes']:>4d} {100 * r['ate_se3']:>12.2f} "
              f"{100 * r['ate_sim3']:>13.2f} {100 * r['scale_error']:>8.2f}% {100 * r['recall@10cm']:>7.1f}% "
              f"{r['fps']:>6.1f} {r['cpu_s']:>7.1f} {r['load']:>5.1f} {r['stage']:>16}")


def main(argv: list[str] | None = None) -> int:
    from vigs_core.vio.config import ABLATIONS

    p = argparse.ArgumentParser(prog="vigs bench vio_hybrid", description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    p.add_argument("--duration", type=float, help="seconds from the first frame (default: whole sequence)")
    p.add_argument("--width", type=int, default=376, help="image width (px), 376 -> 376x240")
    p.add_argument("--strides", type=int, nargs="+", default=[1, 10], help="frame strides to run (IMU kept)")
    p.add_argument("--ablations", action="store_true", help="also the VIGS-SLAM Table 6 ablation rows")
    p.add_argument("--cache", default="/tmp/vigs_vio_hybrid_cache", help="folder of rendered frames")
    p.add_argument("--asl", help="read already rendered ASL folders ROOT/<sequence> instead of rendering")
    p.add_argument("--height", type=int, default=240, help="image height (px) with --asl")
    p.add_argument("--json", help="write all results here")
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    main_rows, ablation_rows, results = [], [], {}
    for name in args.sequences:
        t0 = time.perf_counter()
        if args.asl:
            seq = load_asl(Path(args.asl) / name, args.duration, args.width, args.height)
        else:
            seq = render_hybrid(name, args.duration, args.width, Path(args.cache))
        print(f"{name}: {len(seq['stamps'])} frames ready in {time.perf_counter() - t0:.1f} s", flush=True)
        for stride in args.strides:
            r = run_vio(seq, stride, {})
            main_rows.append((f"{name} stride {stride}", r))
            results[f"{name}/stride{stride}"] = r
            print(f"  stride {stride}: ATE se3 {100 * r['ate_se3']:.2f} cm, scale err {100 * r['scale_error']:.2f}%, "
                  f"recall {100 * r['recall@10cm']:.1f}%, {r['fps']:.1f} fps ({r['cpu_s']:.1f} CPU s, load "
                  f"{r['load']:.1f})", flush=True)
        if args.ablations:
            for ab, overrides in ABLATIONS.items():
                if ab == "full":
                    continue
                r = run_vio(seq, 1, overrides)
                ablation_rows.append((f"{name} {ab}", r))
                results[f"{name}/{ab}"] = r
                print(f"  {ab}: ATE se3 {100 * r['ate_se3']:.2f} cm", flush=True)
    _print_table("VIO on hybrid sequences (ATE with SE(3) alignment, no scale correction)", main_rows)
    if ablation_rows:
        _print_table("Ablations (VIGS-SLAM Table 6), stride 1", ablation_rows)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
