"""Dense visual-inertial odometry: the dense monocular front end with the inertial back end of VIGS-SLAM.

:class:`VisualInertialOdometry` extends :class:`~vigs_core.frontend.odometry.DenseOdometry` through its hooks:

* every keyframe registers its inertial state (velocity, bias) with the
  :class:`~vigs_core.vio.estimator.VisualInertialEstimator`;
* each dense BA receives the inertial terms of its window as
  :class:`~vigs_core.solver.dense_ba.AdditionalTerms` (one normal equation per LM iteration, VIGS-SLAM 3.3) and
  returns the optimised velocities and biases;
* after each keyframe the stage machine runs (VIGS-SLAM 3.2); when the inertial-only stage succeeds the whole
  map (keyframe poses, disparities, every frame's pose) is rescaled and gravity-aligned and a joint VI-BA
  follows at once;
* once metric, every frame's pose prior comes from IMU preintegration from the latest keyframe (falling back
  to that keyframe's pose when the preintegration covariance trace exceeds tau), replacing the constant-velocity
  model (unless ``imu_keyframe_init`` is off); before that, the rotation of the constant-velocity prediction is
  replaced by the gyro's (rotation needs neither scale nor gravity), which keeps the flow initialisation good
  when frames are far apart (frame stride);
* once metric, BA holds only ``metric_fixed_keyframes`` (default 1) window keyframes fixed: the inertial terms
  make the scale observable, so it is no longer pinned by a second fixed keyframe; the fixed keyframes also keep
  their velocity and bias (anchor prior), so a window cannot trade the scale against velocities and biases, and
  (``metric_hold_fixed_disparity``) their disparities, so the depth map carries the scale between windows;
* optionally (``scale_refinement``), ``metric_hold_delay_s`` after the alignment, when the depth starts being
  held, the scale and gravity direction are re-estimated once inertial-only over the keyframes since the
  alignment and the whole map is rescaled (:meth:`VisualInertialEstimator.check_scale`);
* once metric, every keyframe's state is checked after its BA, ``metric_hold_delay_s`` after the alignment the
  scale is checked, and from then on every few keyframes over a rolling window
  (:class:`~vigs_core.vio.estimator.VisualInertialEstimator` ``health``, ``check_scale``, ``monitor_scale``); a
  failure sends the estimator back to the vision-only stage on the current map and it initialises again;
* every processed frame gets a status (:data:`FRAME_STATUSES`, :attr:`VisualInertialOdometry.frame_status`),
  the estimator's when the frame's pose is published (before its keyframe work): ``initialising`` before the
  first alignment, ``tracking`` once metric, ``lost`` from a failure until the
  estimator is metric again, ``reinitialised`` after that. A failure also marks ``lost`` the frames it shows were
  wrong: those after the previous keyframe (a divergent state), all since the alignment (a scale that did not
  hold), or those since the last rolling check that held (a scale that drifted). The status is the metric
  claim: ``tracking`` and ``reinitialised`` frames are metric;
* alternatively (``marginalize``), a keyframe leaving the window once metric is marginalised into a Gaussian
  prior on the remaining keyframes' poses, velocities and biases (:mod:`vigs_core.vio.marginalization`) and BA
  holds no keyframe fixed;

Still start: a monocular front end cannot initialise without parallax, so a platform standing still would get
no pose at all. While the front end has not initialised and the frame's mean flow from the first frame stays
below ``VioConfig.still_max_flow_px`` (the camera has not moved), the frame is held at the first frame's pose
(the identity: the world is the first camera's frame, as for the front end). Once the front end initialises,
its own poses replace the held ones. (The IMU's vibration level cannot tell standing from flying on EuRoC:
the MAV's motors run while it stands.) The front end's two-view initialisation rejects standing-still flow
itself (``DenseOdometry._two_view``); a gyro check of its rotation would not work here: before the inertial
stage the gyro bias is unknown, and EuRoC's 0.08 rad/s turns into 14 deg in 3 s.

With ``VioConfig.enabled`` off it behaves exactly like the vision-only odometry.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from vigs_core.frontend.odometry import DenseOdometry, FrameRows, Keyframe, OdometryConfig
from vigs_core.imu.buffer import ImuBuffer
from vigs_core.imu.preintegration import preintegrate_intervals
from vigs_core.geometry import se3_inverse
from vigs_core.solver import BAResult, EdgeSet, Intrinsics
from vigs_core.solver.normal_equations import linearize_visual, schur_reduce
from vigs_core.types import ImuNoise, ImuSamples
from vigs_core.vio.config import VioConfig
from vigs_core.vio.estimator import VisualInertialEstimator
from vigs_core.vio.initialization import WorldAlignment
from vigs_core.vio.keyframe_init import KeyframePrediction


INCREMENT_BATCH_S = 20.0
"""IMU seconds preintegrated in one batch for the frames' velocity increments: at the world alignment, the frames
tracked before it wait for their increments at once, seconds behind sparse keyframes each (531 s of IMU in 218
intervals on hybrid V1_01, which took about 300 MB of temporaries in one batch)."""

FRAME_STATUSES = ("initialising", "tracking", "lost", "reinitialised")
METRIC_STATUSES = ("tracking", "reinitialised")


def batches_up_to(lengths: np.ndarray, limit: int) -> list[np.ndarray]:
    """Consecutive index groups of ``lengths`` (N,) whose lengths sum to at most ``limit`` each (a longer one
    alone), in order: a batched computation over them keeps its temporaries bounded."""
    groups, start, total = [], 0, 0
    for n, length in enumerate(np.asarray(lengths).tolist()):
        if n > start and total + length > limit:
            groups.append(np.arange(start, n))
            start, total = n, 0
        total += length
    if len(lengths):
        groups.append(np.arange(start, len(lengths)))
    return groups


class VisualInertialOdometry(DenseOdometry):
    """Dense monocular odometry with tightly coupled IMU fusion (module docstring).

    Args:
        intrinsics: pinhole intrinsics of the (undistorted) input images.
        width, height: input image size, pixels.
        imu: the IMU record (body frame, same clock as the images): a growing
            :class:`~vigs_core.imu.buffer.ImuBuffer` the caller appends to as samples arrive (streaming,
            :class:`vigs_core.system.stream.OdometryStream`), or the samples of a whole recording.
        noise: IMU noise densities.
        T_bc: (4, 4) camera pose in the body (IMU) frame (EuRoC ``T_BS`` of cam0).
        config: front-end settings; vio: visual-inertial settings.
    """

    def __init__(self, intrinsics: Intrinsics, width: int, height: int, imu: ImuBuffer | ImuSamples, noise: ImuNoise,
                 T_bc: np.ndarray | torch.Tensor, config: OdometryConfig | None = None,
                 vio: VioConfig | None = None) -> None:
        super().__init__(intrinsics, width, height, config)
        self.vio_config = vio or VioConfig()
        self.vio = VisualInertialEstimator(self.vio_config, imu, noise, T_bc)
        self._prediction: tuple[int, KeyframePrediction] | None = None   # (frame stamp, IMU prediction)
        self._held: list[int] = []                                          # stamps held still before init
        self._anchored: set[int] = set()                                    # fixed keyframes of the current BA
        self.frame_status: dict[int, str] = {}                              # stamp (ns) -> status, every frame
        self._increments = FrameRows((4,))   # per frame row: dt, dv from its settled keyframe (frame_velocities)
        self._awaiting_increments: list[int] = []   # settled keyframes whose frames' increments wait for metric

    # ------------------------------------------------------------------ hooks of DenseOdometry
    def _new_keyframe(self, frame_idx: int, image: np.ndarray, pose: torch.Tensor, disp: torch.Tensor) -> Keyframe:
        kf = super()._new_keyframe(frame_idx, image, pose, disp)
        velocity = None
        if self._prediction is not None and self._prediction[0] == kf.t_ns:
            velocity = self._prediction[1].velocity
        elif self.vio.metric and self.vio.states:
            prev = self.keyframes[max(self.vio.states)]
            if not self.vio.imu_covers(prev.t_ns, kf.t_ns):   # after an IMU gap: the keyframes' own velocity
                p0, p1 = (se3_inverse(k.pose.to(torch.float64)) @ self.vio.T_cb for k in (prev, kf))
                velocity = (p1[:3, 3] - p0[:3, 3]) / ((kf.t_ns - prev.t_ns) * 1e-9)
        self.vio.add_keyframe(kf.id, kf.t_ns, velocity)
        return kf

    def _additional_terms(self, ids: list[int], poses: torch.Tensor):
        out = self.vio.terms(ids, poses, self._anchored)
        return (None, None) if out is None else out

    def _after_ba(self, ids: list[int], result: BAResult) -> None:
        if result.extra_state is not None:
            self.vio.update(ids, result.extra_state)

    def _holds_scale_gauge(self) -> bool:
        """Before the map is metric the scale is the inertial stages' to fix, so the fixed keyframes' disparities
        stay free (holding them in the vision-only stage tilted the gravity alignment of tests/test_vio_odometry.py's
        room sequence from 1.4 to 2.8 deg). Once metric, from ``metric_hold_delay_s`` after the alignment on, they
        are held with ``metric_hold_fixed_disparity``: the fixed keyframe's depth map carries the window's scale
        from one window to the next (see that option). A metric window without inertial terms (an IMU gap in it)
        holds them at once: nothing else observes its scale."""
        c = self.vio_config
        if not c.enabled:
            return self.config.hold_fixed_disparity
        oldest, newest = (self.keyframes[k] for k in (self.graph.keyframes[0], self.graph.keyframes[-1]))
        if self.vio.metric and not self.vio.imu_covers(oldest.t_ns, newest.t_ns):
            return True
        return c.metric_hold_fixed_disparity and self.vio.hold_delay_passed(newest.t_ns)

    def _insert_into_graph(self, kf: Keyframe) -> list[tuple[int, int]]:
        """Insert as the front end does; a keyframe that leaves the window is marginalised (once metric)."""
        c = self.vio_config
        if not (c.enabled and c.marginalize and self.vio.metric):
            return super()._insert_into_graph(kf)
        before, edges = list(self.graph.keyframes), dict(self.edges)
        new_edges = super()._insert_into_graph(kf)
        for k in [k for k in before if k not in self.graph.keyframes]:
            window = [x for x in before if x >= k]
            self._marginalize(window, {e: corr for e, corr in edges.items() if e[0] == k and e[1] in window})
        return new_edges

    def _edge_system(self, window: list[int], edges: dict):
        """Linearised visual terms (float64, :func:`~vigs_core.solver.normal_equations.linearize_visual`) of
        ``edges`` {(i, j): correspondences} over the keyframes ``window`` at their current estimate."""
        index = {k: n for n, k in enumerate(window)}
        es = sorted(edges)
        edge_set = EdgeSet(torch.tensor([index[i] for i, _ in es]), torch.tensor([index[j] for _, j in es]),
                           torch.from_numpy(np.stack([edges[e].target for e in es])),
                           torch.stack([self._weights(edges[e]) for e in es]))
        poses = torch.stack([self.keyframes[k].pose for k in window]).double()
        disps = torch.stack([self.keyframes[k].disp for k in window]).double()
        return linearize_visual(poses, disps, edge_set, self.coords.double(), self.intr, self.config.ba.huber_delta)

    def _marginalize(self, window: list[int], hosted: dict) -> None:
        """Marginalise ``window[0]`` (:meth:`VisualInertialEstimator.marginalize`, :mod:`vigs_core.vio.marginalization`)
        with the reduced camera system of its hosted edges ``hosted`` {(window[0], j): correspondences} (its
        disparities eliminated, no LM damping); the edges ``(j, window[0])`` hosted by the remaining keyframes are
        dropped."""
        poses = torch.stack([self.keyframes[k].pose for k in window]).double()
        visual = None
        if hosted and self.vio_config.marginalize_visual:
            system = self._edge_system(window, hosted)
            visual = schur_reduce(system, system.C + self.config.ba.disparity_damping)
        self.vio.marginalize(window, poses, visual)

    def _ba(self, iterations: int, fixed: list[int] | None = None) -> None:
        n_fixed = self.vio_config.metric_fixed_keyframes
        if fixed is None and self.vio.prior_holds_gauge(list(self.graph.keyframes)):
            fixed = []   # the marginalisation prior holds the gauge (and the scale)
        elif fixed is None and self.vio.metric and n_fixed > 0:
            fixed = self.graph.keyframes[:n_fixed]   # the IMU observes the scale: no second fixed keyframe
            if fixed == self.graph.fixed_ids():
                fixed = None
        self._anchored = set(self.graph.fixed_ids() if fixed is None else fixed)
        super()._ba(iterations, fixed)

    def _predict_pose(self) -> torch.Tensor:
        frame = self.frames[-1]
        kf = self.keyframes[self.graph.keyframes[-1]]
        pred = self.vio.predict(kf.id, kf.pose, frame.t_ns)
        if pred is None:
            self._prediction = None
            cv = super()._predict_pose()
            R_cw = self.vio.predict_rotation(kf.id, kf.pose, frame.t_ns)
            if R_cw is None:
                return cv
            out = cv.clone()   # gyro rotation, constant-velocity camera centre (the scale is not known yet)
            out[:3, :3] = R_cw
            out[:3, 3] = -(R_cw @ (-(cv[:3, :3].T @ cv[:3, 3])))
            return out
        self._prediction = (frame.t_ns, pred)
        return pred.T_cw

    def _initialize(self, T_10: torch.Tensor, disp0: torch.Tensor) -> None:
        super()._initialize(T_10, disp0)
        self._advance_stages()

    def _after_keyframe(self) -> None:
        self._advance_stages()

    # ------------------------------------------------------------------ stages
    def _advance_stages(self) -> None:
        ids = sorted(self.keyframes)
        stamps = np.array([self.keyframes[k].t_ns for k in ids], dtype=np.int64)
        poses = torch.stack([self.keyframes[k].pose for k in ids])
        t0 = self._tic()
        reason = self.vio.health(ids, stamps, poses)
        if reason is not None:   # the frames since the previous keyframe were tracked with the divergent state
            self._fail(int(stamps[-1]), reason, int(stamps[-2]))
        # frames may be tracked during the rolling check's solve: it changes the state only after it
        elif (reason := self.vio.monitor_scale(ids, stamps, poses, between=self._yield_point)) is not None:
            self._fail(int(stamps[-1]), reason, self.vio.scale_verified_ns)   # since the last check that held
        alignment = self.vio.on_keyframe(ids, stamps, poses)
        if alignment is None and self.vio.scale_check_due(int(stamps[-1])):
            since = self.vio.metric_since_ns
            # frames may be tracked during the solve: the check changes the state only after it
            refined = self.vio.check_scale(ids, stamps, poses, between=self._yield_point)
            if not self.vio.metric:   # the scale did not hold since the alignment
                self._mark_lost(since)
            if refined is not None:
                self._apply_alignment(refined)
            self._toc("vio_init", t0)
            return
        self._toc("vio_init", t0)
        if alignment is not None:
            self._apply_alignment(alignment)
            self._ba(self.config.ba.iterations)

    def _fail(self, t_ns: int, reason: str, wrong_after_ns: int) -> None:
        """A failure detected at the keyframe at ``t_ns``: the estimator initialises again; the frames after
        ``wrong_after_ns`` are marked lost."""
        self.vio.fail(t_ns, reason)
        self._mark_lost(wrong_after_ns)

    def _mark_lost(self, after_ns: int) -> None:
        for t in [t for t, status in self.frame_status.items() if t > after_ns and status in METRIC_STATUSES]:
            self.frame_status[t] = "lost"

    @property
    def status(self) -> str:
        """The estimator's status now (:data:`FRAME_STATUSES`), as the next frame would get it."""
        if self.vio.metric:
            return "reinitialised" if self.vio.failures else "tracking"
        return "lost" if self.vio.failures else "initialising"

    def _apply_alignment(self, al: WorldAlignment) -> None:
        """Re-express the whole map in the metric gravity-aligned world (keyframes, disparities, frames)."""
        for kf in self.keyframes.values():
            kf.pose = al.pose(kf.pose)
            kf.rescale_depth(al.scale)
        self.scale_relative_translations(dict.fromkeys(self.keyframes, al.scale))
        for f in self.frames:
            if (odom := f.odom) is not None:
                f.odom = al.pose(odom)

    # ------------------------------------------------------------------ still start
    def process(self, t_ns: int, image: np.ndarray,
                on_pose: Callable[[torch.Tensor], None] | None = None) -> torch.Tensor | None:
        """Consume one frame; its world->camera pose (4, 4), the first frame's while still (module docstring),
        or None while not initialised (``on_pose``: see :meth:`DenseOdometry.process`)."""
        self.frame_status[int(t_ns)] = self.status   # the claim its pose is published with (before keyframe work)
        return super().process(t_ns, image, on_pose)

    def _pose_before_initialization(self, t_ns: int) -> torch.Tensor | None:
        if not self._still():
            return None
        self._held.append(int(t_ns))
        return torch.eye(4, dtype=torch.float64)

    def _still(self) -> bool:
        if not self.vio_config.enabled or self.initialized:
            return False
        if len(self.frames) == 1:
            return True
        corr = self.frames[-1].pending
        from_first = bool(self._init_candidates) and self._init_candidates[0][0] == 0
        return corr is not None and from_first and corr.mean_flow < self.vio_config.still_max_flow_px

    def held_frames(self) -> np.ndarray:
        """Stamps (M,) ns of the frames held at the first frame's pose; empty once the front end initialised."""
        return np.zeros(0, dtype=np.int64) if self.initialized else np.array(self._held, dtype=np.int64)

    def _with_held(self, t_ns: np.ndarray, poses: torch.Tensor) -> tuple[np.ndarray, torch.Tensor]:
        held = self.held_frames()
        if len(held) == 0:
            return t_ns, poses
        t_all = np.concatenate((t_ns, held))
        order = np.argsort(t_all, kind="stable")
        eye = torch.eye(4, dtype=torch.float64).expand(len(held), 4, 4)
        return t_all[order], torch.cat((poses, eye))[torch.as_tensor(order)]

    def final_frame_poses(self) -> tuple[np.ndarray, torch.Tensor]:
        """The front end's final poses, plus the held still-start frames (module docstring)."""
        return self._with_held(*super().final_frame_poses())

    def odometry_poses(self) -> tuple[np.ndarray, torch.Tensor]:
        """The front end's causal poses, plus the held still-start frames (module docstring)."""
        return self._with_held(*super().odometry_poses())

    # ------------------------------------------------------------------ outputs
    def frame_velocities(self) -> tuple[np.ndarray, torch.Tensor]:
        """Stamps (N,) ns and body velocities (N, 3) m/s in the world of every posed frame, propagated by the
        IMU from the frame's reference keyframe state, ``v = v_k + g dt + R_wb,k dv_kf``; NaN while the map is not
        metric and for a frame whose interval holds an IMU gap over ``max_imu_gap_s`` (not integrated across) or
        whose IMU is no longer held. ``dt, dv_kf`` are those kept when the keyframe settled
        (:meth:`_on_settled`), else preintegrated now (in one batch at the keyframes' biases)."""
        posed = [f for f in self.frames if f.ref is not None]
        t = np.array([f.t_ns for f in posed], dtype=np.int64)
        vel = torch.full((len(posed), 3), float("nan"), dtype=torch.float64)
        if not self.vio.metric:
            return t, vel
        inc = self._increments.take([f._row for f in posed])
        at_kf = np.array([f.t_ns == self.vio.states[f.ref].t_ns for f in posed], dtype=bool)
        for n in np.flatnonzero(at_kf):
            vel[n] = self.vio.states[posed[n].ref].velocity
        pending = np.flatnonzero(np.isnan(inc[:, 0]) & ~at_kf)
        if len(pending):
            inc[pending] = self._velocity_increments([posed[n].ref for n in pending], t[pending])
        between = np.flatnonzero(np.isfinite(inc[:, 0]) & ~at_kf).tolist()
        if between:
            refs = [posed[n].ref for n in between]
            R_wb = torch.stack([se3_inverse(self.keyframes[k].pose.to(torch.float64))[:3, :3] @ self.vio.T_cb[:3, :3]
                                for k in refs])
            v0 = torch.stack([self.vio.states[k].velocity for k in refs])
            dt, dv = torch.from_numpy(inc[between, :1]), torch.from_numpy(inc[between, 1:])
            vel[between] = v0 + self.vio.gravity_world() * dt + (R_wb @ dv[..., None])[..., 0]
        return t, vel

    def _velocity_increments(self, refs: list[int], stamps: np.ndarray) -> np.ndarray:
        """``(dt s, dv_kf (3,))`` (M, 4) from keyframes ``refs`` to the frames at ``stamps`` (M,) ns, preintegrated
        at the keyframes' biases; NaN across an IMU gap or where the IMU is not held."""
        out = np.full((len(refs), 4), np.nan)
        sel = np.array([n for n, (k, t) in enumerate(zip(refs, stamps))
                        if self.vio.imu_covers(self.vio.states[k].t_ns, int(t))], dtype=np.int64)
        if len(sel) == 0:
            return out
        b = torch.stack([self.vio.bias_of(refs[n]) for n in sel])
        t0 = np.array([self.vio.states[refs[n]].t_ns for n in sel], dtype=np.int64)
        t1 = np.asarray(stamps, dtype=np.int64)[sel]
        for part in batches_up_to(t1 - t0, int(INCREMENT_BATCH_S * 1e9)):
            pre = preintegrate_intervals(self.vio.imu, t0[part], t1[part], self.vio.noise, b[part, :3], b[part, 3:],
                                         self.vio_config.scheme)
            out[sel[part], 0] = pre.dt.numpy()
            out[sel[part], 1:] = pre.delta_v.numpy()
        return out

    def _on_settled(self, ids: list[int]) -> None:
        """Keep the velocity increments of the settled keyframes' frames (:meth:`frame_velocities`): the IMU
        behind the window is then not needed for the outputs, so a streamed record can be bounded
        (:class:`~vigs_core.imu.buffer.ImuBufferConfig` ``max_age_s``). Keyframes settled before the map is
        metric wait for it: their biases are estimated by the initialisation."""
        self._awaiting_increments += [k for k in ids if k in self.vio.states]
        if not self.vio.metric or not self._awaiting_increments:
            return
        ids, self._awaiting_increments = set(self._awaiting_increments), []
        oldest = min(self.vio.states[k].t_ns for k in ids)
        frames = []
        for f in reversed(self.frames):   # a settled keyframe's frames are among the last few window's worth
            if f.t_ns < oldest:
                break
            if f.ref in ids and f.t_ns != self.vio.states[f.ref].t_ns:
                frames.append(f)
        if frames:
            inc = self._velocity_increments([f.ref for f in frames], np.array([f.t_ns for f in frames]))
            for f, row in zip(frames, inc):
                self._increments.record(f._row)[:] = row

    def frame_twist(self, t_ns: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The twist of the frame at ``t_ns`` when it was the last one tracked with an IMU prediction: velocity
        (3,) m/s in the world (the keyframe state propagated by the IMU to the frame, as its pose prediction)
        and angular velocity (3,) rad/s in the body (the gyro sample nearest the frame minus the newest
        keyframe's gyro bias); None before the map is metric, across an IMU gap, or for another frame."""
        if self._prediction is None or self._prediction[0] != int(t_ns) or not self._prediction[1].from_imu:
            return None
        imu = self.vio.imu_buffer.samples(int(t_ns), int(t_ns))
        nearest = int(np.argmin(np.abs(imu.t_ns - int(t_ns))))
        bias = self.vio.bias_of(self.graph.keyframes[-1])
        omega = torch.from_numpy(np.asarray(imu.gyro[nearest], dtype=np.float64)) - bias[:3]
        return self._prediction[1].velocity.clone(), omega

    def keyframe_states(self) -> dict:
        """JSON-ready per-keyframe inertial states: stamps, velocities (m/s), biases (b_g rad/s, b_a m/s^2)."""
        ids = sorted(self.vio.states)
        return {
            "t_ns": [int(self.vio.states[k].t_ns) for k in ids],
            "velocity": [[float(x) for x in self.vio.states[k].velocity] for k in ids],
            "bias_gyro": [[float(x) for x in self.vio.bias_of(k)[:3]] for k in ids],
            "bias_acc": [[float(x) for x in self.vio.bias_of(k)[3:]] for k in ids],
        }

    def report(self) -> dict:
        """The estimator's report (stage, scale history, biases, prediction counts) and the number of held
        still-start frames, for report.json."""
        counts = {status: 0 for status in FRAME_STATUSES}
        for status in self.frame_status.values():
            counts[status] += 1
        return {**self.vio.report(), "held_still_frames": int(len(self.held_frames())), "frame_status": counts}
