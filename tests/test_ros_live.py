"""The node graph live, on a starved CPU: the replay publishes at the recorded rate (``--rate 1``, as a robot's
drivers do) while busy processes take the cores, so the frontend cannot track every frame.

The recording is the first ``PREFIX_S`` seconds of the shipped sample (1.3 s at rest, the IMU initialisation about
10 s in when every frame is tracked). Checked:

* frames are skipped and reported as the CPU's doing (``frames_skipped``, the ``behind`` warning), never
  silently: every image the frontend received is tracked or skipped, and the images lost before it (subscription
  queue, transport) are counted from the gaps in the stamps;
* no queue grows without bound: at most ``image_queue_depth`` frames wait, and the IMU samples waiting for the
  tracking thread stay below ``MAX_IMU_QUEUE`` (the IMU of ``MAX_IMU_QUEUE / 200`` s);
* latency stays bounded: image arrival to odometry publish p95 below ``MAX_P95_MS`` (the frontend's own
  measure; measured here with three busy processes: 47 ms, 79 of 400 frames skipped);
* the IMU initialises and the trajectory after it stays within ``GT_SE3_ATE_M`` of the ground truth (SE(3));
* ``vigs run --frames-from frames_processed.txt`` (the same input with the same skips, each frame tracked at the
  same point of the keyframe work) gives the same trajectory to ``RUN_MATCH_M``: the node and ``vigs run`` drive
  the same streaming core the same way. They agree to 4e-7-2e-6 m at the start; through the run's BA solves
  the difference grew to 1.4 mm and 11 mm in two runs (about half the frames tracked during keyframe work; 0.09
  mm before frames were interleaved, cause of the growth not found). The same replay with the frames' yield
  points left out differed by 9.9 cm.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from ros_bags import SAMPLE_BAG as BAG, SAMPLE_GT as GT, write_prefix
from ros_helpers import isolated_env

from vigs_core.eval import evaluate_trajectory
from vigs_core.io import read_tum

ROOT = Path(__file__).resolve().parent.parent
PREFIX_S = 20.0
BUSY = 3
MAX_P95_MS = 500.0
MAX_IMU_QUEUE = 1000
GT_SE3_ATE_M = 0.15
RUN_MATCH_M = 0.03


@pytest.fixture(scope="module")
def starved(tmp_path_factory):
    """``vigs launch --bag PREFIX --rate 1`` (frontend and IMU node) beside ``BUSY`` busy processes."""
    base = tmp_path_factory.mktemp("live")
    bag = base / "prefix"
    n_images = write_prefix(BAG, bag, PREFIX_S)
    out = base / "graph"
    out.mkdir()
    params = out / "params.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    output_dir: {out}\n")
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(BUSY)]
    try:
        cmd = [sys.executable, "-m", "vigs_cli.main", "launch", "--bag", str(bag), "--rate", "1", "--params",
               str(params), "--nodes", "imu_preintegration", "frontend", "--linger", "3"]
        proc = subprocess.run(cmd, cwd=ROOT, env=isolated_env(), capture_output=True, text=True, timeout=300)
    finally:
        for b in busy:
            b.kill()
            b.wait()
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    return bag, out, json.loads((out / "frontend_report.json").read_text()), n_images


def test_frames_are_skipped_and_reported_with_bounded_queues_and_latency(starved):
    _, _, report, n_images = starved
    assert report["frames_skipped"] > 0, report
    # images lost before the node (its queue, the transport) are counted too, from the gaps in the stamps
    assert n_images - 3 <= report["frames_in"] + report["frames_lost_before_node"] <= n_images, report
    assert report["counters"].get("warn.behind", 0) > 0
    assert report["frames_tracked"] + report["frames_skipped"] + report["frames_pending_at_shutdown"] == \
        report["frames_in"]
    assert report["queue_max"]["frames"] <= 10 and report["queue_max"]["imu_samples"] < MAX_IMU_QUEUE, report
    assert report["odometry_latency_ms"]["p95"] < MAX_P95_MS, report


def test_imu_initialises_and_the_trajectory_follows_the_groundtruth(starved):
    _, out, report, _ = starved
    assert report["inertial_initialized_at_s"] is not None, report
    result = evaluate_trajectory(read_tum(GT), read_tum(out / "trajectory.txt"), align="se3", max_diff_s=1e-3)
    assert result["ate_rmse"] < GT_SE3_ATE_M, result


def test_vigs_run_with_the_same_skips_gives_the_same_trajectory(starved, tmp_path):
    bag, out, _, _ = starved
    cmd = [sys.executable, "-m", "vigs_cli.main", "run", str(bag), "--params", str(ROOT / "params/frontend.yaml"),
           "--out", str(tmp_path), "--no-progress", "--frames-from", str(out / "frames_processed.txt")]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    node, run = read_tum(out / "trajectory.txt"), read_tum(tmp_path / "trajectory.txt")
    np.testing.assert_array_equal(node.t_ns, run.t_ns)
    diff = np.linalg.norm(node.position - run.position, axis=1)
    assert diff.max() < RUN_MATCH_M, f"node vs vigs run: max position difference {diff.max():.5f} m"
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["frames_skipped"] > 0
