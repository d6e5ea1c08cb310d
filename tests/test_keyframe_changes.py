"""What a consumer last sent of a keyframe and the change since: pose and depth growth ``c`` within a revision
(ratio of depth scales), across revisions (median ratio of the disparities), and no disparities kept once the
keyframe settled."""
import pytest
import torch

from vigs_core.frontend.keyframe_changes import SentKeyframes, depth_scale_change
from vigs_core.frontend.odometry import Keyframe

D = torch.float64


def keyframe():
    disp = torch.linspace(0.2, 1.0, 24, dtype=D)
    disp[0] = -1.0   # unknown: left out of the ratios
    return Keyframe(7, 100, None, torch.eye(4, dtype=D), disp)


def test_an_unchanged_keyframe_reports_nothing_and_a_new_pose_its_sent_one():
    kf, sent = keyframe(), SentKeyframes()
    T0 = torch.eye(4, dtype=D)
    sent.record(kf, T0)
    assert 7 in sent and 8 not in sent and sent.change(kf) is None
    kf.pose = kf.pose.clone()   # the frontend replaces the tensor when it changes the pose
    T_old, c = sent.change(kf)
    assert T_old is T0 and c == 1.0
    assert sent.change(kf) is None   # compared once per change


def test_depth_growth_within_and_across_revisions_accumulates_until_sent():
    kf, sent = keyframe(), SentKeyframes()
    sent.record(kf, torch.eye(4, dtype=D))
    kf.rescale_depth(1.5)                            # a uniform scaling: the revision stays
    assert sent.change(kf)[1] == pytest.approx(1.5, rel=1e-12)
    before = kf.disp
    d = before.clone()
    d[1:] = d[1:] / torch.linspace(1.9, 2.1, 23, dtype=D)   # BA: a new revision, depths about twice
    kf.set_disparities(d)
    assert kf.revision == 1
    growth = 1.5 * depth_scale_change(before, d)     # the scaling, then the median ratio of the revisions
    assert sent.change(kf)[1] == pytest.approx(growth, rel=1e-12)
    kf.disp = None                                   # settled: the frontend drops the disparities
    kf.rescale_depth(2.0)
    assert sent.change(kf)[1] == pytest.approx(2.0 * growth, rel=1e-12)
    assert sent._refs[7].disp is None                # nothing per keyframe kept after it settled
    sent.record(kf, torch.eye(4, dtype=D))
    kf.rescale_depth(0.5)
    assert sent.change(kf)[1] == pytest.approx(0.5, rel=1e-12)
    kf.revision += 1                                 # cannot happen: a settled keyframe is not adjusted again
    with pytest.raises(RuntimeError, match="re-estimated after it left the window"):
        sent.change(kf)
