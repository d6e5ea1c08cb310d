"""Checkpoints keep a run's outputs current without stalling tracking: the caller's thread computes the poses,
a thread of its own writes the files (their text grows with the run), a checkpoint due while one is being
written waits for the next period, and :meth:`Checkpoints.wait` lets the final outputs come last."""
import threading
import time

import numpy as np
import torch

from vigs_core.io import read_tum
from vigs_core.system import pipeline
from vigs_core.system.pipeline import Checkpoints


class FakeOdometry:
    """The reads of ``pose_outputs``: ``n`` frames along x, one keyframe."""

    def __init__(self, n: int) -> None:
        self.n, self.keyframes = n, {0: None}

    def _poses(self) -> tuple[np.ndarray, torch.Tensor]:
        T = torch.eye(4, dtype=torch.float64).repeat(self.n, 1, 1)
        T[:, 0, 3] = -torch.arange(self.n, dtype=torch.float64)   # world->camera: the camera at x = i
        return np.arange(self.n, dtype=np.int64) * 50_000_000, T

    final_frame_poses = odometry_poses = _poses

    def keyframe_poses(self) -> tuple[np.ndarray, torch.Tensor]:
        t, T = self._poses()
        return t[:1], T[:1]


def test_the_files_are_written_off_the_callers_thread_and_the_final_outputs_come_last(tmp_path, monkeypatch):
    writers = []
    write = pipeline.write_pose_outputs

    def slow_write(*args):
        writers.append(threading.current_thread())
        time.sleep(0.5)
        write(*args)

    monkeypatch.setattr(pipeline, "write_pose_outputs", slow_write)
    checkpoints = Checkpoints(tmp_path, period_s=1e-3, map_period_s=0.0)
    time.sleep(0.01)
    t0 = time.monotonic()
    checkpoints.step(FakeOdometry(10), np.eye(4), 10, None)
    assert time.monotonic() - t0 < 0.3   # the caller does not wait for the files
    time.sleep(0.01)
    checkpoints.step(FakeOdometry(20), np.eye(4), 20, None)   # due, but the first is still being written
    checkpoints.wait()
    assert len(writers) == 1 and writers[0] is not threading.current_thread()
    assert len(read_tum(tmp_path / "trajectory.txt").t_ns) == 10
    assert (tmp_path / "report.json").exists()
    checkpoints.step(FakeOdometry(30), np.eye(4), 30, None)   # the next period's checkpoint is written again
    checkpoints.wait()
    trajectory = read_tum(tmp_path / "trajectory.txt")
    assert len(writers) == 2 and len(trajectory.t_ns) == 30 and trajectory.position[-1, 0] == 29.0
