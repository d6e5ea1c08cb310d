"""Node status on a diagnostics topic (``diagnostic_msgs/DiagnosticArray``), plus throttled log warnings.

Every node owns a :class:`StatusReporter`: counters (messages in/out, rejected inputs, ...) and the last
problem of each kind. It publishes one ``DiagnosticStatus`` named after the node every ``period_s`` on a
transient-local topic (a late ``ros2 topic echo`` or monitor sees the latest status). Level: ERROR while an
error is active, WARN if a warning was raised in the last period, else OK.
"""
from __future__ import annotations

import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from vigs_ros.qos import latched_qos


class StatusReporter:
    """Counters and problems of one node, published periodically and logged with throttling."""

    def __init__(self, node, topic: str, period_s: float = 1.0, log_every_s: float = 5.0) -> None:
        self.node = node
        self.counters: dict[str, int] = {}
        self.info: dict[str, str] = {}
        self._errors: dict[str, str] = {}
        self._warnings: dict[str, str] = {}
        self._last_log: dict[str, float] = {}
        self.log_every_s = log_every_s
        self._pub = node.create_publisher(DiagnosticArray, topic, latched_qos(1))
        self._timer = node.create_timer(period_s, self.publish) if period_s > 0 else None

    def count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    def warn(self, key: str, text: str) -> None:
        """Record a warning of kind ``key`` (counted as ``warn.<key>``), logged at most every ``log_every_s``."""
        self.count(f"warn.{key}")
        self._warnings[key] = text
        now = time.monotonic()
        if now - self._last_log.get(key, -1e9) >= self.log_every_s:
            self._last_log[key] = now
            n = self.counters[f"warn.{key}"]
            self.node.get_logger().warning(f"{text} [{key}: {n} so far]")

    def decode(self, convert, msg, key: str, what: str):
        """``convert(msg)``, or ``None`` after a warning of kind ``key`` ("``what`` rejected: ...") when the
        message is malformed (the adapters raise ``ValueError`` saying what was wrong)."""
        try:
            return convert(msg)
        except ValueError as exc:
            self.warn(key, f"{what} rejected: {exc}")
            return None

    def set_error(self, key: str, text: str) -> None:
        """An active error (e.g. a required input missing); stays until ``clear_error``."""
        if self._errors.get(key) != text:
            self.node.get_logger().error(text)
        self._errors[key] = text

    @property
    def errors(self) -> dict[str, str]:
        """The active errors by kind."""
        return dict(self._errors)

    def clear_error(self, key: str) -> None:
        self._errors.pop(key, None)

    @property
    def level(self) -> bytes:
        if self._errors:
            return DiagnosticStatus.ERROR
        return DiagnosticStatus.WARN if self._warnings else DiagnosticStatus.OK

    def status(self) -> DiagnosticStatus:
        if self._errors:
            message = "; ".join(self._errors.values())
        elif self._warnings:
            message = "; ".join(self._warnings.values())
        else:
            message = "ok"
        values = [KeyValue(key=k, value=str(v)) for k, v in sorted(self.counters.items())]
        values += [KeyValue(key=k, value=v) for k, v in sorted(self.info.items())]
        return DiagnosticStatus(level=self.level, name=self.node.get_fully_qualified_name(), message=message,
                                hardware_id="vigs", values=values)

    def publish(self) -> None:
        msg = DiagnosticArray()
        msg.header.stamp = self.node.get_clock().now().to_msg()
        msg.status = [self.status()]
        self._pub.publish(msg)
        self._warnings.clear()
