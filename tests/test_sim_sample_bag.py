"""The shipped sample recording in bags/: size, length, contents and ground truth beside it."""
import itertools
from pathlib import Path

import numpy as np

from vigs_core.io import read_tum
from vigs_core.io.rosbag import read_bag

BAGS = Path(__file__).resolve().parent.parent / "bags"
SAMPLE = BAGS / "v1_01_easy_hybrid_376x240"


def test_sample_bag_is_a_long_enough_small_enough_visual_inertial_recording():
    size = sum(f.stat().st_size for f in SAMPLE.rglob("*") if f.is_file())
    assert size <= 30e6
    rec = read_bag(SAMPLE)
    assert rec.camera is not None and (rec.camera.width, rec.camera.height) == (376, 240)
    assert rec.T_BS is not None and np.allclose(rec.T_BS[3], [0, 0, 0, 1])
    assert rec.image_count >= 20 * 20
    first = list(itertools.islice(rec.images(), 3))
    assert all(img.shape == (240, 376) and img.dtype == np.uint8 for _, img in first)
    t_first = first[0][0]
    span_s = (rec.imu.t_ns[-1] - rec.imu.t_ns[0]) * 1e-9
    assert span_s >= 20.0 and rec.imu.t_ns[0] <= t_first
    rate = (len(rec.imu) - 1) / span_s
    assert abs(rate - 200.0) < 1.0
    gt_files = list(BAGS.glob("v1_01_easy_hybrid_376x240*groundtruth*"))
    assert len(gt_files) == 1
    gt = read_tum(gt_files[0])
    np.testing.assert_array_equal(gt.t_ns, rec.groundtruth.t_ns)
    np.testing.assert_allclose(gt.position, rec.groundtruth.position, atol=1e-9)
    assert np.linalg.norm(np.diff(gt.position, axis=0), axis=1).sum() > 5.0  # it moves
    assert "vigs sim" in (BAGS / "README.md").read_text()
