"""The Gaussian mapper in a child process (:mod:`vigs_core.mapping.process`): the same map as the mapper in
this process, the child's errors raised by the caller, Ctrl-C left to the parent, and no process or spill folder
left behind, whether the parent closes it or dies."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import fields

import numpy as np
import pytest
import torch
from mapping_scenes import orbit_pose, raycast

from vigs_core.camera import CameraModel
from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.mapper import GaussianMapper, MapperConfig
from vigs_core.mapping.ply import load_map
from vigs_core.mapping.process import MapperProcess, MappingProcessError
from vigs_core.spill import SpillConfig

torch.set_num_threads(1)
CAMERA = CameraModel(96, 64, 60.0, 60.0, 47.5, 31.5)


def _config(**kw) -> MapperConfig:
    return MapperConfig(render_scale=1.0, init_stride=2, backend="torch", **kw)


def _feed(mapper, angles, first_id: int = 0) -> None:
    for i, a in enumerate(angles):
        T = orbit_pose(a)
        image, depth = raycast(T, CAMERA)
        mapper.add_keyframe(first_id + i, T, image, depth, timestamp_ns=1000 * (first_id + i))


def _assert_same_map(a: GaussianMap, b: GaussianMap) -> None:
    assert len(a) == len(b) > 0
    for f in fields(GaussianMap):
        torch.testing.assert_close(getattr(a, f.name), getattr(b, f.name))


def test_the_mapper_process_builds_the_same_map_as_the_mapper_here(tmp_path):
    here = GaussianMapper(_config(iterations=4), CAMERA)
    child = MapperProcess(_config(iterations=4), CAMERA)
    try:
        for mapper in (here, child):
            _feed(mapper, [0.0, 0.3, 0.6])
        here.process_pending()
        child.wait_idle()
        _assert_same_map(here.snapshot(), child.snapshot())
        moved = orbit_pose(0.3).clone()
        moved[:3, 3] += torch.tensor([0.0, 0.05, 0.0], dtype=moved.dtype)
        for mapper in (here, child):   # a loop correction: pose and depth scale of keyframe 1
            mapper.update_keyframe_poses({1: moved}, {1: 1.1})
            _feed(mapper, [0.9], first_id=3)
        here.process_pending()
        child.wait_idle()
        _assert_same_map(here.snapshot(), child.snapshot())
        views = [(orbit_pose(a), raycast(orbit_pose(a), CAMERA)[0]) for a in (0.15, 0.45)]
        assert child.evaluate(views) == pytest.approx(here.evaluate(views))
        here.refine(5)
        child.refine(5)
        _assert_same_map(here.snapshot(), child.snapshot())
        summary, expected = child.summary(), here.summary()
        assert (summary.stats.keyframes, summary.stats.steps, summary.gaussians) == \
            (expected.stats.keyframes, expected.stats.steps, expected.gaussians) == (4, 16, len(here.map))
        assert summary.render_size == (96, 64) and summary.stats.pose_updates == 1
        child.save(tmp_path / "map.ply")
        gmap, doc = load_map(tmp_path / "map.ply")
        assert len(gmap) == len(here.map) and len(doc["keyframes"]) == 4
    finally:
        child.close()
        here.close()
    assert child.channel.process.exitcode == 0


def test_an_error_in_the_mapper_process_is_raised_by_the_next_call_and_the_process_goes_on(tmp_path):
    child = MapperProcess(_config(), CAMERA)
    try:
        child.add_keyframe(0, torch.eye(4), np.zeros((64, 96, 7), np.float32), np.ones((64, 96), np.float32))
        with pytest.raises(MappingProcessError, match=r"keyframe image must be .* got shape \(64, 96, 7\)"):
            child.summary()
        _feed(child, [0.0])
        child.wait_idle()
        assert child.summary().stats.keyframes == 1
        (tmp_path / "a_file").write_text("")
        with pytest.raises(MappingProcessError, match="a_file"):
            child.save(tmp_path / "a_file" / "map.ply")
        assert child.summary().stats.keyframes == 1
    finally:
        child.close()


def test_ctrl_c_is_left_to_the_parent_and_close_leaves_no_process_or_spill_folder(tmp_path):
    child = MapperProcess(_config(iterations=2, keyframe_store=SpillConfig(resident=1, directory=str(tmp_path))),
                          CAMERA)
    try:
        _feed(child, [0.0, 0.3, 0.6])
        child.wait_idle()
        pid = child.channel.process.pid
        assert os.getpgid(pid) == pid != os.getpgid(0)   # a group of its own: signals to ours are not its
        with open(f"/proc/{pid}/comm") as f:
            assert f.read().strip() == "vigs-mapper"     # what ps and vigs bench soak show
        with open(f"/proc/{pid}/status") as f:           # blocked from its start, before its handler was set
            blocked = int(next(line for line in f if line.startswith("SigBlk:")).split()[1], 16)
        assert blocked & (1 << (signal.SIGINT - 1))
        os.kill(pid, signal.SIGINT)   # as Ctrl-C would, had it reached the child
        time.sleep(0.5)
        assert child.channel.process.is_alive()
        summary = child.summary()
        assert summary.stats.keyframes == 3 and summary.keyframes_on_disk == 2
        assert any(tmp_path.iterdir())
    finally:
        child.close()
    assert child.channel.process.exitcode == 0
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(MappingProcessError, match="closed"):
        _feed(child, [0.9])


def test_the_mapper_process_ends_when_its_parent_is_killed(tmp_path):
    script = ("import sys, time\n"
              "from vigs_core.camera import CameraModel\n"
              "from vigs_core.mapping.mapper import MapperConfig\n"
              "from vigs_core.mapping.process import MapperProcess\n"
              "m = MapperProcess(MapperConfig(backend='torch'), CameraModel(96, 64, 60.0, 60.0, 47.5, 31.5))\n"
              "m.summary()\n"
              "print(m.channel.process.pid, flush=True)\n"
              "time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        child_pid = int(parent.stdout.readline())
        os.kill(child_pid, 0)   # it runs
        parent.kill()           # SIGKILL: no clean-up in the parent
        parent.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _alive(child_pid):
            time.sleep(0.1)
        assert not _alive(child_pid)
    finally:
        parent.kill()
        parent.stdout.close()


def _alive(pid: int) -> bool:
    """The process ``pid`` runs (a zombie whose parent died is reaped by init and counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(") ", 1)[1][0] != "Z"
    except FileNotFoundError:
        return False
