"""vigs_ros.runtime's threaded subscription: a high-rate topic taken by a thread of its own, not the executor."""
from __future__ import annotations

import threading
import time

from ros_helpers import ros_context, spin_until  # noqa: F401  (ros_context is a fixture)

from msg_adapters.imu import imu_to_sample, sample_to_imu
from msg_adapters.types import RclpyTypes
from vigs_ros.qos import reliable_qos
from vigs_ros.runtime import VigsNode

N = 60


def publish_imu(node, topic: str, n: int) -> None:
    from sensor_msgs.msg import Imu

    pub = node.create_publisher(Imu, topic, reliable_qos(n))
    deadline = time.monotonic() + 10
    while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
        time.sleep(0.02)
    types = RclpyTypes()
    for k in range(n):
        pub.publish(sample_to_imu(types, 1_000_000_000 + 5_000_000 * k, [0.0, 0.0, 0.0], [0.0, 0.0, 9.81]))


def test_threaded_subscription_takes_every_message_once_on_its_own_thread(ros_context):
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Imu

    node = VigsNode("threaded_sub_test", context=ros_context)
    got, threads = [], set()

    def on_imu(msgs):
        threads.add(threading.current_thread().name)
        got.extend(imu_to_sample(m)[0] for m in msgs)

    node.create_threaded_subscription(Imu, "/imu_threaded", on_imu, reliable_qos(N))
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(node)   # spun below: it must not take the threaded subscription's messages
    publish_imu(node, "/imu_threaded", N)
    assert spin_until(executor, lambda: len(got) >= N)
    executor.spin_once(timeout_sec=0.2)
    assert got == [1_000_000_000 + 5_000_000 * k for k in range(N)]   # all, in order, none twice
    assert threads == {"sub/imu_threaded"}
    node.destroy_node()
    assert not any(t.name == "sub/imu_threaded" and t.is_alive() for t in threading.enumerate())


def test_a_failing_threaded_callback_shuts_the_context_down_and_is_reported(ros_context):
    from sensor_msgs.msg import Imu

    node = VigsNode("threaded_sub_fail", context=ros_context)

    def on_imu(msgs):
        raise RuntimeError("boom")

    node.create_threaded_subscription(Imu, "/imu_fail", on_imu, reliable_qos(10))
    publish_imu(node, "/imu_fail", 3)
    deadline = time.monotonic() + 10
    while ros_context.ok() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not ros_context.ok()
    assert node.failed_threads == ["/imu_fail"]


def test_an_error_during_a_signal_shutdown_is_told_from_a_real_one():
    """rclpy's signal handler shuts the context down from a thread of its own: an error raised meanwhile (while
    ``ok()`` still holds) is part of the shutdown; one with the context still up after the wait is real."""
    import threading

    import rclpy
    from rclpy.context import Context

    from vigs_ros.runtime import shutting_down

    for stays_up in (False, True):
        context = Context()
        rclpy.init(context=context, domain_id=0)
        try:
            if not stays_up:
                threading.Timer(0.2, context.try_shutdown).start()
            assert shutting_down(context, wait_s=1.0) is not stays_up
        finally:
            context.try_shutdown()


IDLE_NODE = """
import sys
from rclpy.signals import uninstall_signal_handlers
from vigs_ros.runtime import VigsNode, run_nodes

class Idle(VigsNode):
    def __init__(self, **kwargs):
        super().__init__("idle_on_sim_time", **kwargs)
        self.create_timer(1.0, lambda: None)   # simulated time and no /clock: it never fires
        if sys.argv[1] == "lost":
            uninstall_signal_handlers()   # rclpy's shutdown and wake-up of the executor never come
        print("ready", flush=True)

    def close(self):
        print("closed", flush=True)

sys.exit(run_nodes([Idle], ["idle", "--ros-args", "-p", "use_sim_time:=true"]))
"""


def test_a_node_waiting_on_stopped_simulated_time_exits_on_a_signal_without_rclpy_waking_it():
    """After a replay /clock stops, so a node's timers never fire; rclpy's signal handler wakes the executor, but
    that wake-up was sometimes lost and the node waited for the launcher's SIGKILL. The executor's wait is bounded
    (runtime.SIGNAL_POLL_S): SIGINT and SIGTERM end the run and close the node even without rclpy's handlers."""
    import os
    import signal
    import subprocess
    import sys

    from ros_helpers import isolated_env

    env = isolated_env()
    for mode, sig in (("lost", signal.SIGINT), ("lost", signal.SIGTERM), ("rclpy", signal.SIGINT)):
        proc = subprocess.Popen([sys.executable, "-c", IDLE_NODE, mode], env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True)
        try:
            assert proc.stdout.readline().strip() == "ready"
            time.sleep(0.5)
            t0 = time.monotonic()
            os.kill(proc.pid, sig)
            out, _ = proc.communicate(timeout=10)
            took = time.monotonic() - t0
        finally:
            proc.kill()
        assert proc.returncode == 0, (mode, sig, out)
        assert "closed" in out, (mode, sig, out)
        assert took < 3.0, (mode, sig, took)


SLOW_CLOSE_NODE = """
import sys
import time
from vigs_ros.runtime import VigsNode, run_nodes

class SlowClose(VigsNode):
    def __init__(self, **kwargs):
        super().__init__("slow_close", **kwargs)
        self.timer = self.create_timer(0.05, self.ready)   # spinning

    def ready(self):
        self.timer.cancel()
        print("ready", flush=True)

    def close(self):
        # short waits, as the mapper's drain checks between steps: a signal delivered to another thread does not
        # interrupt a long wait of the main thread, where Python runs the handler that sets ``hurry``
        print("closing", flush=True)
        end = time.monotonic() + 10.0
        while not self.hurry.wait(0.05) and time.monotonic() < end:
            pass
        print("hurried" if self.hurry.is_set() else "not hurried", flush=True)

sys.exit(run_nodes([SlowClose], ["slow_close"]))
"""


def test_a_sigterm_during_close_hurries_the_node():
    """The launcher's escalation: SIGINT stops the node, a SIGTERM while it is still closing (the mapper's drain)
    sets its ``hurry``, so it saves what it has instead of being killed."""
    import os
    import signal
    import subprocess
    import sys

    from ros_helpers import isolated_env

    proc = subprocess.Popen([sys.executable, "-c", SLOW_CLOSE_NODE], env=isolated_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        os.kill(proc.pid, signal.SIGINT)
        assert proc.stdout.readline().strip() == "closing"
        t0 = time.monotonic()
        os.kill(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=15)
        took = time.monotonic() - t0
    finally:
        proc.kill()
    assert out.split() == ["hurried"] and proc.returncode == 0, out
    assert took < 3.0
