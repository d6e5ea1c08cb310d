"""Loop candidate detection: the vectorised orientation test, a candidate's flow that does not depend on which
pairs the detector checked before, and a wide-baseline loop measured at its full length."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from loop_synthetic import cast, look, render, room
from vigs_core.camera.model import CameraModel
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.geometry import quat_to_matrix, so3_exp
from vigs_core.loop.config import LoopDetectionConfig
from vigs_core.loop.detection import (KeyframeView, LoopDetector, ThumbnailRows, rotation_angle_deg,
                                       rotation_cosines, thumbnail)
from vigs_core.sim.render import Renderer
from vigs_core.sim.scene import build_room_scene
from vigs_core.solver import Intrinsics
from vigs_core.spill import SpillConfig

W, H = 160, 120
INTR = Intrinsics(100.0, 100.0, 79.5, 59.5)
GRID = PixelGrid(W, H, 8)


def view(kf_id: int, yaw_deg: float, position: list[float]) -> KeyframeView:
    T = look(math.radians(yaw_deg), np.asarray(position, dtype=float))
    depth = torch.from_numpy(cast(room(), T, GRID.coords(), INTR, shade=False)[0])
    return KeyframeView.from_depth(kf_id, render(room(), T, INTR, W, H), T, depth)


def test_rotation_cosines_match_the_relative_rotation_angle():
    gen = torch.Generator().manual_seed(3)
    poses = []
    for angle in (0.0, 0.3, 1.0, 2.0, 3.1):   # rotation angles (rad) of the relative rotations
        axis = torch.randn(3, generator=gen, dtype=torch.float64)
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = so3_exp(axis / axis.norm() * angle)
        poses.append(T)
    base = torch.eye(4, dtype=torch.float64)
    base[:3, :3] = so3_exp(torch.tensor([0.2, -0.4, 0.1], dtype=torch.float64))
    poses = [base @ T for T in poses]   # relative rotations seen from a rotated new keyframe
    cos = rotation_cosines(base, poses)
    expected = [math.cos(math.radians(rotation_angle_deg(base, T))) for T in poses]
    assert np.allclose(cos, expected, atol=1e-9)
    assert np.allclose(cos, np.cos([0.0, 0.3, 1.0, 2.0, 3.1]), atol=1e-9)
    assert rotation_cosines(base, []).shape == (0,)


def test_a_candidates_loop_edge_does_not_depend_on_the_pairs_checked_before():
    torch.set_num_threads(1)
    old, new = view(0, 30.0, [0.3, 0.2, 1.5]), view(100, 36.0, [0.4, 0.15, 1.45])
    fresh = LoopDetector(DISFlowEstimator(GRID), INTR).detect(new, [old])
    assert fresh.accepted is not None and fresh.accepted.old == 0, fresh.rejected
    used = LoopDetector(DISFlowEstimator(GRID), INTR)
    # other pairs first (their flows: DIS calls with and without initial flows on the same instances)
    used.detect(view(60, 150.0, [-0.5, 0.3, 1.5]), [view(1, 140.0, [-0.4, 0.4, 1.5])])
    used.detect(view(70, -60.0, [0.2, -0.5, 1.5]), [view(2, -40.0, [0.0, -0.4, 1.6])])
    again = used.detect(new, [old])
    assert again.accepted is not None
    assert torch.equal(again.accepted.relative, fresh.accepted.relative)
    assert again.accepted.inlier_fraction == fresh.accepted.inlier_fraction


def test_the_detector_keeps_disparities_and_follows_the_depth_scale_of_views_without_them(tmp_path):
    """Views of keyframes that left the frontend's window come without disparities: the detector uses those it
    kept (read back from disk when spilled), rescaled by the view's depth scale, as if the view carried them."""
    torch.set_num_threads(1)
    old, new = view(0, 30.0, [0.3, 0.2, 1.5]), view(100, 36.0, [0.4, 0.15, 1.45])
    s = 1.5   # a loop correction grew old's depths by s since the detector kept them
    carried = LoopDetector(DISFlowEstimator(GRID), INTR).detect(
        new, [dataclasses.replace(old, disp=old.disp / s, depth_scale=s)])
    kept = LoopDetector(DISFlowEstimator(GRID), INTR, images=SpillConfig(resident=1, directory=str(tmp_path)))
    kept.detect(old, [])                                        # old seen as new: image and disparities kept
    kept.detect(view(50, -60.0, [0.2, -0.5, 1.5]), [])           # another one: old's go to disk
    assert kept._disps.writes >= 1
    again = kept.detect(new, [dataclasses.replace(old, image=None, disp=None, depth_scale=s)])
    assert carried.accepted is not None and again.accepted is not None
    torch.testing.assert_close(again.accepted.relative, carried.accepted.relative, rtol=1e-9, atol=1e-9)
    kept.close()
    assert list(tmp_path.iterdir()) == []


def test_the_detector_keeps_images_of_keyframes_it_has_seen_so_views_need_not(tmp_path):
    """Views of registered keyframes come without images (the callers drop them to bound memory): the detector
    uses the images it kept when they were new, read back from disk when spilled, with the same result."""
    torch.set_num_threads(1)
    old, new = view(0, 30.0, [0.3, 0.2, 1.5]), view(100, 36.0, [0.4, 0.15, 1.45])
    fresh = LoopDetector(DISFlowEstimator(GRID), INTR).detect(new, [old])
    spilling = LoopDetector(DISFlowEstimator(GRID), INTR, images=SpillConfig(resident=1, directory=str(tmp_path)))
    spilling.detect(old, [])                                   # old seen as new: its image kept
    spilling.detect(view(50, -60.0, [0.2, -0.5, 1.5]), [])      # another one: old's image goes to disk
    assert spilling._images.writes >= 1
    again = spilling.detect(new, [dataclasses.replace(old, image=None)])
    assert again.accepted is not None and torch.equal(again.accepted.relative, fresh.accepted.relative)
    with pytest.raises(KeyError):                              # a view never seen needs its image
        spilling.detect(view(200, 30.0, [0.3, 0.2, 1.5]), [dataclasses.replace(view(1, 30.0, [0.3, 0.2, 1.5]),
                                                                                  image=None)])
    spilling.close()
    assert list(tmp_path.iterdir()) == []


def sim_view(kf_id: int, position: list[float], quat_wxyz: list[float], T_estimate: torch.Tensor | None = None
             ) -> tuple[KeyframeView, torch.Tensor]:
    """A keyframe of the simulator's room scene (boxes, pillars, textures) around two camera positions of hybrid
    V1_01, rendered at 376x240 with its exact grid depths; the view's pose is ``T_estimate`` (default: the truth).
    Returns the view and the true ``T_WC``."""
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3], T[:3, 3] = quat_to_matrix(torch.tensor(quat_wxyz, dtype=torch.float64)), torch.tensor(position)
    out = Renderer(build_room_scene(np.array(SIM_POSITIONS)), SIM_CAMERA).render(T)
    image = (np.clip(out.image, 0, 1) * 255).astype(np.uint8)
    c = SIM_GRID.coords().astype(int)
    depth = torch.from_numpy(out.depth[c[:, 1], c[:, 0]].astype(np.float64))
    return KeyframeView.from_depth(kf_id, image, T if T_estimate is None else T_estimate, depth), T


# Camera poses of keyframes 41 and 187 of a hybrid V1_01 run (ground truth at their stamps), 0.55 m apart: a loop
# whose measured translation came out 10 % short when the correspondences' flows started from zero.
SIM_POSITIONS = [[0.422392, -0.37571, 1.033578], [0.973288, -0.369366, 1.050825]]
SIM_QUATS = [[0.465151, -0.648089, 0.469339, -0.378597], [0.470936, -0.731931, 0.394031, -0.295357]]
SIM_CAMERA = CameraModel(376, 240, 229.0, 229.0, 187.5, 119.5)
SIM_GRID = PixelGrid(376, 240, 8)


def test_a_wide_baseline_loop_is_measured_at_its_full_length():
    """The flows that measure a loop start from the warp at the current estimate (here 5 cm off along the
    baseline, a drift the loop must correct); from zero flow DIS fell short of the large displacements."""
    torch.set_num_threads(1)
    old, T_old = sim_view(0, SIM_POSITIONS[0], SIM_QUATS[0])
    _, T_new = sim_view(100, SIM_POSITIONS[1], SIM_QUATS[1])
    drifted = T_new.clone()
    drifted[:3, 3] += 0.05 * (T_new[:3, 3] - T_old[:3, 3]) / (T_new[:3, 3] - T_old[:3, 3]).norm()
    new, _ = sim_view(100, SIM_POSITIONS[1], SIM_QUATS[1], drifted)
    intr = Intrinsics(SIM_CAMERA.fx, SIM_CAMERA.fy, SIM_CAMERA.cx, SIM_CAMERA.cy)
    detector = LoopDetector(DISFlowEstimator(SIM_GRID), intr, LoopDetectionConfig(max_mean_flow_px=100.0))
    decision = detector.detect(new, [old])
    assert decision.accepted is not None, decision.rejected
    truth = (torch.linalg.inv(T_old) @ T_new)[:3, 3]
    measured = decision.accepted.relative[:3, 3]
    assert float((measured - truth).norm()) < 0.02 * float(truth.norm()), (measured, truth)


def test_only_candidates_within_the_check_rotation_get_dense_flow():
    """Of the ranked candidates, one whose estimated relative rotation exceeds ``max_check_rotation_deg`` gets no
    flow (it could not pass the flow and drift tests together), one within it does; the orientation test
    (120 deg) alone would give both a flow check."""
    new = view(100, 0.0, [0.0, 0.0, 1.5])
    near, far = view(0, 30.0, [0.0, 0.0, 1.5]), view(1, 70.0, [0.0, 0.0, 1.5])
    detector = LoopDetector(DISFlowEstimator(GRID), INTR)
    assert {kf.id for kf in detector.candidates(new, [near, far])} == {0}
    wide = LoopDetector(DISFlowEstimator(GRID), INTR, LoopDetectionConfig(max_check_rotation_deg=120.0))
    assert {kf.id for kf in wide.candidates(new, [near, far])} == {0, 1}

    calls = []
    estimate = detector.estimator.estimate
    detector.estimator.estimate = lambda *a, **k: calls.append(1) or estimate(*a, **k)
    detector.detect(new, [near, far])
    assert len(calls) == 1   # the zero-flow test of the candidate within the bound only


def test_candidates_come_best_thumbnail_first_from_rows_that_grow_with_the_run():
    """Thumbnails are the rows of one array that grows past its capacity and keeps every keyframe's row; the
    candidates' correlations with the new keyframe are scored in one product, best match first."""
    rng = np.random.default_rng(0)
    rows = ThumbnailRows(12, capacity=4)
    vecs = {k: rng.normal(size=12).astype(np.float32) for k in range(10)}
    for k, v in vecs.items():
        rows.put(k, v)
    probe = rng.normal(size=12).astype(np.float32)
    np.testing.assert_allclose(rows.scores([7, 0, 3], probe), [vecs[k] @ probe for k in (7, 0, 3)], rtol=1e-5)
    np.testing.assert_array_equal(rows.row(9), vecs[9])
    assert 9 in rows and 10 not in rows
    new = view(100, 0.0, [0.0, 0.0, 1.5])
    history = [view(0, 25.0, [0.0, 0.0, 1.5]), view(1, 0.0, [0.0, 0.0, 1.5]), view(2, 10.0, [0.0, 0.0, 1.5])]
    detector = LoopDetector(DISFlowEstimator(GRID), INTR)
    size = detector.detection.thumbnail_size
    t_new = thumbnail(new.image, size)
    expected = sorted(history, key=lambda kf: -float(thumbnail(kf.image, size) @ t_new))
    assert [kf.id for kf in detector.candidates(new, history)] == [kf.id for kf in expected]
    assert expected[0].id == 1   # the same view as the new keyframe's
