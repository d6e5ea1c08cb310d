"""Issue 9 "done when" (2): a sequence with repeated textures and no real revisit gives no accepted loop.

A camera moves along a corridor wall whose texture (wall and floor) repeats every 0.8 m; keyframes 60 apart
(4.8 m) see identical images, so detection proposes them (tiny flow, same orientation) and even the dense
two-view check agrees, but the loop would claim a correction of the whole distance travelled: rejected."""
import math

import numpy as np
import torch

from loop_synthetic import Plane, cast, drifted_chain, look, render
from vigs_core.frontend import DISFlowEstimator, PixelGrid
from vigs_core.loop.closure import LoopClosure
from vigs_core.loop.config import LoopConfig
from vigs_core.loop.detection import KeyframeView
from vigs_core.solver import Intrinsics

W, H = 160, 120
INTR = Intrinsics(100.0, 100.0, 79.5, 59.5)
GRID = PixelGrid(W, H, 8)
N = 70
STEP_M = 0.08
PERIOD_M = 0.8


def corridor():
    e = np.eye(3)
    return [
        Plane(np.array([-3.0, 2.0, 0.0]), e[0], e[2], 20.0, 3.0, seed=11, period_u=PERIOD_M),    # wall y = 2
        Plane(np.array([-3.0, -1.0, 0.0]), e[0], e[1], 20.0, 3.0, seed=12, period_u=PERIOD_M),   # floor z = 0
    ]


def test_repeated_texture_without_revisit_gives_no_loop():
    torch.set_num_threads(1)
    planes = corridor()
    truth = torch.stack([look(math.pi / 2, np.array([STEP_M * k, 0.0, 1.5]), pitch=math.radians(25))
                         for k in range(N)])
    est, sigma = drifted_chain(truth, rot_per_step=0.0, log_scale_per_step=0.002, trans_noise=0.002)
    closure = LoopClosure(LoopConfig(asynchronous=False), DISFlowEstimator(GRID), INTR)
    views: list[KeyframeView] = []
    for k in range(N):
        depth = torch.from_numpy(cast(planes, truth[k], GRID.coords(), INTR, shade=False)[0]) * sigma[k]
        view = KeyframeView.from_depth(k, render(planes, truth[k], INTR, W, H), est[k], depth)
        closure.add_keyframe(view, views)
        views.append(view)
        assert not closure.start_pgba({v.id: v.T_WC for v in views})
    stats = closure.stats
    assert stats.candidates > 0                       # the repeated texture does fake candidates ...
    assert stats.loops_found == 0                     # ... but none is accepted
    assert stats.loops_rejected == stats.candidates
    assert any("drift allowance" in r for r in stats.rejection_reasons)
    assert stats.pgba_runs == 0
