"""The relative-pose graph over all keyframes and the PGBA driver that optimises it beside tracking (VIGS-SLAM
Sec. 3.1, pose-graph bundle adjustment).

Graph: a node per keyframe, its similarity ``S_k = T_WC_k`` (the current rigid estimate, scale 1: the
keyframe's depth units are the map's). Odometry edges join each keyframe to its ``odometry_neighbours``
predecessors; their measurement is the *current* relative pose ``S_i^{-1} S_j`` when the graph is built (the
local window's relative poses: final for keyframes that left the window) and their information comes from the
dense two-view correspondences (:func:`vigs_core.loop.two_view.relative_information`) or, lacking those, from
fixed standard deviations. Loop edges carry the Sim(3) measured by :class:`~vigs_core.loop.detection.LoopDetector`
and its information, under a Huber kernel. The oldest keyframe is the gauge. Optimising gives ``S'_k``; the
result is a per-keyframe left correction ``C_k = S'_k S_k^{-1}`` (world frame), applied later to whatever the
keyframe's state has become meanwhile (tracking goes on while PGBA runs on the worker thread of
:class:`vigs_core.loop.closure.LoopClosure`; see :mod:`vigs_core.loop.apply`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import torch

from vigs_core.loop.config import LoopGraphConfig
from vigs_core.loop.detection import LoopEdge
from vigs_core.loop.pose_graph import PoseGraph, PoseGraphConfig, optimize_pose_graph

F64 = torch.float64


def default_information(config: LoopGraphConfig) -> torch.Tensor:
    """Diagonal odometry-edge information (7, 7) from the configured standard deviations."""
    sig = torch.tensor([config.sigma_translation_m] * 3 + [config.sigma_rotation_rad] * 3 + [config.sigma_log_scale],
                       dtype=F64)
    return torch.diag(sig**-2)


class KeyframePoseGraph:
    """Odometry and loop edges between keyframe ids (module docstring)."""

    def __init__(self, config: LoopGraphConfig | None = None) -> None:
        self.config = config or LoopGraphConfig()
        self.ids: list[int] = []
        self.odometry: dict[tuple[int, int], torch.Tensor] = {}   # (i, j) -> information (7, 7)
        self.loops: list[LoopEdge] = []
        self.metric: set[int] = set()   # keyframes created while the odometry was metric

    def add_keyframe(self, kf_id: int, information: dict[int, torch.Tensor] | None = None,
                     metric: bool = False) -> list[tuple[int, int]]:
        """Add keyframe ``kf_id`` (newer than all) with odometry edges from its predecessors.

        Args:
            information: optional ``{previous id: (7, 7)}`` information of the edge (previous, kf_id), e.g. from
                the frontend's dense correspondences; missing ones get :func:`default_information`.
            metric: the keyframe was created while the visual-inertial odometry was metric: the IMU observed its
                scale and gravity direction in the window (see :meth:`build`).
        Returns:
            The new odometry edges ``(previous, kf_id)``.
        """
        if self.ids and kf_id <= self.ids[-1]:
            raise ValueError(f"KeyframePoseGraph.add_keyframe: id {kf_id} is not newer than {self.ids[-1]}")
        information = information or {}
        edges = [(i, kf_id) for i in self.ids[-self.config.odometry_neighbours:]]
        for e in edges:
            self.odometry[e] = information.get(e[0], default_information(self.config)).to(F64)
        self.ids.append(kf_id)
        if metric:
            self.metric.add(kf_id)
        return edges

    def add_loop(self, edge: LoopEdge) -> None:
        for k in (edge.old, edge.new):
            if k not in self.ids:
                raise KeyError(f"loop edge ({edge.old}, {edge.new}) names keyframe {k}, not in the graph")
        self.loops.append(edge)

    def build(self, poses: dict[int, torch.Tensor], units: dict[int, float] | None = None
              ) -> tuple[PoseGraph, list[int]]:
        """The :class:`PoseGraph` at the current poses ``{id: T_WC (4, 4)}`` (every graph id needed) and its
        node ids in order. Each metric keyframe's log scale gets an absolute prior of standard deviation
        ``sigma_metric_log_scale`` (a loop corrects its pose, not its scale) and, when ``sigma_metric_gravity_rad``
        > 0, its gravity direction one of that deviation. Keyframes from before the initialisation keep a free
        scale: the vision-only map drifted in scale before it was aligned once as a whole, so a loop to one of
        them measures that drift (a relative scale of several percent) and must not turn it into translation.

        ``units``: the keyframes' current depth units (product of the loop-correction scales applied so far,
        default 1). A loop edge measured when the units were ``u_a, u_b`` relates points ``X_b -> X_a``; with the
        units now ``u'_a, u'_b`` it becomes ``D(u'_a / u_a) Z D(u_b / u'_b)``, ``D(k) = diag(k, k, k, 1)``.
        """
        missing = [k for k in self.ids if k not in poses]
        if missing:
            raise KeyError(f"KeyframePoseGraph.build: no pose for keyframes {missing[:10]}")
        if len(self.ids) < 2:
            raise ValueError(f"KeyframePoseGraph.build: needs at least 2 keyframes, has {len(self.ids)}")
        ids = list(self.ids)
        index = {k: n for n, k in enumerate(ids)}
        S = torch.stack([torch.as_tensor(poses[k], dtype=F64) for k in ids])
        odo = sorted(self.odometry)
        ei = torch.tensor([index[i] for i, _ in odo] + [index[e.old] for e in self.loops], dtype=torch.int64)
        ej = torch.tensor([index[j] for _, j in odo] + [index[e.new] for e in self.loops], dtype=torch.int64)
        z_odo = PoseGraph.relative(S, ei[:len(odo)], ej[:len(odo)])
        units = units or {}

        def rescaled(e: LoopEdge) -> torch.Tensor:
            k_a = units.get(e.old, 1.0) / e.unit_old
            k_b = units.get(e.new, 1.0) / e.unit_new
            D_a = torch.diag(torch.tensor([k_a, k_a, k_a, 1.0], dtype=F64))
            D_b = torch.diag(torch.tensor([1 / k_b, 1 / k_b, 1 / k_b, 1.0], dtype=F64))
            return D_a @ e.relative.to(F64) @ D_b

        meas = torch.cat([z_odo] + [rescaled(e)[None] for e in self.loops])
        info = torch.cat([self.odometry[e][None] for e in odo] + [e.information.to(F64)[None] for e in self.loops])
        robust = torch.cat((torch.zeros(len(odo), dtype=torch.bool), torch.ones(len(self.loops), dtype=torch.bool)))
        scale_prior, gravity_prior = None, None
        metric = torch.tensor([k in self.metric for k in ids], dtype=F64)
        if self.metric:
            scale_prior = metric * self.config.sigma_metric_log_scale ** -2
        if self.metric and self.config.sigma_metric_gravity_rad > 0:
            gravity_prior = metric * self.config.sigma_metric_gravity_rad ** -2
        return PoseGraph(S, ei, ej, meas, info, robust=robust, fixed=[0], scale_information=scale_prior,
                         gravity_information=gravity_prior), ids


@dataclass
class PGBAResult:
    """Per-keyframe left corrections ``{id: C_k (4, 4)}`` (``S'_k = C_k S_k``), the graph's cost before and
    after, LM iterations, the loops it included and the wall time (s)."""

    corrections: dict[int, torch.Tensor]
    initial_cost: float
    final_cost: float
    iterations: int
    loops: int
    seconds: float


def run_pgba(graph: PoseGraph, ids: list[int], loops: int, config: PoseGraphConfig) -> PGBAResult:
    """Optimise ``graph`` (nodes ``ids``) and return the per-keyframe corrections."""
    t0 = time.perf_counter()
    result = optimize_pose_graph(graph, config)
    C = result.poses @ torch.linalg.inv(graph.poses.to(F64))
    return PGBAResult({k: C[n] for n, k in enumerate(ids)}, result.initial_cost, result.final_cost,
                      result.iterations, loops, time.perf_counter() - t0)
