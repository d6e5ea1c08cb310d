"""ROS-side helpers without a graph: REP-105 frames, IMU buffering and frame synchronisation, parameter files
(every shipped key is declared by its node), remap parsing, process priority."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vigs_core.geometry import se3_exp
from vigs_ros.frames import Rep105Frames, body_from_camera, camera_from_body, invert, matrix_from_param
from vigs_ros.params import dataclass_specs, default_params_files, load_params_file, nested
from vigs_ros.replay import parse_remaps
from vigs_core.imu.buffer import ImuBuffer, ImuBufferConfig
from vigs_ros.time_sync import FrameSynchronizer


def pose(seed: int, scale: float = 1.0) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    return se3_exp(scale * torch.randn(6, generator=g, dtype=torch.float64)).numpy()


def test_invert_and_extrinsics():
    T, T_bc = pose(0), pose(1)
    np.testing.assert_allclose(T @ invert(T), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(camera_from_body(body_from_camera(T, T_bc), T_bc), T, atol=1e-12)


def test_rep105_odom_is_continuous_across_a_correction():
    frames = Rep105Frames()
    step = pose(2, 0.05)
    T = np.eye(4)
    odoms = []
    for _ in range(3):
        T = T @ step
        T_map_odom, T_odom_base = frames.update(T)
        np.testing.assert_allclose(T_map_odom, np.eye(4))
        odoms.append(T_odom_base)
    jump = pose(3, 0.5)  # a loop closure moves the map estimate
    frames.mark_correction()
    T_corrected = jump @ T @ step
    T_map_odom, T_odom_base = frames.update(T_corrected, T_map_base_before_correction=T @ step)
    np.testing.assert_allclose(T_odom_base, odoms[-1] @ step, atol=1e-12)  # odom moved only by the motion
    np.testing.assert_allclose(T_map_odom @ T_odom_base, T_corrected, atol=1e-12)  # map is corrected
    np.testing.assert_allclose(T_map_odom, jump, atol=1e-12)


def test_rep105_odom_reset_to_map_jumps_once_then_stays_continuous():
    frames = Rep105Frames()
    T = pose(2, 0.05)
    frames.update(T)
    frames.mark_correction()
    realigned = pose(5, 0.3) @ T   # the world re-expressed: with mark_correction odom would absorb the jump
    frames.reset_to_map()          # ... but odom becomes the map frame instead
    T_map_odom, T_odom_base = frames.update(realigned)
    np.testing.assert_allclose(T_map_odom, np.eye(4))
    np.testing.assert_allclose(T_odom_base, realigned, atol=1e-12)
    jump = pose(3, 0.5)            # a later loop correction is absorbed by map -> odom again
    step = pose(2, 0.05)
    frames.mark_correction()
    T_map_odom, T_odom_base2 = frames.update(jump @ realigned @ step, T_map_base_before_correction=realigned @ step)
    np.testing.assert_allclose(T_odom_base2, T_odom_base @ step, atol=1e-12)
    np.testing.assert_allclose(T_map_odom, jump, atol=1e-12)


def test_rep105_map_to_odom_stays_rigid_over_many_corrections():
    """A long run's loop corrections arrive one after another, each estimate a little off SO(3) (float rounding of
    Sim(3) products): map -> odom, their running product, stays a rigid transform (the odometry message's check
    refused it after 32 corrections of a 300 s run, and every later frame failed)."""
    from msg_adapters.common import check_pose_matrix

    frames = Rep105Frames()
    T = np.eye(4)
    frames.update(T)
    off = np.eye(4)
    off[:3, :3] *= 1.0 + 2e-6   # the pose mapped back through a correction, its rotation 2e-6 off
    for k in range(300):
        T_before = T @ pose(10 + k, 0.02)
        T = pose(1000 + k, 0.01) @ T_before
        frames.mark_correction()
        T_map_odom, T_odom_base = frames.update(T, T_map_base_before_correction=T_before @ off)
        R = T_map_odom[:3, :3]
        assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12, k
    check_pose_matrix(T_odom_base, "odom -> base_link")


def test_matrix_from_param_validates():
    T = matrix_from_param(list(pose(4).reshape(-1)), "T")
    assert T.shape == (4, 4)
    with pytest.raises(ValueError, match="expected 16 numbers"):
        matrix_from_param([1.0] * 15, "T_body_camera")
    with pytest.raises(ValueError, match="not a rigid transform"):
        matrix_from_param([2.0] + [0.0] * 15, "T_body_camera")


def test_imu_buffer_rejects_disorder_reports_gaps_and_brackets():
    buf = ImuBuffer(ImuBufferConfig(nominal_rate_hz=200.0, gap_factor=2.5, max_age_s=1.0))
    assert buf.add(0, np.zeros(3), np.zeros(3)) is None
    assert buf.add(5_000_000, np.ones(3), np.zeros(3)) is None
    assert "older than the previous" in buf.add(4_000_000, np.zeros(3), np.zeros(3))
    assert "duplicates" in buf.add(5_000_000, np.zeros(3), np.zeros(3))
    assert "non-finite value: dropped" in buf.add(6_000_000, np.array([0.0, np.nan, 0.0]), np.zeros(3))
    assert "non-finite value: dropped" in buf.add(7_000_000, np.zeros(3), np.array([np.inf, 0.0, 0.0]))
    assert buf.latest_ns == 5_000_000 and np.isfinite(buf.all().gyro).all()
    assert "IMU gap of 20.0 ms" in buf.add(25_000_000, np.zeros(3), np.zeros(3))
    for k in range(6, 20):
        buf.add(k * 5_000_000, np.full(3, k), np.zeros(3))
    assert len(buf) == 17 and buf.covers(95_000_000) and not buf.covers(95_000_001)
    s = buf.samples(32_000_000, 41_000_000)
    np.testing.assert_array_equal(s.t_ns, [30_000_000, 35_000_000, 40_000_000, 45_000_000])
    buf.add(2_000_000_000, np.zeros(3), np.zeros(3))  # 1.9 s ahead: held until the next sample confirms it
    buf.add(2_005_000_000, np.zeros(3), np.zeros(3))  # older than max_age_s behind the newest: dropped
    assert buf.earliest_ns == 95_000_000


def test_frame_synchronizer_waits_for_imu_and_applies_offset():
    imu = ImuBuffer()
    sync = FrameSynchronizer(time_offset_ns=2_000_000, max_pending=3, max_wait_ns=200_000_000)
    assert sync.push(100_000_000, "a") == []
    assert sync.push(150_000_000, "b") == []
    assert sync.push(150_000_000, "c") == [(150_000_000, "c")]   # not newer: dropped
    assert sync.release(imu) == []
    imu.add(101_000_000, np.zeros(3), np.zeros(3))
    assert sync.release(imu) == []  # a needs IMU up to 102 ms (offset)
    imu.add(105_000_000, np.zeros(3), np.zeros(3))
    assert sync.release(imu) == [(102_000_000, "a", True)]
    assert sync.push(400_000_000, "d") == []  # b waited 250 ms > max_wait: released incomplete
    assert sync.release(imu) == [(152_000_000, "b", False)]
    dropped = [sync.push(500_000_000 + k, k) for k in range(4)]
    assert dropped[:2] == [[], []] and dropped[2] == [(400_000_000, "d")]
    assert [t for t, _, _ in sync.release(None)] == [502_000_001 + k for k in range(3)]   # no IMU: all ready


def test_load_params_file_layout(tmp_path):
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    a: 1\n    b: x\nnode:\n  ros__parameters:\n    a: 2\n"
                 "    nested:\n      c: [1, 2]\nother:\n  ros__parameters:\n    a: 3\n")
    assert load_params_file(f, "node") == {"a": 2, "b": "x", "nested.c": [1, 2]}
    f.write_text("node:\n  a: 1\n")
    with pytest.raises(ValueError, match="ros__parameters"):
        load_params_file(f, "node")


def test_shipped_params_only_use_declared_names():
    """Every key a shipped file sets for a node is a parameter the node declares (catches typos)."""
    from vigs_ros import frontend_node, imu_preintegration_node, loop_detector_node, mapper_node

    modules = [imu_preintegration_node, frontend_node, mapper_node, loop_detector_node]
    all_declared = set().union(*({p.name for p in m.PARAMS} for m in modules))
    for module in modules:
        declared = {p.name for p in module.PARAMS}
        for f in default_params_files():
            for key, value in load_params_file(f, module.NODE_NAME).items():
                section_is_wildcard = key not in declared
                if section_is_wildcard:  # /** keys must be declared by some node
                    assert key in all_declared, f"{f.name}: {key} is declared by no node"
                    continue
                default = next(p.default for p in module.PARAMS if p.name == key)
                assert isinstance(value, type(default)) or (isinstance(default, float) and isinstance(value, int)), \
                    f"{f.name}: {module.NODE_NAME}.{key} = {value!r} but the default is {default!r}"
    names = [f.name for f in default_params_files()]
    assert names[0] == "ros.yaml" and {"imu_preintegration.yaml", "mapper.yaml", "loop_detector.yaml"} <= set(names)


def test_dataclass_specs_recurse_and_nest():
    from dataclasses import dataclass, field

    @dataclass
    class Inner:
        preset: str = "fast"
        sigma: float = 1.0

    @dataclass
    class Cfg:
        a: int = 3
        b: tuple = (1.0, 2.0)
        c: dict = field(default_factory=dict)
        d: float | None = None
        inner: Inner = field(default_factory=Inner)
        skipped: int = 1

    specs = dataclass_specs(Cfg, "x.", skip=("skipped",))
    assert [(s.name, s.default, s.dynamic_typing) for s in specs] == [
        ("x.a", 3, True), ("x.b", [1.0, 2.0], True), ("x.inner.preset", "fast", False), ("x.inner.sigma", 1.0, True)]
    values = {s.name: s.default for s in specs} | {"y.z": 0}
    assert nested(values, "x.") == {"a": 3, "b": [1.0, 2.0], "inner": {"preset": "fast", "sigma": 1.0}}


def test_parameter_descriptions_come_from_the_config_docstrings():
    """Google-style ``Args:`` entries: one name or several sharing a text, continuation lines joined, the
    section ending at a blank line; every parameter every node declares has a described field."""
    import importlib
    from dataclasses import dataclass

    @dataclass
    class Cfg:
        """Settings.

        Args:
            width, height: processing size,
                pixels.
            rate: samples per second.

        Not an entry: text after the section.
        """

        width: int = 1
        height: int = 2
        rate: float = 3.0
        undocumented: int = 4

    assert {s.name: s.description for s in dataclass_specs(Cfg)} == {
        "width": "processing size, pixels.", "height": "processing size, pixels.", "rate": "samples per second.",
        "undocumented": "Cfg.undocumented"}
    for node in ("frontend_node", "mapper_node", "loop_detector_node", "imu_preintegration_node"):
        module = importlib.import_module(f"vigs_ros.{node}")
        specs = [s for name in dir(module) if name.endswith("PARAMS") for s in getattr(module, name)]
        assert specs and all(" " in s.description for s in specs), \
            (node, [s.name for s in specs if " " not in s.description])


def test_parse_remaps():
    assert parse_remaps(["/a:=/b", "/c:=/d"]) == {"/a": "/b", "/c": "/d"}
    with pytest.raises(ValueError, match="must look like"):
        parse_remaps(["/a=/b"])


def test_imu_buffer_rejects_a_future_outlier_stamp_and_keeps_a_real_gap():
    buf = ImuBuffer(ImuBufferConfig(nominal_rate_hz=200.0, max_jump_s=0.5))
    for k in range(10):
        assert buf.add(k * 5_000_000, np.zeros(3), np.zeros(3)) is None
    # one sample stamped 1000 s ahead: held, then rejected when the stream goes on at its time base
    assert "held" in buf.add(1000 * 10**9, np.ones(3), np.ones(3))
    assert buf.latest_ns == 45_000_000 and not buf.covers(50_000_000)
    assert "rejected as an outlier" in buf.add(50_000_000, np.zeros(3), np.zeros(3))
    assert buf.latest_ns == 50_000_000
    for k in range(11, 20):   # later samples are not taken for out-of-order ones
        assert buf.add(k * 5_000_000, np.zeros(3), np.zeros(3)) is None
    # a real 2 s gap: held, then kept when the next sample follows it
    assert "held" in buf.add(2_095_000_000, np.zeros(3), np.zeros(3))
    assert "IMU gap of 2000.0 ms" in buf.add(2_100_000_000, np.zeros(3), np.zeros(3))
    np.testing.assert_array_equal(buf.all().t_ns[-3:], [95_000_000, 2_095_000_000, 2_100_000_000])


def test_stamp_gaps_count_the_frames_missing_between_stamps():
    from vigs_ros.time_sync import StampGaps

    gaps = StampGaps()
    stamps = [k * 50_000_000 + (k % 3) * 1_000_000 for k in range(10)] + [650_000_000, 700_000_000, 1_000_000_000]
    assert [gaps.add(t) for t in stamps] == [0] * 10 + [3, 0, 5]
    assert gaps.add(990_000_000) == 0   # not after the last: not a gap


def test_renice_moves_every_thread_and_the_autogroup_of_its_own_session_only():
    """With autogroup scheduling, a thread's niceness weighs only inside its session: a node the launcher started
    (a session of its own) must renice its autogroup too, and a node started from a shell must not renice the
    shell's session. Where the kernel shows no autogroup (a CPU cgroup, as in many CI containers) only the threads
    are reniced."""
    import os
    import subprocess
    import sys

    code = ("import os, threading, time\n"
            "from vigs_ros.runtime import autogroup_nice, renice\n"
            "worker = threading.Thread(target=time.sleep, args=(2,)); worker.start()\n"
            "before = autogroup_nice()\n"
            "ok = renice(3)\n"
            "nices = {os.getpriority(os.PRIO_PROCESS, int(t)) for t in os.listdir('/proc/self/task')}\n"
            "print(ok, ','.join(map(str, sorted(nices))), before, autogroup_nice())\n")

    def run(new_session):
        out = subprocess.run([sys.executable, "-c", code], start_new_session=new_session, capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    base = os.getpriority(os.PRIO_PROCESS, 0)
    ok, nices, before, after = run(True)
    assert ok == "True" and nices == str(min(19, base + 3))
    if before != "None":
        assert int(after) == min(19, int(before) + 3)
    else:
        assert after == "None"
    ok, nices, before, after = run(False)
    assert ok == "True" and nices == str(min(19, base + 3))
    assert after == before   # the caller's session is left alone


def test_autogroup_nice_reads_the_kernel_line_and_an_empty_file_as_none(tmp_path, monkeypatch):
    """The kernel shows /proc/self/autogroup empty for a task in a CPU cgroup (CI containers): no autogroup."""
    import vigs_ros.runtime as runtime

    path = tmp_path / "autogroup"
    monkeypatch.setattr(runtime, "_AUTOGROUP", str(path))
    assert runtime.autogroup_nice() is None            # no file
    path.write_text("")
    assert runtime.autogroup_nice() is None            # empty: not in an autogroup
    path.write_text("/autogroup-661 nice -2\n")
    assert runtime.autogroup_nice() == -2
