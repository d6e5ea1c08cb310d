"""A worker child's signals: a SIGTERM sent to the parent's process group while the child still starts (imports
its modules, not yet in a group of its own) does not end it; once started, a SIGTERM to the child itself does.
The sender's queue is bounded: the caller waits for a lagging child, reading its answers meanwhile, and not for one
that ended. A deferred child gets what was posted before its start, in order."""
import os
import signal
import threading
import time

from vigs_core.child_process import ChildChannel, enter_child, messages, send


def _slow_start(conn, delay_s: float) -> None:
    """A worker whose start takes ``delay_s`` (as importing torch does) before :func:`enter_child`; then it answers
    every message with its process group."""
    time.sleep(delay_s)
    enter_child("vigs-test")
    for msg in messages(conn):
        send(conn, ("group", os.getpgid(0), msg))


def _sigblk(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return int(next(line for line in f if line.startswith("SigBlk:")).split()[1], 16)


def test_a_sigterm_before_the_child_left_the_group_is_discarded_and_one_after_ends_it():
    channel = ChildChannel(_slow_start, (1.5,), "vigs-test")
    try:
        pid = channel.process.pid
        time.sleep(0.5)                                   # still starting: in our group, SIGTERM blocked
        assert os.getpgid(pid) == os.getpgid(0)
        assert _sigblk(pid) & (1 << (signal.SIGTERM - 1))
        os.kill(pid, signal.SIGTERM)                      # as a SIGTERM to the whole group would reach it
        channel.post(("ping",))
        kind, group, msg = channel.receive()
        assert (kind, msg) == ("group", ("ping",)) and group == pid != os.getpgid(0)
        assert channel.process.is_alive() and not _sigblk(pid) & (1 << (signal.SIGTERM - 1))
        os.kill(pid, signal.SIGTERM)                      # now addressed to the child: it ends
        channel.process.join(timeout=10)
        assert channel.process.exitcode == -signal.SIGTERM
    finally:
        channel.close(timeout_s=5)


def _slow_reader(conn, delay_s: float) -> None:
    """Reads each message ``delay_s`` after the last (a child that lags) and answers ``("end",)`` with the
    sequence numbers it got."""
    enter_child("vigs-test")
    got = []
    for msg in messages(conn):
        if msg[0] == "end":
            send(conn, ("got", got))
            return
        time.sleep(delay_s)
        got.append(msg[1])


def _echo(conn) -> None:
    """Answers every message unasked with 200 KB, more than a pipe's buffer holds."""
    enter_child("vigs-test")
    for msg in messages(conn):
        send(conn, ("echo", msg[1], bytes(200_000)))


def test_post_waits_while_the_queue_of_a_lagging_child_is_over_its_bound_and_loses_nothing():
    limit = 250_000
    channel = ChildChannel(_slow_reader, (0.02,), "vigs-test", max_queued_bytes=limit)
    try:
        peak = 0
        for i in range(25):
            channel.post(("data", i, bytes(100_000)))
            peak = max(peak, channel.queued_bytes)
        assert peak <= limit and channel.waited_s > 0.1
        channel.post(("end",))
        assert channel.receive() == ("got", list(range(25)))
    finally:
        channel.close(timeout_s=5)


def test_a_caller_waiting_for_room_reads_what_the_child_sends_so_neither_waits_on_a_full_pipe():
    answers = []
    channel = ChildChannel(_echo, (), "vigs-test", max_queued_bytes=150_000,
                           while_waiting=lambda: answers.extend(
                               channel.receive()[1] for _ in iter(lambda: channel.conn.poll(0), False)))
    try:
        poster = threading.Thread(target=lambda: [channel.post(("data", i, bytes(100_000))) for i in range(30)],
                                  daemon=True)
        poster.start()
        poster.join(timeout=60)
        assert not poster.is_alive(), "caller and child deadlocked"
        while len(answers) < 30:
            answers.append(channel.receive()[1])
        assert answers == list(range(30))
    finally:
        channel.process.terminate()
        channel.close(timeout_s=5)


def test_post_does_not_wait_for_a_child_that_ended():
    channel = ChildChannel(_slow_reader, (0.0,), "vigs-test", max_queued_bytes=1000)
    try:
        channel.process.terminate()
        channel.process.join(timeout=10)
        t0 = time.perf_counter()
        for i in range(5):
            channel.post(("data", i, bytes(100_000)))
        assert time.perf_counter() - t0 < 5
    finally:
        channel.close(timeout_s=5)


def test_a_deferred_child_gets_the_earlier_messages_first_and_one_never_started_leaves_no_process():
    channel = ChildChannel(_slow_reader, (0.0,), "vigs-test", start=False)
    try:
        for i in range(3):
            channel.post(("data", i, bytes(1000)))
        assert not channel.started and channel.process.pid is None
        channel.start()
        channel.post(("data", 3, bytes(1000)))
        channel.post(("end",))
        assert channel.receive() == ("got", [0, 1, 2, 3])
    finally:
        channel.close(timeout_s=5)
    idle = ChildChannel(_slow_reader, (0.0,), "vigs-test", start=False)
    idle.post(("data", 0, bytes(1000)))
    idle.close()
    assert idle.process.pid is None and idle.conn.closed
    # a deferred start's backlog does not make the caller wait; what is queued beyond it does, down to the bound
    backlog = ChildChannel(_slow_reader, (0.05,), "vigs-test", max_queued_bytes=250_000, start=False)
    try:
        for i in range(6):
            backlog.post(("data", i, bytes(100_000)))
        assert not backlog.started and backlog.queued_bytes > 600_000 and backlog.waited_s == 0
        backlog.start()
        for i in range(6, 10):   # beyond the backlog not yet written, the usual bound
            backlog.post(("data", i, bytes(100_000)))
            assert backlog.queued_bytes <= 250_000 + backlog._backlog
        assert backlog.waited_s > 0 and backlog._backlog < 600_000
        backlog.post(("end",))
        assert backlog.receive() == ("got", list(range(10)))
    finally:
        backlog.close(timeout_s=5)
