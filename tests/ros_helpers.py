"""Shared pieces of the ROS tests: an isolated ROS domain per test process, a fresh rclpy Context per test,
and helpers to spin until a condition holds.

Isolation: ``ROS_DOMAIN_ID`` = 10 + pid % 91 (distinct for test runs of different processes on this
machine) and ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``; both are exported so subprocesses inherit them.
Import with ``from ros_helpers import ros_context, spin_until`` (pytest finds the imported fixture).
"""
from __future__ import annotations

import os
import time

import pytest

DOMAIN_ID = 10 + os.getpid() % 91


def isolated_env() -> dict[str, str]:
    """This process's environment with the test domain settings (for subprocesses too)."""
    os.environ["ROS_DOMAIN_ID"] = str(DOMAIN_ID)
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    os.environ.pop("ROS_LOCALHOST_ONLY", None)
    return dict(os.environ)


@pytest.fixture
def ros_context():
    """A fresh, initialised rclpy Context on the test domain; shut down after the test."""
    import rclpy
    from rclpy.context import Context

    isolated_env()
    context = Context()
    rclpy.init(context=context, domain_id=DOMAIN_ID)
    yield context
    context.try_shutdown()


def spin_until(executor, predicate, timeout_s: float = 10.0, step_s: float = 0.02) -> bool:
    """Spin ``executor`` until ``predicate()`` is true or ``timeout_s`` passes; returns ``predicate()``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        executor.spin_once(timeout_sec=step_s)
    return bool(predicate())
