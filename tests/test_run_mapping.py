"""The Gaussian mapper inside ``vigs run``: a short rendered sequence (project simulator) through the pipeline
with mapping on (map.ply, report numbers, render quality), and the keyframe feeding (depth masking, batched pose
and scale updates when the world is rescaled)."""
import gc
import json
import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
import torch

from vigs_core.camera import CameraModel
from vigs_core.frontend.frame_graph import FrameGraph, FrameGraphConfig
from vigs_core.frontend.keyframe_changes import KeyframeTable
from vigs_core.frontend.odometry import Keyframe
from vigs_core.geometry import se3_inverse
from vigs_core.mapping import MapperConfig, load_map
from vigs_core.sim.render import Renderer
from vigs_core.sim.scene import build_room_scene
from vigs_core.system import PipelineConfig, load_config, run_pipeline
from vigs_core.system.mapping import MappingConfig, OnlineMapping
from vigs_core.system.sources import InputSequence

torch.set_num_threads(1)
cv2.setNumThreads(1)
W, H, RATE, N = 192, 128, 20.0, 40
CAM = CameraModel(W, H, 120.0, 120.0, 95.5, 63.5)
R_WC0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])   # looking along world +x, z up
# Render quality on the sampled non-keyframe frames (96x64 render size). Trivial predictions of the same frames
# score: the image's own mean grey level 18.6 dB / SSIM 0.22, the image shifted by 4 render pixels 18.6 dB / 0.11,
# the image blurred with sigma 3 render pixels 23.2 dB / 0.40. The map reaches about 24.6 dB / 0.67 online and
# 25.3 dB / 0.72 after 30 refinement steps; the bounds below fail for a misplaced or structureless map.
PSNR_MIN_DB, SSIM_MIN = 22.0, 0.55


def camera_poses(t):
    """(N, 4, 4) T_WC: forward and sideways motion with a yaw sway."""
    T = np.tile(np.eye(4), (len(t), 1, 1))
    for k, s in enumerate(t):
        yaw = 0.15 * math.sin(1.3 * s)
        Rz = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1]])
        T[k, :3, :3] = Rz @ R_WC0
        T[k, :3, 3] = [0.35 * s, 0.25 * math.sin(0.9 * s), 0.05 * math.sin(1.7 * s)]
    return T


def rendered_sequence() -> InputSequence:
    t = np.arange(N) / RATE
    T_WC = camera_poses(t)
    scene = build_room_scene(np.concatenate((T_WC[:, :3, 3], T_WC[:, :3, 3] + [4.0, 0, 0])), seed=3)
    r = Renderer(scene, CAM)
    images = [(r.render(T, with_depth=False).image * 255).clip(0, 255).astype(np.uint8) for T in T_WC]
    t_ns = (1_000_000_000 + t * 1e9).astype(np.int64)
    return InputSequence("sim", CAM, np.eye(4), N, lambda: iter(zip(t_ns, images)), None)


def test_vigs_run_maps_keyframes_and_reports_render_quality(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    width: {W}\n    height: {H}\n    odometry:\n"
                      "      init_min_parallax_px: 5.0\n      keyframes:\n        flow_threshold_px: 8.0\n"
                      "    imu:\n      enabled: false\n    loop:\n      enabled: false\n"
                      "    mapping:\n      eval_stride: 3\n      final_refine_iterations: 30\n"
                      "      mapper:\n        iterations: 10\n"
                      f"        keyframe_store: {{resident: 2, directory: {tmp_path / 'spill'}}}\n")
    cfg = load_config(params)
    assert cfg.mapping.enabled and cfg.mapping.final_refine_iterations == 30
    out = tmp_path / "out"
    (tmp_path / "spill").mkdir()
    report = run_pipeline("sim", cfg, out, progress=False, sequence=rendered_sequence())
    assert report["mapping"]["keyframes_on_disk"] == report["keyframes"] - 2
    assert report["mapping"]["keyframe_disk_reads"] > 0
    assert report["mapping"]["queue_wait_seconds"] >= 0   # the mapper runs in its process by default
    gc.collect()   # the store's folder goes with the mapper
    assert list((tmp_path / "spill").iterdir()) == []
    m = json.loads((out / "report.json").read_text())["mapping"]
    assert m == report["mapping"]
    assert m["keyframes_mapped"] == report["keyframes"] >= 4
    gmap, doc = load_map(out / "map.ply")
    assert len(gmap) == m["gaussians"] > 500
    assert len(doc["keyframes"]) == report["keyframes"]
    assert m["mapping_s"] > 0 and m["online"]["frames"] >= 5
    assert m["online"]["psnr"] > PSNR_MIN_DB and SSIM_MIN < m["online"]["ssim"] <= 1.0
    assert m["refined"]["iterations"] == 30
    assert m["refined"]["psnr"] > m["online"]["psnr"] and m["refined"]["ssim"] > m["online"]["ssim"]


def test_a_mapping_process_that_dies_loses_the_map_but_not_the_trajectory_or_the_report(tmp_path, monkeypatch):
    """The mapper's process killed mid-run: the run goes on to the end, writes its trajectory and report (the
    error in ``mapping``, no map) and then raises, so that ``vigs run`` exits non-zero."""
    from vigs_core.mapping.process import MappingProcessError

    params = tmp_path / "p.yaml"
    params.write_text(f"frontend:\n  ros__parameters:\n    width: {W}\n    height: {H}\n    odometry:\n"
                      "      init_min_parallax_px: 5.0\n      keyframes:\n        flow_threshold_px: 8.0\n"
                      "    imu:\n      enabled: false\n    loop:\n      enabled: false\n"
                      "    mapping:\n      mapper:\n        iterations: 2\n")
    step = OnlineMapping.step

    def killing_step(self, image):
        if self._frame_index == 20:
            self.mapper.channel.process.kill()
            self.mapper.channel.process.join()
        step(self, image)

    monkeypatch.setattr(OnlineMapping, "step", killing_step)
    out = tmp_path / "out"
    with pytest.raises(MappingProcessError, match="the mapping process ended"):
        run_pipeline("sim", load_config(params), out, progress=False, sequence=rendered_sequence())
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == N and report["error"].startswith("MappingProcessError")
    assert report["mapping"] == {"error": "the mapping process ended (exit code -9)"}
    assert len(np.loadtxt(out / "trajectory.txt", ndmin=2)) == N and not (out / "map.ply").exists()


def test_mapping_can_be_disabled_and_config_is_validated():
    cfg = PipelineConfig()
    assert cfg.mapping.enabled                       # on by default for vigs run
    with pytest.raises(ValueError, match="max_depth_ratio"):
        MappingConfig(max_depth_ratio=0.5)
    with pytest.raises(KeyError, match="expected one of"):
        from vigs_core.system import apply_overrides
        apply_overrides(PipelineConfig(), {"mapping": {"no_such_key": 1}})


@dataclass
class _Edge:
    weight: np.ndarray


class _Grid:
    rows, cols = 4, 6


class _FakeOdometry:
    """The attributes of DenseOdometry that OnlineMapping reads: two keyframes on a 4x6 grid."""

    def __init__(self):
        self.grid = _Grid()
        rng = np.random.default_rng(0)
        self.keyframes = KeyframeTable()
        for k in range(2):
            T_WC = torch.eye(4, dtype=torch.float64)
            T_WC[0, 3] = 0.2 * k
            disp = torch.full((24,), 0.5, dtype=torch.float64)
            disp[0] = -1.0          # invalid
            disp[1] = 0.01          # 100 m: far beyond 5x the median depth
            self.keyframes[k] = Keyframe(k, 1000 * k, rng.integers(0, 255, (H, W), dtype=np.uint8), se3_inverse(T_WC),
                                    disp)
        weight = np.ones(24)
        weight[2] = 0.0             # unconfident cell
        self.edges = {(0, 1): _Edge(weight), (1, 0): _Edge(np.ones(24))}
        self.frames = []
        self.graph = FrameGraph(FrameGraphConfig(window=4))


@pytest.mark.parametrize("process", [True, False], ids=["mapper process", "mapper thread"])
def test_keyframe_depth_masking_and_world_rescale_moves_the_map_in_one_batch(process):
    odo = _FakeOdometry()
    with pytest.raises(ValueError, match="keyframe_delay .4. must be below the frontend's window .4."):
        OnlineMapping(MappingConfig(keyframe_delay=4), odo, CAM)   # its image would be gone by then
    online = OnlineMapping(MappingConfig(keyframe_delay=1, mapper=MapperConfig(iterations=2), process=process),
                           odo, CAM)
    z = online._depth(0, odo.keyframes[0].disp)
    assert z.shape == (4, 6) and z[0, 0] == 0 and z[0, 1] == 0 and z[0, 2] == 0 and z[0, 3] == pytest.approx(2.0)
    online.step(odo.keyframes[1].image)
    assert [k for k in odo.keyframes if k in online._sent] == [0]   # keyframe 1 waits for a newer one
    online.mapper.wait_idle()
    means = online.mapper.snapshot().means
    # a world rescale by s = 3 (as the visual-inertial alignment does): positions x3, disparities /3
    s = 3.0
    for kf in odo.keyframes.values():
        T_WC = se3_inverse(kf.pose)
        T_WC[:3, 3] *= s
        kf.pose = se3_inverse(T_WC)
        kf.rescale_depth(s)
    online.step(odo.keyframes[1].image)
    assert online.pose_update_batches == 1
    online.mapper.wait_idle()
    # keyframe 0 sits at the origin: its anchored Gaussians scale about the camera centre by s
    torch.testing.assert_close(online.mapper.snapshot().means, means * s, rtol=1e-4, atol=1e-5)
    online.step(odo.keyframes[1].image)               # nothing changed: no further batch
    assert online.pose_update_batches == 1
    # a loop correction reaches the mapper through the loop driver; on_correction records it as sent
    T_WC = se3_inverse(odo.keyframes[0].pose)
    T_WC[1, 3] += 0.5
    odo.keyframes[0].pose = se3_inverse(T_WC)
    online.on_correction({0: (T_WC, 1.0)})
    online.step(odo.keyframes[1].image)
    assert online.pose_update_batches == 1
    online.finish()
    assert all(k in online._sent for k in (0, 1)) and online.mapper.summary().stats.keyframes == 2
    online.close()


def test_evaluation_images_are_a_bounded_uniform_sample_of_a_long_run():
    """A long run keeps at most ``eval_max_frames`` evaluation images, spread over the whole run (reservoir
    sampling), not every ``eval_stride``-th frame of it; a short run keeps them all, as before."""
    from types import SimpleNamespace

    odo = SimpleNamespace(keyframes=KeyframeTable(), graph=FrameGraph())
    online = OnlineMapping(MappingConfig(eval_stride=2, eval_max_frames=20, process=False), odo, CAM)
    try:
        image = np.zeros((H, W), np.uint8)
        for _ in range(30):
            online.step(image)
        assert sorted(online._eval_images) == list(range(0, 30, 2))
        for _ in range(3970):
            online.step(image)
        kept = sorted(online._eval_images)
        assert len(kept) == 20 and all(k % 2 == 0 for k in kept)
        assert kept[0] < 1000 and kept[-1] > 3000   # spread over the run, not its first or last frames
    finally:
        online.close()


def test_a_refinement_a_signal_cuts_short_is_marked_interrupted():
    """A stop request during the map's evaluation leaves the refinement out and says so (``interrupted``), so a
    report never reads as a finished map without its refinement; without one the refinement runs."""
    odo = _FakeOdometry()
    online = OnlineMapping(MappingConfig(keyframe_delay=1, final_refine_iterations=2,
                                         mapper=MapperConfig(iterations=2), process=False), odo, CAM)
    try:
        online.finish()
        t_ns, T_WC = np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))
        stopped = online.evaluate(t_ns, T_WC, stop=lambda: True)
        assert stopped["interrupted"] and "refined" not in stopped
        finished = online.evaluate(t_ns, T_WC, stop=lambda: False)
        assert "interrupted" not in finished and finished["refined"]["iterations"] == 2
    finally:
        online.close()
