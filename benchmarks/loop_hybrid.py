"""Loop closure on hybrid sequences (issue 9 benchmark; VIGS-SLAM Table 7's comparison).

Hybrid sequence: recorded EuRoC ground truth, images rendered by ``vigs_core.sim`` along it at 376x240
(pinhole), cached as npz (same files as ``vio_hybrid``'s cache, so ``--cache`` can share them), or with
``--asl ROOT`` read from the ASL folders ``ROOT/<sequence>`` that ``vigs sim --euroc`` rendered (undistorted to
the inner pinhole camera as ``vigs run`` does; no rendering, so whole-length runs start in seconds). With
``--palindrome`` the frames are played forward and then backward (stamps continue at the frame rate), a path
that revisits every place: the case loop closure is for (the whole V1_01 forward then backward is the long
revisiting path). The dense monocular odometry (:class:`vigs_core.frontend.DenseOdometry`; with ``--imu`` the
visual-inertial one, forward runs only) runs twice on the same frames, without and with loop closure
(:class:`vigs_core.loop.LoopClosureDriver`, detection and PGBA on its worker thread: this benchmark reads the
loop graph and decisions, which a worker process would keep to itself). Reported per run:

* ATE RMSE of the keyframe-corrected camera trajectory of every posed frame, Sim(3) alignment (monocular);
* loops found / candidates rejected, PGBA runs and the mean wall time of one PGBA;
* a ground-truth check of every accepted loop (:func:`loop_geometry`): the error of its measured relative
  rotation and translation direction, false loops, and how many keyframes had a true revisit to find;
* frames/s of the whole loop (odometry + loop closure on the calling thread);
* with ``--psnr``, in the run with loop closure: the Gaussian mapper is fed every keyframe (image, depth from
  the keyframe's disparities) and the PSNR of renders at the final poses of every ``--psnr-every``-th
  non-keyframe frame is measured, once for the map that received the loop-closure keyframe updates (anchored
  Gaussians moved, Eq. 6-7) and once for a second map fed identically but never updated.

    vigs bench loop_hybrid [--asl /tmp/s2/hyb] [--sequences V1_01_easy] [--duration 30] [--palindrome] [--imu]
                           [--psnr] [--json OUT]
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
FALSE_LOOP_ROT_DEG = 5.0   # an accepted loop whose measured rotation is off the ground truth's by more is false
FALSE_LOOP_DIR_DEG = 30.0  # likewise for its translation direction (compared for baselines > MIN_BASELINE_M)
MIN_BASELINE_M = 0.2
REVISIT_M, REVISIT_DEG = 0.5, 30.0   # a ground-truth revisit: an old keyframe this close (m) and this aligned (deg)


def load_hybrid(name: str, duration_s: float | None, width: int, cache: Path) -> dict:
    """Stamps (N,), grey images (N, H, W) uint8, ground-truth camera poses T_WC (N, 4, 4) and the pinhole camera
    of a hybrid sequence (rendered once, cached as npz)."""
    from vigs_core.io import read_camera_yaml, read_euroc_groundtruth, read_euroc_imu, read_imu_yaml, read_tum
    from vigs_core.sim.hybrid import SimConfig, SimSequence, hybrid_source

    root = SHARED / name
    csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt = read_euroc_groundtruth(csv) if csv.exists() else read_tum(root / "groundtruth_tum.txt")
    imu = read_euroc_imu(root / "mav0" / "imu0" / "data.csv")
    calib = read_camera_yaml(SHARED / "calib" / "cam0_sensor.yaml")
    camera = calib.camera.pinhole().scaled(width / calib.camera.width)
    sim = SimSequence(hybrid_source(gt, imu), camera, calib.T_BS, SimConfig(duration_s=duration_s, with_depth=False))
    path = cache / f"{name}_{'full' if duration_s is None else f'{duration_s:g}s'}_{width}.npz"
    if path.exists():
        data = np.load(path)
        stamps, images = data["stamps"], data["images"]
    else:
        cache.mkdir(parents=True, exist_ok=True)
        frames = list(sim.frames())
        stamps = np.array([f.t_ns for f in frames], dtype=np.int64)
        images = np.stack([f.image if f.image.ndim == 2 else f.image.mean(-1).astype(np.uint8) for f in frames])
        np.savez(path, stamps=stamps, images=images)
    return {"stamps": stamps, "images": images, "T_WC": sim.camera_poses(stamps), "camera": camera,
            "imu": sim.imu, "imu_noise": read_imu_yaml(SHARED / "calib" / "imu0_sensor.yaml"), "T_BS": calib.T_BS}


def load_asl(root: Path, duration_s: float | None, width: int) -> dict:
    """The same from an already rendered hybrid EuRoC ASL folder (``vigs sim --euroc ... --asl``): images
    undistorted to the inner pinhole camera at ``width`` (as ``vigs run`` does), ground-truth camera poses
    ``T_WC = T_WB T_BS`` interpolated at the frame stamps."""
    from vigs_core.io.euroc_sequence import EurocSequence
    from vigs_core.system.pipeline import load_frames

    src = EurocSequence(root).camera_calibration.camera
    f = load_frames(root, width, round(src.height * width / src.width), duration_s)
    return {"stamps": f.t_ns, "images": f.images, "T_WC": f.T_WB @ f.sequence.T_BS, "camera": f.camera,
            "imu": f.sequence.imu, "imu_noise": f.sequence.imu_noise, "T_BS": f.sequence.T_BS}


def palindrome(seq: dict) -> dict:
    """Forward then backward along the same frames (the turning frame once); stamps continue at the frame rate.
    Without IMU data: a reversed IMU stream would not be the motion's."""
    n = len(seq["stamps"])
    order = np.concatenate((np.arange(n), np.arange(n - 2, -1, -1)))
    dt = int(np.median(np.diff(seq["stamps"])))
    stamps = seq["stamps"][0] + dt * np.arange(len(order), dtype=np.int64)
    return {"stamps": stamps, "images": seq["images"][order], "T_WC": seq["T_WC"][order], "camera": seq["camera"]}


def _mapper(camera, iterations: int):
    from vigs_core.mapping.mapper import GaussianMapper, MapperConfig

    return GaussianMapper(MapperConfig(iterations=iterations, backend="torch"), camera)


def _depth_image(kf, grid, width: int, height: int) -> np.ndarray:
    """Keyframe depth (H, W) from its grid disparities (bilinear), 0 where unknown."""
    import cv2

    disp = kf.disp.numpy().reshape(grid.rows, grid.cols).astype(np.float32)
    depth = np.where(disp > 0, 1.0 / np.maximum(disp, 1e-9), 0.0).astype(np.float32)
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_LINEAR)


def loop_geometry(seq: dict, odo, driver, gap: int) -> dict:
    """Ground-truth check of loop closure.

    Every accepted loop edge's measured ``Z = S_old^{-1} S_new`` is compared with the ground-truth relative pose
    ``T_old^{-1} T_new`` of the two keyframes' cameras: rotation error (deg) and, when the cameras are more than
    ``MIN_BASELINE_M`` apart, the angle between the measured and the true translation directions (deg; the
    measurement's scale is the map's, so only the direction is compared). A loop with a rotation error above
    ``FALSE_LOOP_ROT_DEG`` or a direction error above ``FALSE_LOOP_DIR_DEG`` counts as false. Also the
    ground-truth distance (m) and rotation (deg) of every accepted pair and rejected candidate, and
    ``keyframes_with_revisit``: keyframes with a ground-truth revisit the detector could find (an older keyframe,
    at least ``gap`` keyframes back, within ``REVISIT_M`` and ``REVISIT_DEG``)."""
    from vigs_core.loop.detection import rotation_angle_deg

    index = {int(t): n for n, t in enumerate(seq["stamps"])}
    ids = sorted(odo.keyframes)
    T = {k: torch.from_numpy(seq["T_WC"][index[int(odo.keyframes[k].t_ns)]]) for k in ids}

    def apart(a: int, b: int) -> tuple[float, float]:
        return float((T[a][:3, 3] - T[b][:3, 3]).norm()), rotation_angle_deg(T[a], T[b])

    errors = []
    for edge in driver.closure.graph.loops:
        Z = edge.relative.to(torch.float64)
        scale = float(torch.linalg.det(Z[:3, :3])) ** (1.0 / 3.0)
        R = torch.eye(4, dtype=torch.float64)
        R[:3, :3] = Z[:3, :3] / scale
        true = torch.linalg.inv(T[edge.old]) @ T[edge.new]
        rot = rotation_angle_deg(R, true)
        t_true, t_meas = true[:3, 3], Z[:3, 3]
        direction = (float(torch.rad2deg(torch.arccos(torch.clamp(
            t_true @ t_meas / (t_true.norm() * t_meas.norm()).clamp_min(1e-12), -1.0, 1.0))))
            if t_true.norm() > MIN_BASELINE_M else 0.0)
        errors.append((rot, direction))
    accepted = [apart(a, b) for a, b in driver.report()["accepted_pairs"]]
    rejected = [apart(old, new) for new, d in driver.closure.decisions.items() for old in d.rejected]
    P = torch.stack([T[k][:3, 3] for k in ids])
    revisits = 0
    for n in range(gap, len(ids)):
        dist = (P[:n - gap + 1] - P[n]).norm(dim=-1)
        close = [m for m in torch.nonzero(dist < REVISIT_M).flatten().tolist()
                 if rotation_angle_deg(T[ids[m]], T[ids[n]]) < REVISIT_DEG]
        revisits += bool(close)
    return {"accepted_gt_m_deg": accepted, "rejected_gt_m_deg": rejected,
            "loop_error_rot_dir_deg": errors,
            "false_loops": sum(r > FALSE_LOOP_ROT_DEG or d > FALSE_LOOP_DIR_DEG for r, d in errors),
            "max_rot_error_deg": max((r for r, _ in errors), default=float("nan")),
            "max_dir_error_deg": max((d for _, d in errors), default=float("nan")),
            "accepted_gt_max_m": max((d for d, _ in accepted), default=float("nan")),
            "keyframes_with_revisit": revisits}


def run(seq: dict, loop: bool, psnr: bool, mapper_iterations: int, psnr_every: int, imu: bool = False) -> dict:
    """One odometry run over the frames (visual-inertial with ``imu``); returns the metrics."""
    from vigs_core.eval import evaluate_trajectory
    from vigs_core.frontend import DenseOdometry
    from vigs_core.geometry import matrix_to_quat, se3_inverse
    from vigs_core.loop import LoopClosureDriver, LoopConfig
    from vigs_core.mapping.metrics import psnr as psnr_of
    from vigs_core.solver import Intrinsics
    from vigs_core.types import Trajectory

    cam = seq["camera"]
    intr = Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy)
    if imu:
        from vigs_core.vio.odometry import VisualInertialOdometry

        odo = VisualInertialOdometry(intr, cam.width, cam.height, seq["imu"], seq["imu_noise"], seq["T_BS"])
    else:
        odo = DenseOdometry(intr, cam.width, cam.height)
    mappers = {"updated": _mapper(cam, mapper_iterations), "not updated": _mapper(cam, mapper_iterations)} if psnr else {}
    driver = LoopClosureDriver(LoopConfig(process=False), odo, mapper=mappers.get("updated")) if loop else None
    fed: set[int] = set()
    t0 = time.perf_counter()
    mapping_s = 0.0
    for t_ns, image in zip(seq["stamps"], seq["images"]):
        odo.process(int(t_ns), image)
        if driver is not None:
            driver.step()
        if mappers:
            tm = time.perf_counter()
            for k in sorted(set(odo.keyframes) - fed):
                kf = odo.keyframes[k]
                rgb = np.repeat(kf.image[..., None], 3, -1)
                depth = _depth_image(kf, odo.grid, cam.width, cam.height)
                for m in mappers.values():
                    m.add_keyframe(k, se3_inverse(kf.pose), rgb, depth, kf.t_ns)
                fed.add(k)
            for m in mappers.values():
                m.process_pending()
            mapping_s += time.perf_counter() - tm
    if driver is not None:
        driver.finish()
    elapsed = time.perf_counter() - t0 - mapping_s
    t_est, T_cw = odo.final_frame_poses()
    T_wc = se3_inverse(T_cw).numpy()
    index = {int(t): n for n, t in enumerate(seq["stamps"])}
    est = Trajectory(t_est, T_wc[:, :3, 3], matrix_to_quat(torch.from_numpy(T_wc[:, :3, :3])).numpy())
    idx = np.array([index[int(t)] for t in t_est], dtype=np.int64)
    T_gt = seq["T_WC"][idx]
    gt = Trajectory(t_est, T_gt[:, :3, 3], matrix_to_quat(torch.from_numpy(T_gt[:, :3, :3])).numpy())
    ate = (evaluate_trajectory(gt, est, align="sim3", thresholds=(0.1,), max_diff_s=0.001)["ate_rmse"]
           if len(t_est) >= 3 else float("nan"))
    out = {"frames": len(seq["stamps"]), "posed": int(len(t_est)), "keyframes": len(odo.keyframes),
           "ate_sim3": ate, "fps": len(seq["stamps"]) / elapsed}
    if driver is not None:
        out["loop"] = driver.report()
        out["loop"]["ground_truth"] = loop_geometry(seq, odo, driver, driver.config.detection.min_keyframe_gap)
    if mappers:
        for m in mappers.values():
            m.process_pending()
        kf_stamps = {kf.t_ns for kf in odo.keyframes.values()}
        picks = [n for n, t in enumerate(t_est) if int(t) not in kf_stamps][::psnr_every]
        for name, m in mappers.items():
            values = []
            for n in picks:
                render = m.render(torch.from_numpy(T_wc[n])).color
                ref = torch.from_numpy(seq["images"][idx[n]]).float().div(255.0)
                ref = torch.nn.functional.interpolate(ref[None, None], size=render.shape[:2], mode="area")[0, 0]
                values.append(psnr_of(render.float(), ref[..., None].expand(*ref.shape, 3)))
            out[f"psnr {name}"] = float(np.mean(values)) if values else float("nan")
        out["mapping_s"] = mapping_s
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="vigs bench loop_hybrid", description=__doc__.split("\n\n")[0])
    p.add_argument("--sequences", nargs="+", default=list(SEQUENCES))
    p.add_argument("--duration", type=float, help="seconds from the first frame (default: whole sequence)")
    p.add_argument("--width", type=int, default=376, help="image width (px), 376 -> 376x240")
    p.add_argument("--palindrome", action="store_true", help="also run forward-then-backward (revisits)")
    p.add_argument("--only-palindrome", action="store_true", help="run only the forward-then-backward variant")
    p.add_argument("--imu", action="store_true", help="visual-inertial odometry (forward runs only)")
    p.add_argument("--psnr", action="store_true", help="also map and compare PSNR with / without loop updates")
    p.add_argument("--mapper-iterations", type=int, default=10, help="mapper iterations per keyframe")
    p.add_argument("--psnr-every", type=int, default=10, help="evaluate every n-th non-keyframe frame")
    p.add_argument("--cache", default="/tmp/vigs_vio_hybrid_cache", help="folder of rendered frames")
    p.add_argument("--asl", help="read the hybrid ASL folders <ASL>/<sequence> rendered by `vigs sim --euroc` "
                                 "instead of rendering (e.g. /tmp/s2/hyb)")
    p.add_argument("--json", help="write all results here")
    args = p.parse_args(argv)
    if args.imu and (args.palindrome or args.only_palindrome):
        p.error("--imu runs forward only: a palindrome's reversed IMU stream would not be the motion's")
    torch.set_num_threads(1)
    rows, results = [], {}
    for name in args.sequences:
        t0 = time.perf_counter()
        base = (load_asl(Path(args.asl) / name, args.duration, args.width) if args.asl
                else load_hybrid(name, args.duration, args.width, Path(args.cache)))
        print(f"{name}: {len(base['stamps'])} frames ready in {time.perf_counter() - t0:.1f} s", flush=True)
        variants = [] if args.only_palindrome else [("", base)]
        if args.palindrome or args.only_palindrome:
            variants.append((" palindrome", palindrome(base)))
        for tag, seq in variants:
            without = run(seq, False, False, args.mapper_iterations, args.psnr_every, args.imu)
            with_loop = run(seq, True, args.psnr, args.mapper_iterations, args.psnr_every, args.imu)
            rows.append((name + tag, without, with_loop))
            results[name + tag] = {"without_loop": without, "with_loop": with_loop}
            lp = with_loop["loop"]
            print(f"  {name + tag}: ATE {100 * without['ate_sim3']:.2f} -> {100 * with_loop['ate_sim3']:.2f} cm, "
                  f"loops {lp['loops_found']} (rejected {lp['loops_rejected']}), PGBA {lp['pgba_runs']} x "
                  f"{lp['pgba_seconds_mean']:.2f} s; false loops {lp['ground_truth']['false_loops']} (max error "
                  f"{lp['ground_truth']['max_rot_error_deg']:.1f} deg rotation, "
                  f"{lp['ground_truth']['max_dir_error_deg']:.1f} deg direction; max gt distance "
                  f"{lp['ground_truth']['accepted_gt_max_m']:.2f} m), keyframes with a true revisit "
                  f"{lp['ground_truth']['keyframes_with_revisit']}/{with_loop['keyframes']}", flush=True)
    kind = "dense visual-inertial odometry" if args.imu else "dense monocular odometry"
    print(f"\nLoop closure on hybrid sequences ({kind}, ATE with Sim(3) alignment)")
    head = (f"{'sequence':<26} {'frames':>6} {'kf':>4} {'ATE no loop [cm]':>16} {'ATE loop [cm]':>13} {'loops':>5} "
            f"{'rejected':>8} {'PGBA runs':>9} {'s/PGBA':>6} {'fps no loop':>11} {'fps loop':>8}")
    if args.psnr:
        head += f" {'PSNR no upd.':>12} {'PSNR upd.':>9}"
    print(head)
    for name, a, b in rows:
        lp = b["loop"]
        line = (f"{name:<26} {a['frames']:>6d} {b['keyframes']:>4d} {100 * a['ate_sim3']:>16.2f} "
                f"{100 * b['ate_sim3']:>13.2f} {lp['loops_found']:>5d} {lp['loops_rejected']:>8d} "
                f"{lp['pgba_runs']:>9d} {lp['pgba_seconds_mean']:>6.2f} {a['fps']:>11.1f} {b['fps']:>8.1f}")
        if args.psnr:
            line += f" {b['psnr not updated']:>12.2f} {b['psnr updated']:>9.2f}"
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
