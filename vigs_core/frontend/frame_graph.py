"""Frame graph over a sliding window of keyframes (VIGS-SLAM 3.1, DROID-SLAM 3.4 frontend).

Edges are directed keyframe pairs ``(i, j)`` (source grid pixels of ``i`` observed in ``j``) and always come in
both directions, so both keyframes' disparities are constrained. A new keyframe is connected to its
``temporal_radius`` predecessors (temporal adjacency) and to up to ``covis_max_edges`` older window keyframes
(among those that stay in the window) whose predicted mean flow to it (geometric warp with the current poses
and depths, see :func:`vigs_core.frontend.odometry.DenseOdometry.predicted_flow`) is below
``covis_max_flow_px`` (flow-based co-visibility).

Keyframes leaving the window are FIXED, not marginalised: their poses and disparities are frozen at their last
estimate and their edges are dropped. Inside the window the ``fixed`` oldest keyframes are held constant as the
gauge: their poses fix 6 DoF; with :attr:`vigs_core.frontend.odometry.OdometryConfig.hold_fixed_disparity` their
disparities are held too and the depth map pins the monocular scale, otherwise (the default) the scale is a
free direction of BA that only the LM damping holds (see that option for the measured effect). Fixing discards
the information the old edges carried (no prior is kept), so the window drifts like visual odometry;
marginalisation would keep it as a dense prior at the cost of fill-in (eliminating a keyframe's P disparities
couples all its neighbours' poses) and of linearisation errors that cannot be undone once the prior is formed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from vigs_core.ranges import bounded


@dataclass
class FrameGraphConfig:
    """Args:
        window: keyframes optimised together.
        fixed: oldest window keyframes whose poses are held constant (and disparities, with
            ``OdometryConfig.hold_fixed_disparity``).
        temporal_radius: edges from a new keyframe to this many previous keyframes.
        covis_max_flow_px: co-visibility edge when the predicted mean flow is below this, input pixels.
        covis_max_edges: at most this many co-visibility edges (pairs) per new keyframe.
    """

    window: int = bounded(8, 2)
    fixed: int = bounded(1, 1)
    temporal_radius: int = bounded(2, 0)
    covis_max_flow_px: float = bounded(50.0, 0)
    covis_max_edges: int = bounded(1, 0)


class FrameGraph:
    """Keyframe ids in the window (oldest first) and the directed edges between them."""

    def __init__(self, config: FrameGraphConfig | None = None) -> None:
        self.config = config or FrameGraphConfig()
        if self.config.window < 2 or not 1 <= self.config.fixed < self.config.window:
            raise ValueError(f"FrameGraphConfig: window {self.config.window}, fixed {self.config.fixed}; "
                             "expected window >= 2 and 1 <= fixed < window")
        self.keyframes: list[int] = []
        self.edges: set[tuple[int, int]] = set()

    def add_keyframe(self, kf_id: int, predicted_flow: Callable[[int, int], float]
                     ) -> tuple[list[tuple[int, int]], list[int]]:
        """Insert keyframe ``kf_id`` (newer than all), connect it, slide the window.

        ``predicted_flow(i, j)`` gives the predicted mean flow from ``i`` to ``j`` (pixels, inf when not
        co-visible). Returns the new edges (both directions) and the keyframe ids that left the window.
        """
        if self.keyframes and kf_id <= self.keyframes[-1]:
            raise ValueError(f"FrameGraph.add_keyframe: id {kf_id} not newer than {self.keyframes[-1]}")
        cfg = self.config
        previous = self.keyframes[-cfg.temporal_radius:] if cfg.temporal_radius > 0 else []
        staying = self.keyframes[max(0, len(self.keyframes) + 1 - cfg.window):]   # still in the window after
        older = [k for k in staying if k not in previous]
        scored = sorted((predicted_flow(k, kf_id), k) for k in older)
        covisible = [k for flow, k in scored if flow < cfg.covis_max_flow_px][:cfg.covis_max_edges]
        new_edges = []
        for k in previous + covisible:
            new_edges += [(k, kf_id), (kf_id, k)]
        self.keyframes.append(kf_id)
        self.edges.update(new_edges)
        removed = []
        while len(self.keyframes) > cfg.window:
            old = self.keyframes.pop(0)
            removed.append(old)
            self.edges = {e for e in self.edges if old not in e}
        return new_edges, removed

    def is_temporal(self, i: int, j: int) -> bool:
        """Whether window keyframes ``i`` and ``j`` are at most ``temporal_radius`` apart in the window (an
        edge between them is a temporal one; other edges are co-visibility edges)."""
        return abs(self.keyframes.index(i) - self.keyframes.index(j)) <= self.config.temporal_radius

    def fixed_ids(self) -> list[int]:
        """Window keyframes held constant: the ``fixed`` oldest, leaving at least one free."""
        return self.keyframes[:min(self.config.fixed, max(len(self.keyframes) - 1, 1))]

    def sorted_edges(self) -> list[tuple[int, int]]:
        """Edges in a deterministic order."""
        return sorted(self.edges)
