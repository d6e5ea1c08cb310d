"""A worker child's signals: a SIGTERM sent to the parent's process group while the child still starts (imports
its modules, not yet in a group of its own) does not end it; once started, a SIGTERM to the child itself does."""
import os
import signal
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
