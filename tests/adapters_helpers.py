"""Shared pieces of the adapter tests: a ``types`` fixture giving each message-class provider, and a
serialize/deserialize round trip through CDR so the message classes (not just the adapters) are exercised.

Import with ``from adapters_helpers import types, cdr_round_trip`` (pytest finds the imported fixture).
"""
from __future__ import annotations

import pytest

from msg_adapters.types import RclpyTypes, RosbagsTypes

_PROVIDERS: dict = {}


@pytest.fixture(params=["rclpy", "rosbags"])
def types(request):
    """The message-class provider under test (one test run per provider)."""
    if request.param not in _PROVIDERS:
        _PROVIDERS[request.param] = RclpyTypes() if request.param == "rclpy" else RosbagsTypes()
    return _PROVIDERS[request.param]


def cdr_round_trip(types, msg, typename: str):
    """``msg`` serialized to CDR and read back by the same provider."""
    return types.deserialize(types.serialize(msg, typename), typename)
