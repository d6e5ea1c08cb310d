"""End to end: a short rendered sequence (project simulator) through the dense odometry, the pipeline and
``vigs run`` on an EuRoC ASL folder."""
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel
from vigs_core.frontend import DenseOdometry, OdometryConfig
from vigs_core.heap import allocator
from vigs_core.io import read_tum, write_euroc_camera, write_euroc_groundtruth
from vigs_core.io.calibration import CameraCalibration, write_camera_yaml
from vigs_core.sim.render import Renderer
from vigs_core.sim.scene import build_room_scene
from vigs_core.solver import Intrinsics
from vigs_core.system import PipelineConfig, run_pipeline
from vigs_core.system.pipeline import poses_to_trajectory
from vigs_cli.main import main as vigs_main

ROOT = Path(__file__).resolve().parent.parent

torch.set_num_threads(1)
cv2.setNumThreads(1)
W, H, RATE, N = 192, 128, 20.0, 44
CAM = CameraModel(W, H, 120.0, 120.0, 95.5, 63.5)
# camera (x right, y down, z forward) looking along world +x, z up
R_WC0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BS = np.eye(4)
T_BS[:3, 3] = [0.05, -0.02, 0.01]


def camera_poses(t):
    """(N, 4, 4) T_WC: forward and sideways motion with a yaw and pitch sway."""
    T = np.tile(np.eye(4), (len(t), 1, 1))
    for k, s in enumerate(t):
        yaw, pitch = 0.15 * math.sin(1.3 * s), 0.05 * math.sin(2.1 * s)
        Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        Ry = np.array([[math.cos(pitch), 0, math.sin(pitch)], [0, 1, 0], [-math.sin(pitch), 0, math.cos(pitch)]])
        T[k, :3, :3] = Rz @ Ry @ R_WC0
        T[k, :3, 3] = [0.35 * s, 0.25 * math.sin(0.9 * s), 0.05 * math.sin(1.7 * s)]
    return T


@pytest.fixture(scope="module")
def sequence():
    t = np.arange(N) / RATE
    T_WC = camera_poses(t)
    scene = build_room_scene(np.concatenate((T_WC[:, :3, 3], T_WC[:, :3, 3] + [4.0, 0, 0])), seed=3)
    r = Renderer(scene, CAM)
    images = [(r.render(T, with_depth=False).image * 255).clip(0, 255).astype(np.uint8) for T in T_WC]
    t_ns = (1_000_000_000 + t * 1e9).astype(np.int64)
    return t_ns, images, T_WC


def test_odometry_tracks_every_frame_with_small_error(sequence):
    t_ns, images, T_WC = sequence
    cfg = OdometryConfig()
    cfg.keyframes.flow_threshold_px = 8.0
    cfg.init_min_parallax_px = 5.0
    odo = DenseOdometry(Intrinsics(CAM.fx, CAM.fy, CAM.cx, CAM.cy), W, H, cfg)
    for t, img in zip(t_ns, images):
        odo.process(int(t), img)
    assert odo.initialized
    ts, P = odo.final_frame_poses()
    assert len(ts) == N                                           # every frame has a pose
    assert len(odo.keyframes) >= 4 and odo.ba_calls >= 2
    from vigs_core.eval.alignment import umeyama
    est = np.linalg.inv(P.numpy())[:, :3, 3]
    gt = T_WC[:, :3, 3]
    s, R, tt = umeyama(est, gt, True)
    err = np.linalg.norm(s * est @ R.T + tt - gt, axis=1)
    path = np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()
    assert np.sqrt((err ** 2).mean()) < 0.02 * path               # < 2 % of the travelled distance
    # causal odometry exists for every frame too
    to, Po = odo.odometry_poses()
    assert len(to) == N


def write_asl(root, t_ns, images, T_WC):
    cam_dir = root / "mav0" / "cam0"
    for p, img in zip(write_euroc_camera(cam_dir, t_ns), images):
        cv2.imwrite(str(p), img)
    write_camera_yaml(cam_dir / "sensor.yaml", CameraCalibration(CAM, T_BS, RATE))
    T_WB = T_WC @ np.linalg.inv(T_BS)
    gt_dir = root / "mav0" / "state_groundtruth_estimate0"
    gt_dir.mkdir(parents=True)
    write_euroc_groundtruth(gt_dir / "data.csv", poses_to_trajectory(t_ns, T_WB))


def _vigs_run(sequence, tmp_path, switches: str) -> tuple[dict, Path]:
    """``vigs run`` on the sequence written as an ASL folder, with ``switches`` (YAML lines of the frontend's
    parameters, e.g. which parts are off); returns the report and the output folder."""
    t_ns, images, T_WC = sequence
    write_asl(tmp_path / "seq", t_ns, images, T_WC)
    params = tmp_path / "p.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    width: {W}\n    height: {H}\n    odometry:\n"
                      "      init_min_parallax_px: 5.0\n      keyframes:\n        flow_threshold_px: 8.0\n" + switches)
    out = tmp_path / "out"
    assert vigs_main(["run", str(tmp_path / "seq"), "--params", str(params), "--out", str(out),
                      "--no-progress"]) == 0
    return json.loads((out / "report.json").read_text()), out


def test_vigs_run_on_asl_folder_writes_outputs(sequence, tmp_path, capsys):
    report, out = _vigs_run(sequence, tmp_path, "    imu:\n      enabled: false\n    loop:\n      enabled: false\n")
    assert report["frames"] == N and report["frames_posed"] == N
    assert report["keyframes"] >= 4
    assert report["accuracy"]["recall@0.1"] == pytest.approx(1.0)
    assert report["accuracy"]["ate_rmse"] < 0.03
    assert report["frames_per_s"] > 0 and report["peak_rss_mb"] > 0 and report["allocator"] == allocator()
    assert {"flow", "tracking", "ba"} <= set(report["timings_s"])
    traj = np.loadtxt(out / "trajectory.txt")
    assert traj.shape == (N, 8)
    assert np.loadtxt(out / "keyframes.txt").shape[0] == report["keyframes"]
    assert np.loadtxt(out / "trajectory_cam.txt").shape == (N, 8)
    out_text = capsys.readouterr().out
    assert "ate_rmse" in out_text and "report.html" in out_text.splitlines()[-1]


def test_vigs_run_with_loop_closure_in_its_worker_process(sequence, tmp_path):
    """Loop closure on (by default in a child process): the run completes with the worker closed at the end, its
    counters and its peak memory reported, and the odometry as accurate as without it (no loop to find). The worker
    starts at the keyframe gap's keyframe (a run with fewer keyframes never starts it): a gap of 5 here, the run's
    keyframe count, so that it starts at the last keyframe, which has no candidate old enough."""
    report, _ = _vigs_run(sequence, tmp_path, "    imu:\n      enabled: false\n    mapping:\n      enabled: false\n"
                          "    loop:\n      detection:\n        min_keyframe_gap: 5\n")
    assert report["keyframes"] == 5
    assert report["frames_posed"] == N and report["accuracy"]["ate_rmse"] < 0.03
    assert report["loop"]["loops_found"] == 0 and report["loop"]["corrections_applied"] == 0
    assert report["loop"]["process_peak_rss_mb"] > 50   # a Python process with torch imported
    assert report["loop"]["queue_wait_seconds"] >= 0


def test_unreadable_frames_are_skipped_and_too_many_end_the_run_with_its_outputs(sequence, tmp_path, capsys):
    """A 0-byte PNG and a garbage PNG mid-sequence: skipped with a warning naming the file, listed in the report,
    every other frame posed. With ``max_bad_frames: 1`` the second one ends the run: exit 2 with a one-line
    message, and the trajectory and report of the frames before it are written (``error`` says why)."""
    t_ns, images, T_WC = sequence
    seq = tmp_path / "seq"
    write_asl(seq, t_ns, images, T_WC)
    frames = sorted((seq / "mav0" / "cam0" / "data").iterdir())
    frames[10].write_bytes(b"")
    frames[20].write_bytes(np.random.default_rng(0).integers(0, 255, 700, dtype=np.uint8).tobytes())
    params = tmp_path / "p.yaml"
    switches = (f"frontend:\n  ros__parameters:\n    width: {W}\n    height: {H}\n    odometry:\n"
                "      init_min_parallax_px: 5.0\n      keyframes:\n        flow_threshold_px: 8.0\n"
                "    imu: {enabled: false}\n    loop: {enabled: false}\n    mapping: {enabled: false}\n")
    params.write_text(switches)
    out = tmp_path / "out"
    assert vigs_main(["run", str(seq), "--params", str(params), "--out", str(out), "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [b["t_ns"] for b in report["bad_frames"]] == [int(t_ns[10]), int(t_ns[20])]
    assert report["frames_posed"] == N - 2 and report["error"] is None
    assert f"skipped: cannot read image {frames[10]}" in capsys.readouterr().err
    params.write_text(switches + "    max_bad_frames: 1\n")
    assert vigs_main(["run", str(seq), "--params", str(params), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "vigs run: 2 frames could not be read (max_bad_frames 1)" in err and "Traceback" not in err
    report = json.loads((out / "report.json").read_text())
    assert report["error"].startswith("ValueError: 2 frames") and report["frames"] == 19
    assert len(read_tum(out / "trajectory.txt")) == 19


@pytest.mark.parametrize("text, says", [
    ("    odometry:\n      no_such_key: 1\n", "unknown parameter odometry.'no_such_key'"),
    ("    width: abc\n", "parameter width: expected int, got 'abc' (str)"),
    ("    width: [1, 2]\n", "parameter width: expected int, got [1, 2] (list)"),
    ("    mapping: false\n", "parameter mapping: expected a mapping of MappingConfig fields, got False"),
    ("    imu: {max_speed: fast}\n", "parameter imu.max_speed: expected float, got 'fast'"),
    ("    imu: {enabled: 1}\n", "parameter imu.enabled: expected bool, got 1 (int)"),
    ("  [\n", "not valid YAML"),
    ("odometry:\n  flow: {patch_stride: 5}\n", "top-level 'odometry' is not a '<node>: ros__parameters:' section"),
])
def test_vigs_run_rejects_bad_params_in_one_line_naming_file_and_key(tmp_path, capsys, text, says):
    bad = tmp_path / "bad.yaml"
    bad.write_text("frontend:\n  ros__parameters:\n" + text)
    assert vigs_main(["run", str(tmp_path), "--params", str(bad), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vigs run: bad --params: {bad}: ") and says in err and err.count("\n") == 1, err


@pytest.mark.parametrize("option, value, says", [
    ("--stride", "0", "parameter frame_stride: expected a value in [1, inf), got 0"),
    ("--max-frames", "-5", "parameter max_frames: expected a value in [0, inf), got -5"),
    ("--refine", "-1", "parameter mapping.final_refine_iterations: expected a value in [0, inf), got -1"),
])
def test_vigs_run_checks_its_options_as_parameters(tmp_path, capsys, option, value, says):
    assert vigs_main(["run", str(tmp_path), option, value, "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vigs run: bad {option}: ") and says in err and err.count("\n") == 1, err


def test_vigs_run_refine_overrides_the_parameter_file(tmp_path, monkeypatch):
    """``--refine N`` sets ``mapping.final_refine_iterations`` over what ``--params`` says; the file's other
    mapping settings stay."""
    import vigs_core.system

    params = tmp_path / "p.yaml"
    params.write_text("frontend:\n  ros__parameters:\n    mapping: {final_refine_iterations: 30, eval_stride: 7}\n")
    seen = {}

    def fake_run(input_path, cfg, out_dir, **kwargs):
        seen["cfg"] = cfg
        return {"frames": 0, "frames_posed": 0, "keyframes": 0, "frames_per_s": 0.0, "peak_rss_mb": 0.0}

    monkeypatch.setattr(vigs_core.system, "run_pipeline", fake_run)
    assert vigs_main(["run", str(tmp_path), "--params", str(params), "--refine", "2000", "--out",
                      str(tmp_path / "o"), "--no-progress"]) == 0
    assert seen["cfg"].mapping.final_refine_iterations == 2000 and seen["cfg"].mapping.eval_stride == 7
    assert vigs_main(["run", str(tmp_path), "--params", str(params), "--out", str(tmp_path / "o"),
                      "--no-progress"]) == 0
    assert seen["cfg"].mapping.final_refine_iterations == 30


def test_vigs_run_rejects_bad_input(tmp_path):
    assert vigs_main(["run", str(tmp_path / "missing"), "--no-progress"]) == 2


def test_pipeline_config_overrides_and_validation():
    from vigs_core.system import apply_overrides
    cfg = apply_overrides(PipelineConfig(), {"width": 320, "odometry": {"graph": {"window": 6}}})
    assert cfg.width == 320 and cfg.odometry.graph.window == 6
    with pytest.raises(KeyError, match="expected one of"):
        apply_overrides(PipelineConfig(), {"odometry": {"graph": {"windw": 6}}})
    with pytest.raises(ValueError):
        apply_overrides(PipelineConfig(), {"odometry": {"solver_dtype": "float16"}})
    cfg = apply_overrides(PipelineConfig(), {"imu": {"max_speed": 5, "gravity": 9.8}, "max_frames": None,
                                             "loop": {"detection": {"thumbnail_size": [16, 12]}}})
    assert isinstance(cfg.imu.max_speed, float) and cfg.max_frames is None
    assert cfg.loop.detection.thumbnail_size == (16, 12)
    with pytest.raises(ValueError, match=r"thumbnail_size\[1\]: expected int"):
        apply_overrides(PipelineConfig(), {"loop": {"detection": {"thumbnail_size": [16, 1.5]}}})


def test_vigs_run_on_ros2_bag_with_groundtruth_beside_it(sequence, tmp_path):
    from vigs_core.io import write_tum
    from vigs_core.io.rosbag import BagWriter
    from vigs_core.types import ImuSamples

    t_ns, images, T_WC = sequence
    bag = tmp_path / "rec"
    t_imu = np.arange(t_ns[0], t_ns[-1] + 1, 5_000_000, dtype=np.int64)   # 200 Hz (content unused here)
    imu = ImuSamples(t_imu, np.zeros((len(t_imu), 3)), np.tile([0.0, 0.0, 9.81], (len(t_imu), 1)))
    writer = BagWriter(bag, CAM, T_BS, imu, groundtruth=None, image_format="png")
    for t, img in zip(t_ns, images):
        writer.write_frame(int(t), img)
    writer.close()
    write_tum(tmp_path / "rec_groundtruth_tum.txt", poses_to_trajectory(t_ns, T_WC @ np.linalg.inv(T_BS)))
    cfg = PipelineConfig(width=W, height=H)
    cfg.imu.enabled = False          # the bag's IMU is a placeholder; this tests the visual frontend
    cfg.loop.enabled = False
    cfg.odometry.init_min_parallax_px = 5.0
    cfg.odometry.keyframes.flow_threshold_px = 8.0
    report = run_pipeline(bag, cfg, tmp_path / "out", progress=False)
    assert report["frames_posed"] == N
    assert report["accuracy"]["ate_rmse"] < 0.03
    assert report["accuracy"]["n_matched"] == N


def test_unscaled_runs_are_scored_on_camera_poses():
    """A monocular trajectory exact up to scale 0.3: scored on camera poses it is exact; turned into body poses
    with the metric lever arm (what trajectory.txt holds) it is not, by an error no Sim(3) alignment removes."""
    from vigs_core.system.pipeline import _accuracy

    t = np.arange(N) / RATE
    t_ns = (1_000_000_000 + t * 1e9).astype(np.int64)
    T_WC = camera_poses(t)
    lever = np.eye(4)
    lever[:3, 3] = [0.3, -0.2, 0.1]                     # a large camera-IMU lever arm shows the effect clearly
    gt = poses_to_trajectory(t_ns, T_WC @ np.linalg.inv(lever))
    est_WC = T_WC.copy()
    est_WC[:, :3, 3] *= 0.3                              # arbitrary monocular scale
    cam = _accuracy(gt, t_ns, t_ns, est_WC, T_BX=lever)
    assert cam["frame"] == "camera" and cam["ate_rmse"] < 1e-9 and cam["scale"] == pytest.approx(1 / 0.3)
    body = _accuracy(gt, t_ns, t_ns, est_WC @ np.linalg.inv(lever))
    assert body["frame"] == "body" and body["ate_rmse"] > 0.01


def test_load_frames_reads_a_whole_input_at_the_processing_size(sequence, tmp_path):
    from vigs_core.system.pipeline import load_frames

    t_ns, images, T_WC = sequence
    write_asl(tmp_path / "seq", t_ns, images, T_WC)
    f = load_frames(tmp_path / "seq", W // 2, H // 2, duration_s=1.0)
    assert f.images.shape == (21, H // 2, W // 2) and f.images.dtype == np.uint8   # 0 .. 1.0 s at 20 Hz
    np.testing.assert_array_equal(f.t_ns, t_ns[:21])
    np.testing.assert_allclose(f.T_WB, T_WC[:21] @ np.linalg.inv(T_BS), atol=1e-9)
    assert (f.camera.width, f.camera.height) == (W // 2, H // 2)


def run_until_frame(cmd: list[str], frames: int, own_group: bool = False) -> tuple[subprocess.Popen, str]:
    """``cmd`` (a ``vigs run`` with its progress bar on the sample's 441 frames) started (``own_group``: as the
    leader of a new process group, as a shell's job) and read until the bar passed ``frames`` frames; the process
    and its stderr so far."""
    proc = subprocess.Popen(cmd, cwd=ROOT, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            process_group=0 if own_group else None)
    seen = ""
    while not any(int(n) >= frames for n in re.findall(r"\b(\d+)/441", seen)):
        # what the pipe holds, however little: a read of a fixed size waited for more once the bar's last line
        # was in, and with a long refinement after it that could be an hour
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, f"vigs run ended before {frames} frames: {seen[-2000:]}"
        seen += chunk.decode(errors="replace")
    return proc, seen


@pytest.mark.parametrize("signum, mapping, group", [(signal.SIGINT, True, False), (signal.SIGTERM, False, False),
                                                    (signal.SIGINT, True, True), (signal.SIGTERM, True, True)],
                         ids=["SIGINT mapping", "SIGTERM", "SIGINT to the group mapping",
                              "SIGTERM to the group mapping"])
def test_vigs_run_interrupted_writes_what_it_computed_and_leaves_no_child(tmp_path, signum, mapping, group):
    """Ctrl-C or SIGTERM mid-run (loop closure and mapping in child processes), to the run or to its whole process
    group (Ctrl-C in a terminal, ``kill -- -PGID``): the run stops at a frame boundary, writes trajectory, report
    (marked interrupted) and, with mapping, the map of every keyframe (the mapper's backlog inserted without
    refinement), and exits 128 + the signal; its children are gone."""
    import psutil

    from ros_bags import SAMPLE_BAG

    cmd = [sys.executable, "-c", "import signal, sys; from vigs_cli.main import main; "
           "signal.signal(signal.SIGINT, signal.default_int_handler); sys.exit(main())",
           "run", str(SAMPLE_BAG), "--out", str(tmp_path), "--params", str(tmp_path / "p.yaml")]
    (tmp_path / "p.yaml").write_text("frontend:\n  ros__parameters:\n"   # the loop worker started by frame 100
                                     f"    mapping: {{enabled: {str(mapping).lower()}}}\n"
                                     "    loop: {detection: {min_keyframe_gap: 3}}\n")
    proc, seen = run_until_frame(cmd, 100, own_group=group)
    children = psutil.Process(proc.pid).children(recursive=True)
    if group:
        os.killpg(proc.pid, signum)
    else:
        proc.send_signal(signum)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum, seen[-1000:] + err[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["interrupted"] == signal.Signals(signum).name and 100 <= report["frames"] < 441
    assert len(read_tum(tmp_path / "trajectory.txt")) == report["frames_posed"] > 0
    assert 'src="report_figures/trajectory.png"' in (tmp_path / "report.html").read_text()   # plotted too
    if mapping:
        from vigs_core.mapping.ply import read_ply_vertices

        assert report["mapping"]["interrupted"] and report["mapping"]["keyframes_mapped"] == report["keyframes"]
        assert len(read_ply_vertices(tmp_path / "map.ply")) == report["mapping"]["gaussians"] > 1000
        assert report["mapping"]["process_peak_rss_mb"] > 50   # the mapper's own process, torch imported
    # multiprocessing's resource tracker ends when it reads EOF from the exited parent: give it a moment
    _, alive = psutil.wait_procs(children, timeout=15)
    assert children and not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in alive)


def test_vigs_run_interrupted_while_the_map_is_finished_writes_everything(tmp_path):
    """Ctrl-C after the last frame, while the mapper drains its backlog or refines the map (``--refine`` far
    longer than the test): the drain or the refinement gives way within seconds, and the run writes trajectory,
    report (marked interrupted) and map, and exits 130 (it used to raise KeyboardInterrupt and write nothing)."""
    from ros_bags import SAMPLE_BAG

    from vigs_core.mapping.ply import read_ply_vertices

    cmd = [sys.executable, "-c", "import signal, sys; from vigs_cli.main import main; "
           "signal.signal(signal.SIGINT, signal.default_int_handler); sys.exit(main())",
           "run", str(SAMPLE_BAG), "--out", str(tmp_path), "--refine", "100000"]
    proc, seen = run_until_frame(cmd, 441)
    time.sleep(3.0)
    proc.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, seen[-1000:] + err[-3000:]
    assert time.monotonic() - t0 < 60
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["interrupted"] == "SIGINT" and report["frames"] == 441
    assert len(read_tum(tmp_path / "trajectory.txt")) == report["frames_posed"] > 0
    m = report["mapping"]
    assert m.get("interrupted") or 0 < m["refined"]["iterations"] < 100000, m
    assert len(read_ply_vertices(tmp_path / "map.ply")) == m["gaussians"] > 1000


def test_inputs_without_imu_or_recognisable_layout_are_named(sequence, tmp_path, capsys):
    """An ASL folder without imu0 runs vision-only with a warning saying so; a folder that is neither an ASL
    folder nor a bag is refused in one line."""
    from vigs_core.system.sources import MissingImuWarning, open_input

    t_ns, images, T_WC = sequence
    write_asl(tmp_path / "seq", t_ns[:3], images[:3], T_WC[:3])
    with pytest.warns(MissingImuWarning, match="vision only"):
        assert open_input(tmp_path / "seq").imu is None
    # three frames give no pose: the outputs are written, the report page is not, and the summary says so
    with pytest.warns(MissingImuWarning):
        assert vigs_main(["run", str(tmp_path / "seq"), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    captured = capsys.readouterr()
    wrote = captured.out.splitlines()[-1]
    assert wrote.startswith("wrote ") and "report.json" in wrote and "report.html" not in wrote, wrote
    assert "report.html not written" in captured.err and not (tmp_path / "out" / "report.html").exists()
    (tmp_path / "empty").mkdir()
    assert vigs_main(["run", str(tmp_path / "empty"), "--no-progress"]) == 2
    assert "neither an EuRoC ASL folder (with mav0/) nor a ROS bag" in capsys.readouterr().err


def test_vigs_run_killed_mid_run_leaves_its_last_checkpoint(tmp_path):
    """SIGKILL (no chance to write anything) mid-run: the outputs of the last checkpoint are there and load (the
    pose files and a partial report, each replaced atomically), and the loop-closure child does not outlive its
    parent."""
    import psutil

    from ros_bags import SAMPLE_BAG

    from vigs_core.io import read_frame_status

    (tmp_path / "p.yaml").write_text("frontend:\n  ros__parameters:\n    mapping: {enabled: false}\n"
                                     "    checkpoint_period_s: 0.5\n")
    proc, _ = run_until_frame([sys.executable, "-m", "vigs_cli.main", "run", str(SAMPLE_BAG), "--out", str(tmp_path),
                               "--params", str(tmp_path / "p.yaml")], 200)
    children = psutil.Process(proc.pid).children(recursive=True)
    proc.kill()
    proc.communicate(timeout=60)
    report = json.loads((tmp_path / "report.json").read_text())
    # each file is whole; a kill between a checkpoint's pose files and its report leaves the poses one ahead
    assert report["partial"] and 100 < report["frames"] < 441 and report["frames_posed"] > 100
    assert 0 <= len(read_tum(tmp_path / "trajectory.txt")) - report["frames_posed"] <= 40
    assert 0 <= len(read_frame_status(tmp_path / "frame_status.txt")) - report["frames"] <= 40
    assert 0 <= len(read_tum(tmp_path / "keyframes.txt")) - report["keyframes"] <= 10
    assert not list(tmp_path.glob("*.tmp"))
    _, alive = psutil.wait_procs(children, timeout=15)
    assert not any(c.is_running() and c.status() != psutil.STATUS_ZOMBIE for c in alive), alive


def test_frames_arriving_during_keyframe_work_are_tracked_there_and_replayed_alike(sequence, tmp_path):
    """A live caller tracks a frame that arrives during a keyframe's work at the work's next yield point
    (``DenseOdometry.interleave``): the frame is posed at once, against the new keyframe, never becomes a keyframe,
    and the final trajectory stays as accurate; ``vigs run`` replaying the recorded schedule
    (``frames_processed.txt``: stamp and yield point) gives the same trajectory."""
    from vigs_core.eval.alignment import umeyama
    from vigs_core.io import read_frame_schedule, write_frame_schedule
    from vigs_core.system import OdometryStream

    t_ns, images, T_WC = sequence
    cfg = PipelineConfig(width=W, height=H)
    cfg.imu.enabled = cfg.loop.enabled = cfg.mapping.enabled = False
    cfg.odometry.init_min_parallax_px = 5.0
    cfg.odometry.keyframes.flow_threshold_px = 8.0
    stream = OdometryStream(CAM, cfg)
    odo = stream.odometry
    arrivals = iter(zip(t_ns, images))
    schedule, nested_poses, passed = [], {}, []

    def feed(t, img):
        posed = []
        stream.add_image(int(t), img, posed.append)
        nested = odo.in_keyframe_work
        schedule.append((int(t), odo.yield_points if nested else None))
        if nested:
            assert len(posed) == 1   # the pose is out before the keyframe work goes on
            nested_poses[int(t)] = posed[0]

    def at_yield_point():   # a frame arrives every second yield point (live: during the keyframe work)
        passed.append(odo.yield_points)
        if len(passed) % 2 == 0:
            item = next(arrivals, None)
            if item is not None:
                feed(*item)

    odo.interleave = at_yield_point
    for t, img in arrivals:
        feed(t, img)
    assert len(schedule) == N and len(nested_poses) >= 3, schedule
    keyframe_stamps = {kf.t_ns for kf in odo.keyframes.values()}
    assert not keyframe_stamps & set(nested_poses)   # a frame tracked during keyframe work is no candidate
    ts, P = odo.final_frame_poses()
    assert len(ts) == N
    est, gt = np.linalg.inv(P.numpy())[:, :3, 3], T_WC[:, :3, 3]
    s, R, tt = umeyama(est, gt, True)
    err = np.linalg.norm(s * est @ R.T + tt - gt, axis=1)
    assert np.sqrt((err ** 2).mean()) < 0.02 * np.linalg.norm(np.diff(gt, axis=0), axis=1).sum()

    write_asl(tmp_path / "seq", t_ns, images, T_WC)
    write_frame_schedule(tmp_path / "frames_processed.txt", schedule)
    report = run_pipeline(tmp_path / "seq", cfg, tmp_path / "out", progress=False,
                          schedule=read_frame_schedule(tmp_path / "frames_processed.txt"))
    assert report["frames_skipped"] == 0
    replay = read_tum(tmp_path / "out" / "trajectory_cam.txt")
    np.testing.assert_array_equal(replay.t_ns, ts)
    np.testing.assert_allclose(replay.position, np.linalg.inv(P.numpy())[:, :3, 3], atol=1e-6)
