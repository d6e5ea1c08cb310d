"""The frontend node's engine reports keyframe changes as the mapper and the loop detector need them: the pose
and the depth scale since the last publication (the IMU initialisation re-expresses the world in metres), and
small changes accumulate until they pass the tolerance instead of being dropped frame by frame."""
import numpy as np
import torch

from ros_bags import SAMPLE_BAG
from vigs_core.camera import CameraModel
from vigs_core.frontend.keyframe_changes import KeyframeTable
from vigs_core.frontend.odometry import Keyframe
from vigs_core.geometry import se3_inverse, se3_exp
from vigs_core.system import PipelineConfig
from vigs_core.system.sources import open_input
from vigs_ros.frontend_engine import FrameOutput, FrontendEngine

D = torch.float64


def engine_with_keyframe():
    camera = CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5)
    config = PipelineConfig(width=64, height=48)
    engine = FrontendEngine(camera, config, np.eye(4), None, pose_update_tolerance=1e-3)
    grid = engine.odometry.grid
    T_wc = se3_exp(torch.tensor([0.5, -0.2, 1.0, 0.1, 0.2, -0.3], dtype=D))
    disp = torch.linspace(0.2, 1.0, grid.size, dtype=D)
    engine.odometry.keyframes[3] = Keyframe(3, 10, np.zeros((48, 64), np.uint8), se3_inverse(T_wc), disp)
    out = FrameOutput(10, None)
    engine.report_keyframes(out, metric=False)
    assert [kf.id for kf in out.new_keyframes] == [3] and not out.new_keyframes[0].metric
    return engine, T_wc


def test_world_rescaling_is_reported_with_its_depth_scale():
    engine, T_wc = engine_with_keyframe()
    kf = engine.odometry.keyframes[3]
    s = 0.3   # world x -> s x: positions times s, disparities over s
    T_new = T_wc.clone()
    T_new[:3, 3] *= s
    kf.pose = se3_inverse(T_new)
    kf.rescale_depth(s)
    out = FrameOutput(20, None)
    engine.report_keyframes(out, metric=True)
    T_reported, c = out.updated_keyframes[3]
    np.testing.assert_allclose(T_reported, T_new.numpy(), atol=1e-9)
    assert abs(c - s) < 1e-12
    again = FrameOutput(30, None)
    engine.report_keyframes(again, metric=True)
    assert not again.updated_keyframes   # published once


def test_small_moves_accumulate_until_they_pass_the_tolerance():
    engine, T_wc = engine_with_keyframe()
    kf = engine.odometry.keyframes[3]
    reported = []
    for step in range(1, 6):   # 0.4 mm per frame, tolerance 1 mm
        T = T_wc.clone()
        T[0, 3] += 4e-4 * step
        kf.pose = se3_inverse(T)
        out = FrameOutput(step, None)
        engine.report_keyframes(out, metric=False)
        reported.append(3 in out.updated_keyframes)
    assert reported == [False, False, True, False, False]


def test_a_pose_after_a_loop_correction_maps_back_to_the_uncorrected_world():
    """REP-105's odom continues across a loop correction by the motion the odometry would have given without it:
    a frame's corrected pose maps back through its reference keyframe's Sim(3) correction."""
    engine, T_wc = engine_with_keyframe()
    T_new = se3_exp(torch.tensor([1.0, 0.3, -0.2, 0.0, 0.1, 0.05], dtype=D)).numpy()
    c = 1.3
    assert engine.apply_corrections({3: T_new}, {3: c}) == 1
    T_old = T_wc.numpy() @ se3_exp(torch.tensor([0.02, 0.0, 0.01, 0.0, 0.01, 0.0], dtype=D)).numpy()
    # the same frame in the corrected world: rotation by R_c, position by the similarity x -> c R_c x + t_c
    C = engine.last_corrections[3]
    T_corrected = np.eye(4)
    T_corrected[:3, :3] = (C[:3, :3] / c) @ T_old[:3, :3]
    T_corrected[:3, 3] = C[:3, :3] @ T_old[:3, 3] + C[:3, 3]
    np.testing.assert_allclose(engine.pose_before_correction(T_corrected, 3), T_old, atol=1e-9)
    np.testing.assert_allclose(T_corrected[:3, 3], T_new[:3, 3] + c * T_new[:3, :3] @ (
        np.linalg.inv(T_wc.numpy()) @ np.append(T_old[:3, 3], 1.0))[:3], atol=1e-9)   # the keyframe moved to T_new
    assert engine.pose_before_correction(T_corrected, 4) is None


def test_only_keyframes_whose_tensors_were_replaced_are_compared(monkeypatch):
    """A long run keeps every keyframe; per frame only those the core changed (new tensors) are examined."""
    engine, T_wc = engine_with_keyframe()
    kf = engine.odometry.keyframes[3]
    for k in range(4, 204):   # old keyframes, published once
        engine.odometry.keyframes[k] = Keyframe(k, 10 + k, None, kf.pose.clone(), kf.disp.clone())
    engine.report_keyframes(FrameOutput(20, None), metric=False)
    examined = []
    inverse = FrontendEngine._rigid_inverse
    monkeypatch.setattr(FrontendEngine, "_rigid_inverse", staticmethod(lambda T, out: examined.append(1) or
                                                                       inverse(T, out)))
    T = T_wc.clone()
    T[0, 3] += 0.01
    engine.odometry.keyframes[150].pose = se3_inverse(T)   # BA replaced one keyframe's pose
    out = FrameOutput(30, None)
    engine.report_keyframes(out, metric=False)
    assert len(examined) == 1 and list(out.updated_keyframes) == [150]


def test_the_change_log_notes_every_assignment_once_per_consumer():
    """Each consumer's cursor lists the keyframes put in or assigned since it last looked, each once, whoever
    made the change; a late consumer starts with every keyframe; attributes nobody reports are not noted."""
    table = KeyframeTable()
    first = table.subscribe()
    disp = torch.ones(6, dtype=D)
    for k in range(4):
        table[k] = Keyframe(k, 10 * k, None, torch.eye(4, dtype=D), disp.clone())
    late = table.subscribe()
    assert first.take() == [0, 1, 2, 3] and late.take() == [0, 1, 2, 3] and first.take() == []
    table[2].pose = torch.eye(4, dtype=D) * 2
    table[0].set_disparities(disp * 2)
    table[3].rescale_depth(1.5)
    table[1].tracked = (0, torch.eye(4, dtype=D))   # not part of what consumers are sent
    assert first.take() == [0, 2, 3]
    table[1].image = table[1].disp = None           # settled
    assert first.take() == [1] and late.take() == [0, 1, 2, 3]
    loose = Keyframe(9, 90, None, torch.eye(4, dtype=D), None)
    loose.pose = torch.eye(4, dtype=D)              # in no table yet: nothing to note
    assert first.take() == []


def test_no_change_of_the_core_escapes_the_report():
    """Reporting visits only the keyframes the change log lists: over the sample's IMU initialisation (the world
    re-expressed), BA, settling keyframes and a loop correction, after every frame each keyframe's current pose,
    disparity revision and depth scale are the ones last compared, and a settled keyframe's reference keeps no
    disparities; a keyframe leaving the window is listed too (the loop driver sends its last disparities then)."""
    seq = open_input(SAMPLE_BAG)
    engine = FrontendEngine(seq.camera, PipelineConfig(), seq.T_BS, seq.imu_noise)
    imu, k = seq.imu, 0
    cursor, window, exits = engine.odometry.keyframes.subscribe(), [], 0

    def unseen() -> list[int]:
        refs = engine._published._refs
        return [i for i, kf in engine.odometry.keyframes.items()
                if i not in refs or refs[i].seen_pose is not kf.pose or refs[i].seen_revision != kf.revision
                or refs[i].seen_scale != kf.depth_scale or (kf.disp is None and refs[i].disp is not None)]

    for n, (t_ns, image) in enumerate(seq.frames()):
        if n == 280:
            break
        while k < len(imu) and not engine.stream.imu.covers(t_ns):
            engine.stream.add_imu(int(imu.t_ns[k]), imu.gyro[k], imu.acc[k])
            k += 1
        if n == 260:   # a loop correction of every keyframe, as the loop detector sends one
            ids = list(engine.odometry.keyframes)
            G = se3_exp(torch.tensor([0.05, -0.02, 0.01, 0.0, 0.0, 0.02], dtype=D)).numpy()
            poses = {i: G @ np.linalg.inv(engine.odometry.keyframes[i].pose.numpy()) for i in ids}
            assert engine.apply_corrections(poses, {i: 1.01 for i in ids}) == len(ids)
        engine.track(t_ns, image, "mono8")
        assert unseen() == [], f"frame {n}"
        left = set(window) - set(engine.odometry.graph.keyframes)
        assert left <= set(cursor.take()), f"frame {n}"
        window, exits = list(engine.odometry.graph.keyframes), exits + len(left)
    assert engine.stream.metric and exits > 0


def test_a_dropped_consumer_stops_collecting_changes():
    """The log holds its cursors weakly: a consumer gone before the odometry leaves nothing behind that grows."""
    import gc

    table = KeyframeTable()
    kept, dropped = table.subscribe(), table.subscribe()
    del dropped
    gc.collect()
    table[0] = Keyframe(0, 0, None, torch.eye(4, dtype=D), None)
    assert len(table.changes._cursors) == 1 and kept.take() == [0]
