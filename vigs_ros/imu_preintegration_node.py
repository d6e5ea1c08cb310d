"""IMU preintegration node: buffers the IMU, serves preintegration between keyframe stamps, and publishes
IMU-rate odometry propagated from the latest estimated state.

Topics (names are parameters; see params/imu_preintegration.yaml):

* in ``imu_topic`` (sensor_msgs/Imu, sensor-data QoS), taken by a thread of its own
  (:class:`vigs_ros.runtime.ThreadedSubscription`; the other callbacks share the node's state under ``lock``):
  validated on arrival
  (:class:`vigs_core.imu.buffer.ImuBuffer`): malformed, out-of-order and duplicated samples are dropped with a
  warning, gaps are reported, a sample stamped far ahead of the stream is held until the next one and rejected
  as an outlier when the stream goes on at its old time base.
* in ``keyframe_event_topic`` (vigs_msgs/NavState, reliable): the frontend created a keyframe at that stamp;
  its biases are the current estimate. The window from the previous keyframe's stamp to this one is
  preintegrated (:func:`vigs_core.imu.preintegration.preintegrate`, Forster et al. T-RO 2017) once the IMU
  covers it, linearised at the event's biases, and published.
* in ``state_topic`` (vigs_msgs/NavState, transient-local): the latest optimised state; odometry is
  propagated from it (:func:`vigs_core.imu.propagation.propagate_path`, Forster Eq. 33).
* out ``preintegrated_topic`` (vigs_msgs/PreintegratedImu, reliable).
* out ``odometry_topic`` (nav_msgs/Odometry, reliable): pose of ``base_frame`` in ``world_frame`` at IMU
  rate (every ``odometry_every_n``-th sample), velocity and bias-corrected angular rate in the body.
* out ``status_topic`` (diagnostic_msgs/DiagnosticArray, transient-local).
"""
from __future__ import annotations

import sys
import threading
import time
import warnings
from collections import deque

import numpy as np
import torch
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu
from vigs_msgs.msg import NavState, PreintegratedImu

from msg_adapters.imu import imu_to_sample
from msg_adapters.odometry import odometry_messages
from msg_adapters.types import RclpyTypes
from msg_adapters.vigs import NavStateData, PreintegrationData, msg_to_nav_state, preintegration_to_msg
from vigs_core.imu.buffer import ImuBuffer, ImuBufferConfig
from vigs_core.imu.preintegration import Preintegrated, preintegrate
from vigs_core.imu.propagation import ImuState, propagate_path
from vigs_core.ranges import Range
from vigs_core.types import ImuNoise
from vigs_ros.diagnostics import StatusReporter
from vigs_ros.params import ParamSpec, dataclass_specs, declare
from vigs_ros.qos import latched_qos, reliable_qos, sensor_qos
from vigs_ros.runtime import VigsNode, process_nice, run_nodes

NODE_NAME = "imu_preintegration"

PARAMS = [
    process_nice(-10),
    ParamSpec("imu_topic", "/imu", "input sensor_msgs/Imu topic (sensor-data QoS)"),
    ParamSpec("keyframe_event_topic", "/vigs/keyframe_events", "input vigs_msgs/NavState: new keyframes"),
    ParamSpec("state_topic", "/vigs/state", "input vigs_msgs/NavState: latest optimised state"),
    ParamSpec("preintegrated_topic", "/vigs/preintegrated_imu", "output vigs_msgs/PreintegratedImu"),
    ParamSpec("odometry_topic", "/vigs/imu_odometry", "output nav_msgs/Odometry at IMU rate"),
    ParamSpec("status_topic", "/vigs/status", "output diagnostic_msgs/DiagnosticArray"),
    ParamSpec("world_frame", "map", "frame of the propagated odometry (the estimator's world)"),
    ParamSpec("base_frame", "base_link", "body (IMU) frame: child frame of the odometry"),
    ParamSpec("gap_factor", 2.5, "an IMU interval longer than this many nominal periods is reported as a gap",
              range=Range(1, lo_open=True)),
    ParamSpec("buffer_s", 30.0, "IMU history kept (s)", range=Range(0, lo_open=True)),
    ParamSpec("gravity", 9.81, "gravity magnitude (m/s^2); the world z axis points up", range=Range(0, lo_open=True)),
    ParamSpec("integration_scheme", "closed_form", "preintegration scheme: closed_form or forster"),
    ParamSpec("publish_odometry", True, "publish IMU-rate propagated odometry"),
    ParamSpec("odometry_every_n", 1, "publish odometry for every n-th IMU sample", range=Range(1)),
    ParamSpec("odometry_before_init", False, "propagate odometry before the estimator reports inertial "
                                             "initialisation (the world is then not gravity-aligned)"),
    ParamSpec("event_timeout_s", 2.0, "give up on a keyframe window the IMU has not covered after this (wall s)",
              range=Range(0, lo_open=True)),
    ParamSpec("no_imu_error_s", 5.0, "report an error when no IMU message arrived this long after start (wall s)",
              range=Range(0, lo_open=True)),
    ParamSpec("status_period_s", 1.0, "period of the diagnostics status (s)", range=Range(0, lo_open=True)),
    ParamSpec("torch_threads", 1, "torch CPU threads of this process", range=Range(1)),
]
PARAMS += dataclass_specs(ImuNoise)   # gyro_noise_density, ..., rate_hz (vigs_core.types.ImuNoise)


class ImuPreintegrationNode(VigsNode):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.p = declare(self, PARAMS)
        torch.set_num_threads(int(self.p["torch_threads"]))
        if self.p["integration_scheme"] not in ("closed_form", "forster"):
            raise ValueError(f"integration_scheme must be closed_form or forster, got {self.p['integration_scheme']!r}")
        if int(self.p["odometry_every_n"]) < 1:
            raise ValueError(f"odometry_every_n must be >= 1, got {self.p['odometry_every_n']}")
        self.noise = ImuNoise(self.p["gyro_noise_density"], self.p["gyro_random_walk"], self.p["acc_noise_density"],
                              self.p["acc_random_walk"], self.p["rate_hz"])
        self.gravity = (0.0, 0.0, -float(self.p["gravity"]))
        self.types = RclpyTypes()
        self.status = StatusReporter(self, self.p["status_topic"], self.p["status_period_s"])
        self.buffer = ImuBuffer(ImuBufferConfig(self.p["rate_hz"], self.p["gap_factor"], self.p["buffer_s"]))
        self.last_keyframe: NavStateData | None = None
        self.pending: deque[tuple[NavStateData, NavStateData, float]] = deque()  # (from, to, wall time queued)
        self.state: ImuState | None = None  # propagated state at the newest odometry stamp
        self.state_initialized = False
        self._since_odom = 0
        self._started = time.monotonic()

        self.pub_pre = self.create_publisher(PreintegratedImu, self.p["preintegrated_topic"], reliable_qos(100))
        self.pub_odom = self.create_publisher(Odometry, self.p["odometry_topic"], reliable_qos(50))
        self.lock = threading.Lock()   # on_imu runs on the IMU subscription's own thread
        self.imu_sub = self.create_threaded_subscription(Imu, self.p["imu_topic"], self.on_imu, sensor_qos(200))
        self.odometry_latency_ms: deque[float] = deque(maxlen=2000)   # IMU reception -> odometry publish
        self._latencies_recorded = 0
        self.create_subscription(NavState, self.p["keyframe_event_topic"], self.on_keyframe_event, reliable_qos(100))
        self.create_subscription(NavState, self.p["state_topic"], self.on_state, latched_qos(1))
        self.create_timer(0.5, self.expire_events)

    # ------------------------------------------------------------------ inputs
    def on_imu(self, msgs: list[Imu]) -> None:
        """Buffer the samples taken (all those queued: :class:`ThreadedSubscription`), serve the keyframe windows
        they complete, then propagate odometry over all of them at once: a node that fell behind catches up in
        one vectorised propagation instead of one per sample."""
        with self.lock:
            accepted = sum(self.add_imu(m) for m in msgs)
            if not accepted:
                return
            self.serve_pending()
            self._since_odom += accepted
            if self.p["publish_odometry"] and self._since_odom >= int(self.p["odometry_every_n"]):
                self._since_odom = 0
                if self.publish_odometry(self.buffer.latest_ns):
                    self.record_latency()

    def record_latency(self) -> None:
        """Latency inside the node: DDS reception of the newest IMU sample to its odometry published (the rest of
        what a subscriber sees is transport and its own scheduling); p50 / p95 in the status every 200 samples."""
        self.odometry_latency_ms.append((time.time_ns() - self.imu_sub.received_ns) * 1e-6)
        self._latencies_recorded += 1
        if self._latencies_recorded % 200 == 1:   # not len(): the deque stops growing at its maxlen
            p50, p95 = np.percentile(self.odometry_latency_ms, (50, 95))
            self.status.info["odometry_latency_ms"] = f"p50 {p50:.2f}, p95 {p95:.2f} (reception to publish)"

    def add_imu(self, msg: Imu) -> bool:
        """Buffer one sample; False when it was malformed, dropped (out of order) or held (far ahead)."""
        try:
            t_ns, gyro, acc = imu_to_sample(msg)
        except ValueError as exc:
            self.status.warn("malformed_imu", f"malformed Imu message dropped: {exc}")
            return False
        remark = self.buffer.add(t_ns, gyro, acc)
        if remark is not None:
            self.status.warn("imu_stream", remark)
        if self.buffer.latest_ns != t_ns:   # dropped (out of order), or held far ahead of the stream
            return False
        self.status.count("imu_in")
        return True

    def on_keyframe_event(self, msg: NavState) -> None:
        with self.lock:
            event = self.status.decode(msg_to_nav_state, msg, "malformed_event", "keyframe event")
            if event is None:
                return
            self.status.count("keyframe_events")
            prev = self.last_keyframe
            if prev is not None and event.t_ns <= prev.t_ns:
                self.status.warn("event_order", f"keyframe {event.keyframe_id} at {event.t_ns} ns is not after "
                                                f"keyframe {prev.keyframe_id} at {prev.t_ns} ns: ignored")
                return
            self.last_keyframe = event
            if prev is not None:
                self.pending.append((prev, event, time.monotonic()))
                self.serve_pending()

    def on_state(self, msg: NavState) -> None:
        with self.lock:
            s = self.status.decode(msg_to_nav_state, msg, "malformed_state", "state")
            if s is None:
                return
            self.status.count("states_in")
            self.state_initialized = s.inertial_initialized
            f64 = lambda x: np.array(x, dtype=np.float64)  # noqa: E731
            self.state = ImuState(s.t_ns, f64(s.T_wb[:3, :3]), f64(s.T_wb[:3, 3]), f64(s.velocity),
                                  f64(s.bias_gyro), f64(s.bias_acc))
            latest = self.buffer.latest_ns
            if latest is not None and latest > s.t_ns:  # catch up silently: odometry stamps never go back
                self.publish_odometry(latest, publish=False)

    # ------------------------------------------------------------------ preintegration
    def serve_pending(self) -> None:
        while self.pending and self.buffer.covers(self.pending[0][1].t_ns):
            start, end, _ = self.pending.popleft()
            samples = self.buffer.samples(start.t_ns, end.t_ns)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    pre = preintegrate(samples, start.t_ns, end.t_ns, self.noise, end.bias_gyro, end.bias_acc,
                                       self.p["integration_scheme"])
                except ValueError as exc:
                    self.status.warn("preintegration", f"cannot preintegrate keyframes {start.keyframe_id} -> "
                                                       f"{end.keyframe_id}: {exc}")
                    continue
            for w in caught:
                self.status.warn("imu_stream", str(w.message))
            n_inside = int(np.count_nonzero((samples.t_ns > start.t_ns) & (samples.t_ns < end.t_ns)))
            self.pub_pre.publish(preintegration_to_msg(self.types, to_message_data(
                pre, start.keyframe_id, end.keyframe_id, n_inside, self.p["base_frame"])))
            self.status.count("preintegrations_out")

    def expire_events(self) -> None:
        with self.lock:
            now = time.monotonic()
            while self.pending and now - self.pending[0][2] > self.p["event_timeout_s"]:
                start, end, _ = self.pending.popleft()
                self.status.warn("imu_missing", f"no IMU data up to keyframe {end.keyframe_id} ({end.t_ns} ns) "
                                                f"after {self.p['event_timeout_s']} s: window {start.keyframe_id} "
                                                f"-> {end.keyframe_id} not preintegrated")
            if self.buffer.latest_ns is None and now - self._started > self.p["no_imu_error_s"]:
                self.status.set_error("no_imu", f"no IMU messages received on {self.p['imu_topic']}")
            else:
                self.status.clear_error("no_imu")

    # ------------------------------------------------------------------ odometry
    def publish_odometry(self, t_ns: int, publish: bool = True) -> bool:
        """Propagate the state to ``t_ns`` through the buffered IMU and publish odometry at every sample (NumPy
        state and unchecked batch messages: this runs for every IMU sample); True when messages went out."""
        state = self.state
        if state is None or t_ns <= state.t_ns:
            return False
        if not (self.state_initialized or self.p["odometry_before_init"]):
            return False
        samples = self.buffer.samples(state.t_ns, t_ns)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # stream defects were reported on arrival
            try:
                path = propagate_path(state, samples, t_ns, self.gravity, self.p["integration_scheme"],
                                      rate_hz=self.p["rate_hz"])
            except ValueError as exc:
                self.status.warn("propagation", f"cannot propagate the state from {state.t_ns} ns: {exc}")
                return False
        if publish:
            T = np.tile(np.eye(4), (len(path.t_ns) - 1, 1, 1))
            T[:, :3, :3], T[:, :3, 3] = path.R[1:], path.p[1:]
            gyro = samples.gyro[-1] - state.bias_gyro
            for msg in odometry_messages(self.types, path.t_ns[1:], T, self.p["world_frame"], self.p["base_frame"],
                                         velocity_world=path.v[1:], angular_velocity_body=gyro):
                self.pub_odom.publish(msg)
            self.status.count("odometry_out", len(T))
        self.state = ImuState(int(path.t_ns[-1]), path.R[-1], path.p[-1], path.v[-1], state.bias_gyro,
                              state.bias_acc)
        return publish


def to_message_data(pre: Preintegrated, from_id: int, to_id: int, num_samples: int, frame_id: str
                    ) -> PreintegrationData:
    """The message form of a core :class:`Preintegrated` (the (phi, v, p) 9x9 block of its covariance)."""
    n = lambda x: x.detach().cpu().numpy()  # noqa: E731
    return PreintegrationData(
        from_id=from_id, to_id=to_id, start_ns=int(pre.t0_ns), end_ns=int(pre.t1_ns), num_samples=num_samples,
        delta_R=n(pre.delta_R), delta_v=n(pre.delta_v), delta_p=n(pre.delta_p), covariance=n(pre.cov)[:9, :9],
        jacobians={"d_rotation_d_gyro_bias": n(pre.J_R_bg), "d_velocity_d_gyro_bias": n(pre.J_v_bg),
                   "d_velocity_d_acc_bias": n(pre.J_v_ba), "d_position_d_gyro_bias": n(pre.J_p_bg),
                   "d_position_d_acc_bias": n(pre.J_p_ba)},
        bias_gyro=n(pre.bias_gyro), bias_acc=n(pre.bias_acc), frame_id=frame_id,
    )


def main(args: list[str] | None = None) -> int:
    return run_nodes([ImuPreintegrationNode], args)


if __name__ == "__main__":
    sys.exit(main())
