"""Running nodes: one node per process (each node's ``main``) or several in one process (composed).

``run_nodes`` initialises rclpy with the process's ``--ros-args`` (so ``--params-file``, remapping and
``-p use_sim_time:=true`` work as in any ROS 2 node), changes the process's niceness by the node's
``process_nice`` when it runs one node alone (the mapper and the loop detector yield to real-time tracking; a
composed process keeps the frontend's priority), spins the nodes in one executor (multi-threaded when
there are several), and on SIGINT/SIGTERM (rclpy's signal handlers shut the context down) closes every node
(``close()``: flush what must be saved) before destroying it. Exit code: 0 after a clean shutdown, 1 when a
node raised.
"""
from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence

from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node

from vigs_core.gc_freeze import freeze_startup_objects
from vigs_core.heap import single_arena
from vigs_ros.params import ParamSpec


class VigsNode(Node):
    """Base of the VIGS nodes: ``close()`` is called once at shutdown, before ``destroy_node``.

    Publishers, and subscriptions that cannot be incompatible (best-effort and volatile: they match any writer),
    get no QoS event handlers unless given some: rclpy adds default ones (incompatible QoS and type warnings) to
    every wait-set round of the executor, a cost paid for every message a node takes (docs/benchmarks.md, live
    operation, ninth session). The reliable and transient-local subscriptions keep them, so a QoS mismatch is still
    reported on the subscriber's side."""

    def create_publisher(self, *args, **kwargs):
        from rclpy.event_handler import PublisherEventCallbacks

        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def create_subscription(self, msg_type, topic, callback, qos_profile, **kwargs):
        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        if (isinstance(qos_profile, QoSProfile) and qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT
                and qos_profile.durability == DurabilityPolicy.VOLATILE):
            kwargs.setdefault("event_callbacks", SubscriptionEventCallbacks(use_default_callbacks=False))
        return super().create_subscription(msg_type, topic, callback, qos_profile, **kwargs)

    def __init__(self, *args, **kwargs) -> None:
        self._threaded_subscriptions: list[ThreadedSubscription] = []
        # set by run_nodes on a SIGTERM after the signal that stopped the node (a launcher's escalation when the
        # node is slow to exit): ``close()`` should save what it has now
        self.hurry = threading.Event()
        super().__init__(*args, **kwargs)

    def close(self) -> None:
        """Release resources and flush outputs (override); the context may already be shut down."""

    def create_threaded_subscription(self, msg_type, topic: str, callback: Callable[[list], None],
                                     qos_profile) -> "ThreadedSubscription":
        """A subscription served by a thread of its own (:class:`ThreadedSubscription`), for a high-rate topic;
        ``callback`` gets every message queued, as a list, on that thread. Stopped by ``destroy_node``."""
        reader = ThreadedSubscription(self, msg_type, topic, callback, qos_profile)
        self._threaded_subscriptions.append(reader)
        return reader

    @property
    def failed_threads(self) -> list[str]:
        """Threaded subscriptions whose callback raised (the process then shuts down and exits non-zero)."""
        return [r.topic for r in self._threaded_subscriptions if r.error is not None]

    def destroy_node(self) -> None:
        for reader in self._threaded_subscriptions:
            reader.stop()
        super().destroy_node()


class _ServedElsewhere(CallbackGroup):
    """A callback group no executor serves: its entities are waited on by a thread of their own."""

    def can_execute(self, entity) -> bool:
        return False

    def beginning_execution(self, entity) -> bool:
        return False

    def ending_execution(self, entity) -> None:
        pass


class ThreadedSubscription:
    """A subscription waited on and taken by a dedicated thread, outside the executor.

    rclpy's executor rebuilds its wait set from every entity of the node (parameter services, timers, event
    handlers) and takes one message per round, at several times the CPU per message of one subscription in a
    wait set of its own (docs/benchmarks.md, live operation, tenth session); the IMU, at 200 Hz the graph's most
    frequent message, is taken by two processes. The callback runs on this thread, so it must
    only share state with the node's other callbacks under a lock; ``received_ns`` is the DDS reception time
    (system clock, ns) of the newest message of the list it is called with, for latency measured inside the
    node. An exception in it is printed and shuts the context down (the node's process exits non-zero)."""

    def __init__(self, node: Node, msg_type, topic: str, callback: Callable[[list], None], qos_profile,
                 poll_s: float = 0.1, raw: bool = False, with_info: bool = False) -> None:
        """``raw``: the callback gets serialized messages (bytes); ``with_info``: it gets ``(message, info)``
        pairs (info: rclpy's message info, with the reception stamp)."""
        self.topic = topic
        self._with_info = with_info
        self.error: BaseException | None = None
        self.received_ns = 0
        self._callback = callback
        self._context = node.context
        self._poll_ns = int(poll_s * 1e9)
        self._stopping = threading.Event()
        self.subscription = node.create_subscription(msg_type, topic, lambda msg: None, qos_profile,
                                                     callback_group=_ServedElsewhere(), raw=raw)
        self._thread = threading.Thread(target=self._run, name=f"sub{topic}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

        try:
            wait_set = _rclpy.WaitSet(1, 0, 0, 0, 0, 0, self._context.handle)
            while not self._stopping.is_set() and self._context.ok():
                with self.subscription.handle, self._context.handle:
                    wait_set.clear_entities()
                    wait_set.add_subscription(self.subscription.handle)
                    wait_set.wait(self._poll_ns)
                taken = list(take_queued(self.subscription))
                if taken and not self._stopping.is_set():
                    self.received_ns = max(int(info["received_timestamp"]) for _, info in taken)
                    self._callback(taken if self._with_info else [msg for msg, _ in taken])
        except InvalidHandle:   # the node or the context was destroyed under us: shutting down
            pass
        except Exception as exc:  # noqa: BLE001 - reported, then the process shuts down
            if not shutting_down(self._context):
                traceback.print_exc()
                self.error = exc
                self._context.try_shutdown()

    def stop(self) -> None:
        """Stop the thread after the callback it is running, if any."""
        self._stopping.set()
        if self._thread is not threading.current_thread():
            self._thread.join(5.0)


def shutting_down(context, wait_s: float = 2.0) -> bool:
    """Whether ``context`` is being shut down, waiting up to ``wait_s`` for it: rclpy's signal handler shuts the
    contexts down from a thread of its own, so a take that fails because of the signal (RCLError, or a
    RuntimeError from the message's conversion) can come while ``context.ok()`` still holds for a moment. An
    error with the context still up after ``wait_s`` is a real one."""
    deadline = time.monotonic() + wait_s
    while context.ok() and time.monotonic() < deadline:
        time.sleep(0.02)
    return not context.ok()


def take_queued(subscription) -> Iterator:
    """The ``(message, info)`` pairs already waiting for ``subscription``, taken now (a :class:`ThreadedSubscription`
    hands the messages to its callback in one list, so a node that fell behind catches up in one call)."""
    while True:
        try:
            with subscription.handle:
                taken = subscription.handle.take_message(subscription.msg_type, subscription.raw)
        except InvalidHandle:   # destroyed at shutdown
            return
        if taken is None:
            return
        yield taken


def process_nice(default: int) -> ParamSpec:
    """The ``process_nice`` parameter of a node that runs alone in its process (not composed)."""
    return ParamSpec("process_nice", int(default), "niceness increment of the node's process when it runs alone "
                                                   "(not composed); positive yields the CPU to tracking, negative "
                                                   "(needs root or CAP_SYS_NICE) takes it first")


SIGNAL_POLL_S = 0.25  # longest wait of the executor between checks for a stop signal (run_nodes)

_AUTOGROUP = "/proc/self/autogroup"


def renice(increment: int, threads: bool = True) -> bool:
    """Add ``increment`` to the niceness of every thread of this process (clamped to -20..19; not with ``threads``
    False: child processes would inherit it) and, when the process leads its own session, of its scheduling
    autogroup; False when the system refused (a negative increment without the privilege).

    Linux keeps a niceness per thread and ``os.nice`` changes only the caller's: a node's worker thread (the
    mapper's optimisation) and the DDS threads, started before, would keep the old priority. With autogroup
    scheduling (``/proc/sys/kernel/sched_autogroup_enabled``, the default of desktop kernels) the CPU is shared
    first between sessions, and a thread's niceness only weighs within its session: the launcher starts every
    node in a session of its own, so a node yields to tracking only through its autogroup's niceness."""
    done = True
    for tid in os.listdir("/proc/self/task") if threads else ():
        try:
            now = os.getpriority(os.PRIO_PROCESS, int(tid))
            os.setpriority(os.PRIO_PROCESS, int(tid), max(-20, min(19, now + int(increment))))
        except ProcessLookupError:   # a thread that ended meanwhile
            pass
        except PermissionError:
            done = False
    now = autogroup_nice()
    if os.getsid(0) == os.getpid() and now is not None:   # never renice a shell's session
        try:
            with open(_AUTOGROUP, "w") as f:
                f.write(str(max(-20, min(19, now + int(increment)))))
        except OSError:
            done = False
    return done


def autogroup_nice() -> int | None:
    """The niceness of this process's scheduling autogroup; None where there is none: a kernel without autogroup
    scheduling, or a process in a CPU cgroup of its own (a container, a systemd service), where the kernel shows
    the file empty and the cgroup, not the session, shares the CPU."""
    try:
        with open(_AUTOGROUP) as f:
            fields = f.read().split()          # "/autogroup-<id> nice <n>"
    except OSError:
        return None
    if len(fields) == 3 and fields[1] == "nice":
        try:
            return int(fields[2])
        except ValueError:
            return None
    return None


def run_nodes(factories: Sequence[Callable[..., Node]], args: list[str] | None = None,
              multithreaded: bool | None = None, num_threads: int | None = None) -> int:
    """Create the nodes from ``factories`` (each called with ``context=``), spin until shutdown, close them.

    Args:
        args: command-line arguments for rclpy (default ``sys.argv``).
        multithreaded: use a MultiThreadedExecutor (default: when there is more than one node).
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    context = Context()
    # rclpy's handlers shut the context down and wake the executor, then chain to the Python handlers installed
    # before them, which only set ``stop``: Python's default SIGINT handler would raise KeyboardInterrupt at any
    # point of the main thread, e.g. inside an executor's Task constructor (a half-made Task then prints
    # "Exception ignored in Future.__del__" when collected). The executor waits at most SIGNAL_POLL_S at a time:
    # rclpy's wake-up was sometimes lost (a node on simulated time whose /clock had stopped then waited for the
    # launcher's SIGKILL), and Python runs ``stop``'s handler only when the main thread is back from the wait.
    # A SIGTERM once stopped sets the nodes' ``hurry`` (their ``close()`` runs on this thread, so it is handled).
    stop = threading.Event()
    nodes: list[Node] = []

    def on_signal(signum: int, _frame) -> None:
        if signum == signal.SIGTERM and stop.is_set():
            for node in nodes:
                if isinstance(node, VigsNode):
                    node.hurry.set()
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)
    single_arena()   # before rclpy.init starts the middleware's threads and the executor its own
    rclpy.init(args=sys.argv if args is None else args, context=context,
               signal_handler_options=SignalHandlerOptions.ALL)
    code = 0
    try:
        for factory in factories:
            nodes.append(factory(context=context))
        alone = nodes[0] if len(nodes) == 1 else None
        nice = int(alone.get_parameter("process_nice").value) if alone and alone.has_parameter("process_nice") else 0
        if nice and not renice(nice):
            nodes[0].get_logger().warn(f"process_nice {nice}: not permitted (a negative niceness needs root or "
                                       f"CAP_SYS_NICE); the process keeps its priority")
        if multithreaded is None:
            multithreaded = len(nodes) > 1
        executor = (MultiThreadedExecutor(num_threads=num_threads, context=context) if multithreaded
                    else SingleThreadedExecutor(context=context))
        for node in nodes:
            executor.add_node(node)
        freeze_startup_objects()   # the modules and the nodes: full collections skip them
        while context.ok() and not stop.is_set():
            executor.spin_once(timeout_sec=SIGNAL_POLL_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:  # a node's callback or constructor failed: report it and exit non-zero
        if not (stop.is_set() or shutting_down(context)):
            traceback.print_exc()
            code = 1
        # else a signal shut the context down while the executor was taking a message (rclpy then raises
        # RCLError / RuntimeError from the wait set or the take): an ordinary shutdown
    finally:
        failed = [topic for node in nodes if isinstance(node, VigsNode) for topic in node.failed_threads]
        if failed:
            print(f"[{nodes[0].get_name()}] the callback of {failed} failed (above): shut down", file=sys.stderr)
            code = 1
        for node in nodes:
            try:
                if isinstance(node, VigsNode):
                    node.close()
            except Exception:
                traceback.print_exc()
                code = 1
            node.destroy_node()
        if context.ok():
            context.try_shutdown()
    return code
