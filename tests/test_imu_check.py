"""imu-check: defect detection on a doctored stream, and the command line on a EuRoC folder and a ROS 2 bag."""
from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import numpy as np
import torch

from vigs_cli.main import main
from vigs_core.imu.check import check_imu, format_report
from vigs_core.io import read_camera_yaml, read_euroc_imu
from vigs_core.types import ImuNoise, ImuSamples

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

DATA = Path(__file__).parent / "data" / "imu"


def unzip(name: str, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(DATA / name, "rb") as src, open(dst, "wb") as out:
        shutil.copyfileobj(src, out)
    return dst


def euroc_folder(root: Path) -> Path:
    """A minimal EuRoC sequence from the shipped V1_01 excerpt (IMU, its YAML, ground truth)."""
    mav0 = root / "V1_01_excerpt" / "mav0"
    unzip("V1_01_easy_imu.csv.gz", mav0 / "imu0" / "data.csv")
    shutil.copy(DATA / "imu0_sensor.yaml", mav0 / "imu0" / "sensor.yaml")
    unzip("V1_01_easy_groundtruth.csv.gz", mav0 / "state_groundtruth_estimate0" / "data.csv")
    return mav0.parent


def test_reports_doctored_defects():
    rng = np.random.default_rng(1)
    t = np.arange(0, 6_000_000_000, 5_000_000) + rng.integers(-20_000, 20_000, 1200)  # 200 Hz, 20 us jitter
    gyro = rng.normal(0, 0.002, (len(t), 3)) + [0.01, -0.02, 0.03]
    acc = rng.normal(0, 0.02, (len(t), 3)) + [0.0, 0.0, 9.80]
    acc[700:720, 0] = 16.0  # clipped accelerometer axis
    acc[700:720, 1:] = 0.0
    keep = np.ones(len(t), bool)
    keep[500:520] = False  # a 100 ms gap
    t, gyro, acc = t[keep], gyro[keep], acc[keep]
    t = np.insert(t, 100, t[100])  # one duplicate
    gyro, acc = np.insert(gyro, 100, gyro[100], 0), np.insert(acc, 100, acc[100], 0)
    t[[300, 301]] = t[[301, 300]]  # one swap
    report = check_imu(ImuSamples(t, gyro, acc), ImuNoise())
    assert report["duplicates"] == 1 and report["out_of_order"] == 1
    assert report["gaps"]["count"] == 1 and 100 <= report["gaps"]["longest_ms"] <= 106
    assert report["saturation"]["acc"]["samples"] == 20 and report["saturation"]["gyro"]["samples"] == 0
    assert abs(report["rate_hz"] - 200) < 1
    assert 0.005 < report["jitter_std_ms"] < 0.03
    assert len(report["static_segments"]) >= 1
    seg = report["static_segments"][0]
    np.testing.assert_allclose(seg["gyro_bias"], [0.01, -0.02, 0.03], atol=1e-3)
    # white noise of 0.002 rad/s at 200 Hz is a density of 0.002 / sqrt(200)
    assert abs(seg["implied_gyro_noise_density"] / (0.002 / np.sqrt(200)) - 1) < 0.1
    assert abs(report["gravity_magnitude"] - 9.80) < 0.01
    text = format_report(report)
    assert "duplicates       1" in text and "gaps             1" in text


def test_cli_on_euroc_folder_json(tmp_path, capsys):
    seq = euroc_folder(tmp_path)
    assert main(["imu-check", str(seq), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["samples"] == 3201 and abs(report["rate_hz"] - 200) < 0.01
    assert report["gaps"]["count"] == 0 and report["out_of_order"] == 0
    still = report["static_segments"][0]
    assert still["start_s"] < 2.0 and abs(still["gravity_magnitude"] - 9.81) < 0.05
    c = report["preintegration_consistency"]
    assert c["bias_source"] == "ground truth" and c["windows"] >= 10
    # EuRoC's datasheet densities understate the vibrating platform's noise: NEES/dof well above 1, and the
    # verdict says by how much to inflate them
    assert 1 < c["mean_nees_per_dof"] < 1e4
    factor = np.sqrt(c["mean_nees_per_dof"])
    assert c["verdict"].startswith("optimistic") and f"{factor:.1f}x" in c["verdict"]
    # gravity magnitude that best explains the ground-truth motion with the ground truth's biases
    assert abs(c["gravity_magnitude_fit"] - 9.81) < 0.05, c["gravity_magnitude_fit"]


def test_nees_verdicts():
    from vigs_core.imu.check import nees_verdict

    assert nees_verdict(1.0).startswith("consistent") and nees_verdict(1.9).startswith("consistent")
    assert "2.0x" in nees_verdict(4.0) and nees_verdict(4.0).startswith("optimistic")
    assert nees_verdict(0.25).startswith("pessimistic") and "0.50x" in nees_verdict(0.25)


def test_cli_counts_the_disorder_of_a_shuffled_file(tmp_path, capsys):
    """The file's rows as recorded: a reader that sorted first would report a shuffled IMU as clean."""
    seq = euroc_folder(tmp_path)
    csv = seq / "mav0" / "imu0" / "data.csv"
    header, *rows = csv.read_text().splitlines()
    rows[100], rows[101] = rows[101], rows[100]
    rows[2000], rows[2003] = rows[2003], rows[2000]   # 2003, 2001, 2002, 2000: two stamps step back
    csv.write_text("\n".join([header, *rows]) + "\n")
    assert main(["imu-check", str(seq), "--json", "--no-gt"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["out_of_order"] == 3 and report["samples"] == 3201


def test_cli_on_ros2_bag(tmp_path, capsys):
    from vigs_core.io.rosbag import BagWriter

    imu = read_euroc_imu(unzip("V2_01_easy_imu.csv.gz", tmp_path / "imu.csv"))
    calib = read_camera_yaml(DATA / "cam0_sensor.yaml")
    writer = BagWriter(tmp_path / "bag", calib.camera, calib.T_BS, imu)
    writer.close()
    assert main(["imu-check", str(tmp_path / "bag")]) == 0
    out = capsys.readouterr().out
    assert f"samples          {len(imu)}" in out and "rate             200.00 Hz" in out


def test_cli_reports_missing_input(tmp_path, capsys):
    assert main(["imu-check", str(tmp_path / "nothing")]) == 1
    assert "not found" in capsys.readouterr().err


def test_still_segments_from_the_ground_truth_motion():
    """A trajectory that stands still 2 s (with motion-capture noise), moves 3 s, then stands 1 s: two segments."""
    from vigs_core.imu.static_init import still_segments_from_motion
    from vigs_core.types import Trajectory

    rng = np.random.default_rng(0)
    t = np.arange(0, 6.0, 0.005)
    x = np.where(t < 2, 0.0, np.where(t < 5, 0.5 * (t - 2), 1.5))
    pos = np.stack([x, np.zeros_like(t), np.ones_like(t)], 1) + rng.normal(0, 2e-4, (len(t), 3))
    quat = np.tile([1.0, 0, 0, 0], (len(t), 1))
    segments = still_segments_from_motion(Trajectory((t * 1e9).astype(np.int64), pos, quat)) * 1e-9
    assert segments.shape == (2, 2)
    np.testing.assert_allclose(segments, [[0.0, 2.0], [5.0, 6.0]], atol=0.15)


def test_the_shipped_sample_stands_still_by_its_ground_truth(capsys):
    """The sample's multirotor vibrates at rest as in flight, so the IMU alone finds no static segment; its
    ground truth stands still for about its first second: the segment, its gyro bias and |g| are reported."""
    sample = Path(__file__).resolve().parent.parent / "bags" / "v1_01_easy_hybrid_376x240"
    assert main(["imu-check", str(sample), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    (still,) = report["static_segments"]
    assert still["found_by"] == "ground-truth motion" and still["start_s"] < 0.1 and 0.8 < still["duration_s"] < 1.5
    assert abs(report["gravity_magnitude"] - 9.81) < 0.05
    assert "ground-truth motion" in report["gravity_source"]
    # the real V1_01 gyro bias (EuRoC's estimate) is about (-0.002, 0.025, 0.082) rad/s
    np.testing.assert_allclose(still["gyro_bias"], [-0.002, 0.025, 0.082], atol=0.01)
