"""Static detection and static initialisation on the real still start of EuRoC V1_01."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import torch

from vigs_core.geometry import quat_to_matrix
from vigs_core.imu.static_init import detect_static_segments, static_initialize
from vigs_core.io import read_euroc_groundtruth, read_euroc_imu
from vigs_core.types import ImuSamples

torch.set_num_threads(1)  # the test machine is shared; one thread each is fastest

DATA = Path(__file__).parent / "data" / "imu"


def unzip(name: str, tmp_path: Path) -> Path:
    out = tmp_path / name.removesuffix(".gz")
    with gzip.open(DATA / name, "rb") as src, open(out, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return out


def test_static_init_on_v1_01_still_start(tmp_path):
    imu = read_euroc_imu(unzip("V1_01_easy_imu.csv.gz", tmp_path))
    gt = read_euroc_groundtruth(unzip("V1_01_easy_groundtruth.csv.gz", tmp_path))
    segments = detect_static_segments(imu)
    assert len(segments) >= 1
    t0, t1 = segments[0]
    # the drone stands still for the first 4.7 s (motors on: the first second vibrates more)
    assert (t0 - imu.t_ns[0]) * 1e-9 < 2.0 and 2.5 < (t1 - imu.t_ns[0]) * 1e-9 < 4.8
    init = static_initialize(imu, t0, t1)
    gt_bias = gt.bias_gyro[np.searchsorted(gt.t_ns, t0)]
    assert np.abs(init.bias_gyro.numpy() - gt_bias).max() < 0.003
    assert abs(init.gravity_magnitude - 9.81) < 0.05
    # attitude: the estimated gravity-aligned R_wb agrees with ground truth in roll and pitch
    k = np.searchsorted(gt.t_ns, (t0 + t1) // 2)
    R_gt = quat_to_matrix(torch.as_tensor(gt.quat_wxyz[k]))
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    angle = torch.arccos((init.R_wb.T @ up).dot(R_gt.T @ up).clamp(-1, 1))
    assert float(angle) < np.radians(1.0)


def test_no_static_segment_in_constant_rotation():
    t = np.arange(0, 3_000_000_000, 5_000_000)
    rng = np.random.default_rng(0)
    moving = ImuSamples(t, np.tile([0.0, 0.0, 0.5], (len(t), 1)) + rng.normal(0, 0.3, (len(t), 3)),
                        np.tile([0.0, 0.0, 9.81], (len(t), 1)) + rng.normal(0, 1.0, (len(t), 3)))
    assert len(detect_static_segments(moving)) == 0
    still = ImuSamples(t, rng.normal(0, 0.003, (len(t), 3)), np.tile([0.0, 0.0, 9.81], (len(t), 1)))
    seg = detect_static_segments(still)
    assert len(seg) == 1 and seg[0, 0] == t[0] and seg[0, 1] == t[-1]
