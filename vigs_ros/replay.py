"""Bag replay: publishes the recorded messages of a ROS 2 (MCAP or sqlite3) or ROS 1 bag, with ``/clock``.

* ROS 2 bags: the recorded CDR bytes are published as they are (serialized publishing: no decode/encode).
* ROS 1 bags: each message is decoded (rosbags) and re-encoded as its ROS 2 type (fields ROS 2 dropped, e.g.
  ``Header.seq``, are left out), then published.
* Pacing: ``rate`` x recorded time (1.0 = real time), or ``fast``: as fast as the graph consumes, i.e. after
  each message on a *gate* topic (default: the bag's first image topic) wait for one acknowledgement on
  ``ack_topic`` (the frontend publishes a ``std_msgs/Header`` per consumed frame on ``/vigs/frame_done``), with
  a timeout so a missing consumer cannot stall replay forever. The other topics run ``fast_lookahead_s``
  ahead of the gated message before the wait, so a consumer that needs the IMU up to the image's stamp
  (the frontend synchronises frames with the IMU) gets it.
* ``/clock`` (rosgraph_msgs/Clock) carries the recorded time, so nodes with ``use_sim_time:=true`` run on bag
  time: before the first message, then at most ``clock_hz`` times a second of recorded time (40, as ``ros2 bag
  play --clock``). A clock message per recorded message (about 220 a second with a 200 Hz IMU) cost every node
  process an executor wake-up each: on 2 cores, CPU the graph needs for tracking.
* Remapping: ``{"/cam0/image_raw": "/image"}`` publishes a recorded topic under another name.

Messages are published with reliable keep-last QoS (matches best-effort and reliable subscribers).
"""
from __future__ import annotations

import dataclasses
import importlib
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from vigs_ros.qos import replay_qos

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")


@dataclass
class ReplayConfig:
    """Args:
        rate: playback speed factor relative to recorded time (ignored when ``fast``).
        fast: pace on acknowledgements instead of time (see module docstring).
        remap: ``{recorded topic: published topic}``.
        topics: replay only these recorded topics (default: all).
        clock: publish ``/clock``.
        clock_hz: most ``/clock`` messages per second of recorded time.
        gate_topic: recorded topic whose messages wait for an acknowledgement in ``fast`` mode (default: the
            first image topic).
        ack_topic: topic of the acknowledgements (``std_msgs/Header``).
        ack_timeout_s: longest wait for one acknowledgement (s); replay then goes on (counted as a timeout).
        fast_lookahead_s: in ``fast`` mode, recorded time (s) of non-gated messages published after a gated
            one before waiting for its acknowledgement.
        wait_for: published topics that must have a subscriber before replay starts.
        wait_timeout_s: longest wait for those subscribers (s).
        settle_s: once they are matched, wait this long before the first message (s): Fast DDS reports a
            match before a fresh best-effort reader's transport receives, and the first messages were lost
            without it (measured: the first image and camera info of a replay, about one run in two).
        start_offset_s: skip this much of the bag's beginning (s).
        duration_s: replay at most this much recorded time (s; <= 0: all).
    """

    rate: float = 1.0
    fast: bool = False
    remap: dict[str, str] = field(default_factory=dict)
    topics: list[str] | None = None
    clock: bool = True
    clock_hz: float = 40.0
    gate_topic: str | None = None
    ack_topic: str = "/vigs/frame_done"
    ack_timeout_s: float = 5.0
    fast_lookahead_s: float = 0.1
    wait_for: list[str] = field(default_factory=list)
    wait_timeout_s: float = 10.0
    settle_s: float = 1.0
    start_offset_s: float = 0.0
    duration_s: float = 0.0


@dataclass
class ReplayStats:
    """What a replay did: messages published per (published) topic, acknowledgement timeouts, wall time (s)
    and recorded time span (s)."""

    published: dict[str, int] = field(default_factory=dict)
    skipped_topics: dict[str, str] = field(default_factory=dict)
    ack_timeouts: int = 0
    wall_s: float = 0.0
    bag_s: float = 0.0


def parse_remaps(items: list[str]) -> dict[str, str]:
    """``["A:=B", ...]`` -> ``{"A": "B"}``; ValueError for anything else."""
    out = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src or not dst:
            raise ValueError(f"remap {item!r} must look like /recorded/topic:=/published/topic")
        out[src] = dst
    return out


def _message_class(typename: str):
    package, kind, name = typename.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def ros1_to_ros2(msg, typename: str, store):
    """Rebuild a decoded ROS 1 message as the ROS 2 type ``typename`` of typestore ``store`` (recursively;
    fields the ROS 2 type lacks are dropped, e.g. ``Header.seq``)."""
    cls = store.types[typename]
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "__msgtype__":
            continue
        value = getattr(msg, f.name)
        kwargs[f.name] = _convert_value(value, store)
    return cls(**kwargs)


def _convert_value(value, store):
    msgtype = getattr(value, "__msgtype__", None)
    if msgtype is not None:
        return ros1_to_ros2(value, msgtype, store)
    if isinstance(value, list):
        return [_convert_value(v, store) for v in value]
    return value


class BagPlayer:
    """Publishes a bag into a ROS graph from an rclpy node it creates in ``context``."""

    def __init__(self, bag: str | Path, config: ReplayConfig | None = None, context=None,
                 node_name: str = "vigs_replay") -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        from vigs_core.io.rosbag import open_bag_reader

        self.config = config or ReplayConfig()
        if not self.config.fast and self.config.rate <= 0:
            raise ValueError(f"replay rate must be > 0, got {self.config.rate}")
        self.reader = open_bag_reader(bag)
        self.is_ros1 = not self.reader.is2
        if self.is_ros1:
            from rosbags.typesys import Stores, get_typestore

            self.ros2_store = get_typestore(Stores.ROS2_JAZZY)
        self.context = context or rclpy.get_default_context()
        self.node = Node(node_name, context=self.context)
        self.stats = ReplayStats()
        self.publishers = {}
        self.connections = []
        recorded = {c.topic for c in self.reader.connections}
        if self.config.topics:
            missing = set(self.config.topics) - recorded
            if missing:
                raise ValueError(f"topics {sorted(missing)} are not in the bag (it has {sorted(recorded)})")
        for conn in self.reader.connections:
            if self.config.topics and conn.topic not in self.config.topics:
                continue
            out_topic = self.config.remap.get(conn.topic, conn.topic)
            if out_topic not in self.publishers:
                try:
                    cls = _message_class(conn.msgtype)
                except (ImportError, AttributeError, ValueError) as exc:
                    self.stats.skipped_topics[conn.topic] = f"type {conn.msgtype} not importable in rclpy: {exc}"
                    continue
                self.publishers[out_topic] = self.node.create_publisher(cls, out_topic, replay_qos())
            self.connections.append(conn)
        if not self.connections:
            raise ValueError(f"nothing to replay from {bag}: topics {sorted(recorded)}, skipped "
                             f"{self.stats.skipped_topics}")
        self.gate_topic = self.config.gate_topic
        if self.gate_topic is None:
            images = [c.topic for c in self.connections if c.msgtype in IMAGE_TYPES]
            self.gate_topic = images[0] if images else None
        self.clock_pub = None
        if self.config.clock:
            from rosgraph_msgs.msg import Clock

            self.clock_pub = self.node.create_publisher(Clock, "/clock", replay_qos(10))
        self._acks = 0
        self._ack_cond = threading.Condition()
        self._executor = None
        if self.config.fast:
            from std_msgs.msg import Header

            self._ack_sub = self.node.create_subscription(Header, self.config.ack_topic, self._on_ack, replay_qos())
            self._executor = SingleThreadedExecutor(context=self.context)
            self._executor.add_node(self.node)
            self._spin_thread = threading.Thread(target=self._spin, daemon=True)
            self._spin_thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self._executor.spin()
        except (ExternalShutdownException, KeyboardInterrupt):
            pass

    def _on_ack(self, msg) -> None:
        with self._ack_cond:
            self._acks += 1
            self._ack_cond.notify_all()

    def wait_for_subscribers(self, stop: threading.Event | None = None) -> list[str]:
        """Wait until every ``wait_for`` topic has a subscriber and, in ``fast`` mode with ``wait_for`` topics,
        the acknowledgement topic a publisher (so the first acknowledgement is not lost to discovery);
        returns the topics still missing one (``stop`` ends the wait early)."""
        stop = stop or threading.Event()
        deadline = time.monotonic() + self.config.wait_timeout_s
        missing = list(self.config.wait_for)
        if self.config.fast and missing:
            missing.append(self.config.ack_topic)

        def has_peer(topic: str) -> bool:
            # matched endpoints (not just discovered ones): a best-effort reader that is discovered but not
            # yet matched would lose the first messages
            if topic == self.config.ack_topic and self.config.fast:
                return self._ack_sub.get_publisher_count() > 0
            if topic in self.publishers:
                return self.publishers[topic].get_subscription_count() > 0
            return self.node.count_subscribers(topic) > 0

        while missing and time.monotonic() < deadline and self.context.ok() and not stop.is_set():
            missing = [t for t in missing if not has_peer(t)]
            if missing:
                time.sleep(0.05)
        if self.config.wait_for:
            time.sleep(self.config.settle_s)
        return missing

    def play(self, stop: threading.Event | None = None) -> ReplayStats:
        """Publish the bag (blocking); ``stop`` ends it early. Returns the statistics."""
        from rosgraph_msgs.msg import Clock

        stop = stop or threading.Event()
        from msg_adapters.common import ns_to_stamp
        from msg_adapters.types import RclpyTypes

        cfg = self.config
        missing = self.wait_for_subscribers(stop)
        if missing:
            self.node.get_logger().warning(f"no subscriber on {missing} after {cfg.wait_timeout_s} s: replaying anyway")
        t_first = self.reader.start_time + int(cfg.start_offset_s * 1e9)
        t_last = self.reader.end_time if cfg.duration_s <= 0 else t_first + int(cfg.duration_s * 1e9)
        wall0 = time.monotonic()
        types = RclpyTypes()
        last_t = last_clock = None
        clock_step_ns = int(1e9 / cfg.clock_hz)
        lookahead_ns = int(cfg.fast_lookahead_s * 1e9)
        waiting: tuple[int, int] | None = None  # (stamp of the gated message, acks counted before it)
        for conn, t_ns, raw in self.reader.messages(connections=self.connections, start=t_first, stop=t_last + 1):
            if stop.is_set() or not self.context.ok():
                break
            gated = cfg.fast and conn.topic == self.gate_topic
            if waiting is not None and (gated or t_ns > waiting[0] + lookahead_ns):
                self._wait_ack(waiting[1], stop)
                waiting = None
            if not cfg.fast:
                due = wall0 + (t_ns - t_first) * 1e-9 / cfg.rate
                while (left := due - time.monotonic()) > 0 and not stop.is_set():
                    time.sleep(min(left, 0.1))
            if self.clock_pub is not None and (last_clock is None or t_ns >= last_clock + clock_step_ns):
                if not self._publish(self.clock_pub, Clock(clock=ns_to_stamp(types, t_ns))):
                    break
                last_clock = t_ns
            last_t = t_ns
            if self.is_ros1:
                msg = ros1_to_ros2(self.reader.deserialize(raw, conn.msgtype), conn.msgtype, self.ros2_store)
                data = bytes(self.ros2_store.serialize_cdr(msg, conn.msgtype))
            else:
                data = bytes(raw)
            out_topic = cfg.remap.get(conn.topic, conn.topic)
            if gated:
                waiting = (t_ns, self._acks)
            if not self._publish(self.publishers[out_topic], data):
                break
            self.stats.published[out_topic] = self.stats.published.get(out_topic, 0) + 1
        if waiting is not None:
            self._wait_ack(waiting[1], stop)
        self.stats.wall_s = time.monotonic() - wall0
        self.stats.bag_s = ((last_t - t_first) * 1e-9) if last_t is not None else 0.0
        return self.stats

    def _publish(self, publisher, msg) -> bool:
        """Publish; False when a signal shut the context down meanwhile (rclpy then raises RCLError: the replay
        ends as interrupted, without a traceback), otherwise errors are raised."""
        try:
            publisher.publish(msg)
            return True
        except Exception:   # noqa: BLE001 - only a shut-down context is expected here
            if self.context.ok():
                raise
            return False

    def _wait_ack(self, acks_before: int, stop: threading.Event) -> None:
        """Wait for an acknowledgement after ``acks_before``, in short slices so ``stop`` ends the wait."""
        deadline = time.monotonic() + self.config.ack_timeout_s
        with self._ack_cond:
            while self._acks <= acks_before and self.context.ok() and not stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    self.stats.ack_timeouts += 1
                    return
                self._ack_cond.wait(timeout=min(left, 0.1))

    def close(self) -> None:
        if self._executor is not None:  # stop the spin thread before its node goes away
            self._executor.shutdown(timeout_sec=5.0)
            self._spin_thread.join(timeout=5.0)
        self.node.destroy_node()
        self.reader.close()


def run_replay(bag: str | Path, config: ReplayConfig, args: list[str] | None = None) -> int:
    """Process entry: init rclpy, play the bag, print a summary; exit code.

    SIGINT / SIGTERM set a stop flag that the replay loop checks between messages, and the main thread then
    closes the node and the context in order. rclpy's own handlers are not installed: they shut the context
    down from a thread of their own, which could finalise a publisher while the loop was inside ``publish``
    (a segmentation fault, seen once in about 30 interrupted launches)."""
    import rclpy
    from rclpy.context import Context
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    rclpy.init(args=args or [], context=context, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
    player = None
    try:
        player = BagPlayer(bag, config, context)
        for topic, why in player.stats.skipped_topics.items():
            print(f"[replay] skipping {topic}: {why}")
        stats = player.play(stop)
    except ValueError as exc:
        print(f"[replay] error: {exc}")
        return 2
    finally:
        if player is not None:
            player.close()
        context.try_shutdown()
        for s, handler in previous.items():
            signal.signal(s, handler)
    if stop.is_set():
        print("[replay] interrupted")
    total = sum(stats.published.values())
    speed = stats.bag_s / stats.wall_s if stats.wall_s > 0 else float("nan")
    print(f"[replay] {total} messages on {len(stats.published)} topics, {stats.bag_s:.2f} s of bag in "
          f"{stats.wall_s:.2f} s (x{speed:.2f})" + (f", {stats.ack_timeouts} ack timeouts" if config.fast else ""))
    for topic, n in sorted(stats.published.items()):
        print(f"[replay]   {topic}: {n}")
    return 0


