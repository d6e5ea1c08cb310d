"""Loop candidate detection: the vectorised orientation test, and a candidate's flow that does not depend on
which pairs the detector checked before."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from loop_synthetic import cast, look, render, room
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.geometry import so3_exp
from vigs_core.loop.detection import KeyframeView, LoopDetector, rotation_angle_deg, rotation_cosines
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
