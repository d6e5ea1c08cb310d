"""ATE agrees with evo's APE (translation part) and RPE with evo's (all pairs along the reference's path) on real
EuRoC ground truth, via the API and `vigs eval`."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface
from scipy.spatial.transform import Rotation

from vigs_core.eval import evaluate_trajectory
from vigs_core.io import read_euroc_groundtruth, read_trajectory, write_euroc_groundtruth, write_tum
from vigs_core.types import Trajectory

GT_CSV = Path(__file__).parent / "data" / "euroc_excerpt" / "mav0" / "state_groundtruth_estimate0" / "data.csv"
MAX_DIFF_S = 0.01


def perturbed_estimate(path: Path, fmt: str) -> Path:
    """The excerpt ground truth mapped by a known Sim(3), with 2 cm position noise, 0.1 deg orientation
    noise, up to 3 ms stamp jitter and 7 dropped poses; written as TUM text or EuRoC CSV."""
    gt = read_euroc_groundtruth(GT_CSV)
    rng = np.random.default_rng(42)
    rot = Rotation.from_rotvec([0.4, -1.3, 2.2])
    scale, trans = 0.63, np.array([4.0, -1.5, 0.8])
    keep = np.ones(len(gt), bool)
    keep[rng.choice(len(gt), size=7, replace=False)] = False
    position = scale * rot.apply(gt.position) + trans + rng.normal(scale=0.02, size=gt.position.shape)
    wobble = Rotation.from_rotvec(rng.normal(scale=np.radians(0.1), size=(len(gt), 3)))
    orientation = wobble * rot * Rotation.from_quat(gt.quat_wxyz, scalar_first=True)
    t_ns = gt.t_ns + rng.integers(-3_000_000, 3_000_000, size=len(gt))
    est = Trajectory(t_ns[keep], position[keep], orientation.as_quat(scalar_first=True)[keep])
    if fmt == "tum":
        write_tum(path, est)
    else:
        write_euroc_groundtruth(path, est)
    return path


def evo_ape(est_path: Path, fmt: str, correct_scale: bool) -> tuple[dict, float]:
    """APE translation statistics and Sim(3) scale computed entirely by evo (its own file readers)."""
    ref = file_interface.read_euroc_csv_trajectory(str(GT_CSV))
    if fmt == "tum":
        est = file_interface.read_tum_trajectory_file(str(est_path))
    else:
        est = file_interface.read_euroc_csv_trajectory(str(est_path))
    assert isinstance(est, PoseTrajectory3D)
    ref, est = sync.associate_trajectories(ref, est, max_diff=MAX_DIFF_S)
    _, _, scale = est.align(ref, correct_scale=correct_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_all_statistics(), float(scale)


CASES = [("se3", "tum"), ("sim3", "tum"), ("se3", "euroc"), ("sim3", "euroc")]


@pytest.mark.parametrize("mode, fmt", CASES)
def test_api_matches_evo(tmp_path, mode, fmt):
    est_path = perturbed_estimate(tmp_path / f"est.{fmt}", fmt)
    stats, scale = evo_ape(est_path, fmt, correct_scale=mode == "sim3")
    ours = evaluate_trajectory(
        read_trajectory(GT_CSV), read_trajectory(est_path), align=mode, max_diff_s=MAX_DIFF_S
    )
    assert ours["n_matched"] == 73
    for name in ("rmse", "mean", "median", "max"):
        assert abs(ours[f"ate_{name}"] - stats[name]) < 1e-6, name
    if mode == "sim3":
        assert abs(ours["scale"] - scale) < 1e-6
        assert ours["scale"] == pytest.approx(1 / 0.63, rel=0.03)  # the estimate was shrunk by 0.63
        assert ours["ate_rmse"] < 0.05
    else:
        assert ours["ate_rmse"] > 0.1  # SE(3) cannot undo the scale


@pytest.mark.parametrize("mode, fmt", CASES[:2])
def test_cli_json_matches_evo(tmp_path, mode, fmt):
    est_path = perturbed_estimate(tmp_path / f"est.{fmt}", fmt)
    stats, _ = evo_ape(est_path, fmt, correct_scale=mode == "sim3")
    command = [sys.executable, "-m", "vigs_cli.main", "eval", str(GT_CSV), str(est_path)]
    command += ["--align", mode, "--max-diff", str(MAX_DIFF_S), "--recall", "0.03", "0.5", "--json"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert abs(result["ate_rmse"] - stats["rmse"]) < 1e-6
    assert abs(result["ate_max"] - stats["max"]) < 1e-6
    assert set(result) >= {"recall@0.03", "recall@0.5", "scale", "ate_mean", "ate_median", "alignment"}
    assert result["recall@0.5"] <= 73 / 80  # 7 ground-truth poses have no estimate


def test_cli_table_rpe_and_errors(tmp_path):
    est_path = perturbed_estimate(tmp_path / "est.txt", "tum")
    command = [sys.executable, "-m", "vigs_cli.main", "eval", str(GT_CSV), str(est_path)]
    rpe_args = ["--rpe-delta", "1", "--rpe-unit", "s"]
    done = subprocess.run(command + rpe_args, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "ATE RMSE [m]" in done.stdout and "RPE pairs (1 s)" in done.stdout and "recall@0.05" in done.stdout
    bad = tmp_path / "bad.txt"
    bad.write_text("# t x y z qx qy qz qw\n1.0 0 0 0 0 0 0 1\n2.0 0 0\n")
    command = [sys.executable, "-m", "vigs_cli.main", "eval", str(GT_CSV), str(bad)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    assert f"{bad}, line 3: expected 8 columns" in done.stderr


@pytest.mark.parametrize("delta", [0.25, 1.0])
def test_rpe_matches_evo_all_pairs_from_the_reference(tmp_path, delta):
    """``evo_rpe --delta D --delta_unit m --all_pairs --pairs_from_reference`` after the same SE(3) alignment:
    the same pairs and the same translation and rotation statistics."""
    est_path = perturbed_estimate(tmp_path / "est.txt", "tum")
    ref = file_interface.read_euroc_csv_trajectory(str(GT_CSV))
    est = file_interface.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=MAX_DIFF_S)
    est.align(ref)
    evo_stats = {}
    for relation, name in ((metrics.PoseRelation.translation_part, "trans"),
                           (metrics.PoseRelation.rotation_angle_deg, "rot")):
        rpe = metrics.RPE(relation, delta=delta, delta_unit=metrics.Unit.meters, all_pairs=True,
                          pairs_from_reference=True)
        rpe.process_data((ref, est))
        evo_stats[name] = rpe.get_all_statistics()
        pairs = len(rpe.error)
    ours = evaluate_trajectory(read_trajectory(GT_CSV), read_trajectory(est_path), align="se3",
                               max_diff_s=MAX_DIFF_S, rpe_delta=delta, rpe_unit="m")
    assert ours["rpe_pairs"] == pairs > 10
    for name in ("rmse", "mean", "median", "max"):
        assert abs(ours[f"rpe_trans_{name}"] - evo_stats["trans"][name]) < 1e-6, name
        assert abs(ours[f"rpe_rot_{name}"] - evo_stats["rot"][name]) < 1e-6, name
