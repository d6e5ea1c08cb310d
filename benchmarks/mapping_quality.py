"""Gaussian mapper on a hybrid sequence with ground-truth poses and depths (issue 8 benchmark).

A hybrid sequence (recorded EuRoC ground truth + IMU, images and depth rendered by ``vigs_core.sim`` at
376x240, pinhole) is generated in-process, or read from an ASL folder written by ``vigs sim`` with a
``depth0`` folder (``--asl DIR``). Keyframes are chosen by motion (translation or rotation since the last
keyframe); the mapper (reference rasterizer, ``render_scale=1``: 376x240) integrates each one with the
default iterations, synchronously, so the time per keyframe is measured. Then every non-keyframe frame is
rendered at its ground-truth pose and compared to its image: online PSNR/SSIM; then the optional final
colour refinement and the metrics again. Prints one table.

    vigs bench mapping_quality [--sequence V1_01_easy] [--start 10] [--duration 10] [--refine 300]
"""
from __future__ import annotations

import argparse
import math
import os
import resource
import time
from pathlib import Path

import numpy as np
import torch

from vigs_core.mapping.mapper import GaussianMapper, MapperConfig

SHARED = Path(os.environ.get("VIGS_SHARED", "/work/shared")) / "data" / "euroc"


def _load_hybrid(args) -> tuple[object, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]]:
    """(camera, [(t_ns, image, depth, T_WC)]) rendered in-process by the simulator."""
    from vigs_core.io import read_camera_yaml, read_euroc_groundtruth, read_euroc_imu, read_tum
    from vigs_core.sim.hybrid import SimConfig, SimSequence, hybrid_source
    from vigs_core.sim.render import RenderConfig

    seq_dir = SHARED / args.sequence / "mav0"
    gt_csv = seq_dir / "state_groundtruth_estimate0" / "data.csv"
    gt_tum = SHARED / args.sequence / "groundtruth_tum.txt"  # MH_03_medium ships only this
    if not gt_csv.exists() and not gt_tum.exists():
        raise FileNotFoundError(f"no ground truth for {args.sequence}: neither {gt_csv} nor {gt_tum}")
    gt = read_euroc_groundtruth(gt_csv) if gt_csv.exists() else read_tum(gt_tum)
    imu = read_euroc_imu(seq_dir / "imu0" / "data.csv")
    calib = read_camera_yaml(SHARED / "calib" / "cam0_sensor.yaml")
    camera = calib.camera.pinhole().scaled(0.5)
    config = SimConfig(
        rate_hz=20.0, start_s=args.start, duration_s=args.duration, render=RenderConfig(rgb=args.rgb)
    )
    seq = SimSequence(hybrid_source(gt, imu), camera, calib.T_BS, config)
    return camera, [(f.t_ns, f.image, f.depth, f.T_WC) for f in seq.frames()]


def _load_asl(root: Path) -> tuple[object, list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]]:
    """(camera, frames) from an ASL folder with depth0 (poses: ground truth interpolated, T_WB T_BS)."""
    import cv2

    from vigs_core.geometry import interpolate_poses, quat_to_matrix
    from vigs_core.io import read_camera_yaml, read_euroc_camera, read_euroc_groundtruth
    from vigs_core.sim.writers import read_depth

    mav0 = root / "mav0"
    calib = read_camera_yaml(mav0 / "cam0" / "sensor.yaml")
    t_ns, paths = read_euroc_camera(mav0 / "cam0")
    gt = read_euroc_groundtruth(mav0 / "state_groundtruth_estimate0" / "data.csv")
    R = quat_to_matrix(torch.from_numpy(gt.quat_wxyz))
    R_q, p_q = interpolate_poses(
        torch.from_numpy(gt.t_s), R, torch.from_numpy(gt.position), torch.from_numpy(t_ns * 1e-9)
    )
    frames = []
    for i, (t, path) in enumerate(zip(t_ns, paths)):
        T_WB = np.eye(4)
        T_WB[:3, :3], T_WB[:3, 3] = R_q[i].numpy(), p_q[i].numpy()
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
        depth = read_depth(mav0 / "depth0" / "data" / f"{int(t)}.tiff")
        frames.append((int(t), image, depth, T_WB @ calib.T_BS))
    return calib.camera.pinhole(), frames


def _select_keyframes(poses: list[np.ndarray], min_translation: float, min_rotation_deg: float) -> list[int]:
    """Indices of keyframes: the first frame, then each frame that moved enough from the last keyframe."""
    keys = [0]
    for i in range(1, len(poses)):
        T_rel = np.linalg.inv(poses[keys[-1]]) @ poses[i]
        angle = math.degrees(math.acos(np.clip((np.trace(T_rel[:3, :3]) - 1) / 2, -1, 1)))
        if np.linalg.norm(T_rel[:3, 3]) > min_translation or angle > min_rotation_deg:
            keys.append(i)
    return keys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vigs bench mapping_quality", description=__doc__.splitlines()[0])
    parser.add_argument("--sequence", default="V1_01_easy", help="EuRoC sequence under /work/shared/data/euroc")
    parser.add_argument("--asl", type=Path, default=None, help="read a `vigs sim` ASL folder with depth0 instead")
    parser.add_argument("--start", type=float, default=10.0, help="start of the hybrid sequence (s)")
    parser.add_argument("--duration", type=float, default=10.0, help="length of the hybrid sequence (s)")
    parser.add_argument("--rgb", action="store_true", help="render colour instead of grey images")
    parser.add_argument("--kf-translation", type=float, default=0.15, help="keyframe translation threshold (m)")
    parser.add_argument("--kf-rotation", type=float, default=10.0, help="keyframe rotation threshold (deg)")
    parser.add_argument("--iterations", type=int, default=10, help="mapper iterations per keyframe")
    parser.add_argument(
        "--init-stride", type=int, default=MapperConfig.init_stride, help="pixel stride of new Gaussians"
    )
    parser.add_argument("--refine", type=int, default=300, help="final colour refinement iterations (0: none)")
    parser.add_argument("--eval-every", type=int, default=2, help="evaluate every n-th non-keyframe frame")
    parser.add_argument("--backends", nargs="+", default=["torch", "numba"], choices=["torch", "numba", "gsplat"],
                        help="rasterizer backends to compare (one mapping run each)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    t0 = time.perf_counter()
    camera, frames = _load_asl(args.asl) if args.asl else _load_hybrid(args)
    t_load = time.perf_counter() - t0
    keys = _select_keyframes([f[3] for f in frames], args.kf_translation, args.kf_rotation)
    key_set = set(keys)
    evals = [i for i in range(len(frames)) if i not in key_set][:: args.eval_every]

    columns = [_map_with(backend, args, camera, frames, keys, evals) for backend in args.backends]
    rows = [
        ("sequence", f"{args.asl or args.sequence} {args.start:g}+{args.duration:g} s, {len(frames)} frames"),
        ("resolution", f"{camera.width}x{camera.height} (render scale 1)"),
        ("keyframes", f"{len(keys)}"),
        ("iterations / keyframe", f"{args.iterations}"),
        ("init stride", f"{args.init_stride} px"),
        ("eval frames (non-keyframe)", f"{len(evals)}"),
        ("load/simulate time", f"{t_load:.1f} s"),
    ]
    names = [name for name, _ in columns[0]]
    print(f"| {'quantity'} | " + " | ".join(args.backends) + " |")
    print("| --- |" + " --- |" * len(args.backends))
    for name, value in rows:
        print(f"| {name} | " + " | ".join([value] * len(columns)) + " |")
    for i, name in enumerate(names):
        print(f"| {name} | " + " | ".join(col[i][1] for col in columns) + " |")
    print(f"| load average | {' '.join(f'{x:.2f}' for x in os.getloadavg())} |")
    return 0


def _warm_up(mapper: GaussianMapper, camera) -> None:
    """One differentiated render of a tiny scene: a compiled backend compiles (or loads its cache) here, not in
    the first keyframe's timing."""
    from vigs_core.mapping.rasterizer import RenderCamera

    means = torch.tensor([[0.0, 0.0, 2.0]], requires_grad=True)
    out = mapper.rasterizer(means, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.full((1, 3), 0.1),
                            torch.tensor([0.5]), torch.ones(1, 3), torch.eye(4), RenderCamera.from_camera(camera))
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()


def _map_with(backend: str, args, camera, frames, keys, evals) -> list[tuple[str, str]]:
    """Map the keyframes with ``backend`` from scratch, evaluate online and after refinement: table rows."""
    config = MapperConfig(iterations=args.iterations, init_stride=args.init_stride, render_scale=1.0, backend=backend)
    mapper = GaussianMapper(config, camera)
    _warm_up(mapper, camera)
    per_kf, cpu_kf = [], []
    usage0 = resource.getrusage(resource.RUSAGE_SELF)
    for kf_id, i in enumerate(keys):
        t_ns, image, depth, T_WC = frames[i]
        mapper.add_keyframe(kf_id, T_WC, image, depth, t_ns)
        t, c = time.perf_counter(), time.process_time()
        mapper.step()
        per_kf.append(time.perf_counter() - t)
        cpu_kf.append(time.process_time() - c)
    usage1 = resource.getrusage(resource.RUSAGE_SELF)
    user_kf = (usage1.ru_utime - usage0.ru_utime) / len(keys)
    sys_kf = (usage1.ru_stime - usage0.ru_stime) / len(keys)
    views = [(frames[i][3], frames[i][1]) for i in evals]
    online = mapper.evaluate(views)
    t = time.perf_counter()
    mapper.refine(args.refine)
    t_refine = time.perf_counter() - t
    refined = mapper.evaluate(views) if args.refine > 0 else {"psnr": math.nan, "ssim": math.nan}
    return [
        ("mapping time / keyframe", f"{np.mean(per_kf):.3f} s (median {np.median(per_kf):.3f}, max {max(per_kf):.3f})"),
        ("throughput (wall)", f"{len(keys) / sum(per_kf):.2f} keyframes/s"),
        ("CPU time / keyframe", f"{np.mean(cpu_kf):.3f} s ({len(keys) / sum(cpu_kf):.2f} keyframes per CPU-second)"),
        ("CPU time / keyframe: user + sys", f"{user_kf:.3f} + {sys_kf:.3f} s (incl. the keyframes' insertion)"),
        ("gaussians", f"{len(mapper.map)} (added {mapper.stats.added}, pruned {mapper.stats.pruned})"),
        ("map memory", f"{mapper.map.memory_bytes() / 2**20:.2f} MiB"),
        ("process peak RSS so far (incl. simulator)", f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB"),
        ("online PSNR / SSIM", f"{online['psnr']:.2f} dB / {online['ssim']:.3f}"),
        (f"after refinement ({args.refine} it)", f"{refined['psnr']:.2f} dB / {refined['ssim']:.3f} ({t_refine:.1f} s)"),
    ]


if __name__ == "__main__":
    raise SystemExit(main())
