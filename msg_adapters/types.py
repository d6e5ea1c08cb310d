"""Message-class providers: one adapter code path builds rclpy messages or rosbags messages.

Reading needs no provider: rclpy and rosbags message classes have the same field names, so adapters
read fields duck-typed. Building a message needs its class and the right container for sequence
fields, which differ:

* rclpy: classes from ``<pkg>.msg``; unbounded sequences are ``array.array`` (built from raw bytes
  here, which is O(1) per element instead of a Python loop), fixed-size arrays are numpy arrays.
* rosbags: dataclasses from a typestore (``get_typestore(Stores.ROS2_JAZZY)``); every field must be
  given; numeric sequences and arrays are numpy arrays. The VIGS messages (interfaces/vigs_msgs) are
  registered into the typestore from their ``.msg`` files.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
import array
import importlib
import sys
from pathlib import Path
from typing import Any

import numpy as np

# numpy dtype -> array.array type code, for rclpy's unbounded sequences.
_ARRAY_CODES = {
    np.dtype(np.uint8): "B",
    np.dtype(np.int8): "b",
    np.dtype(np.uint16): "H",
    np.dtype(np.int16): "h",
    np.dtype(np.uint32): "I",
    np.dtype(np.int32): "i",
    np.dtype(np.uint64): "Q",
    np.dtype(np.int64): "q",
    np.dtype(np.float32): "f",
    np.dtype(np.float64): "d",
}

VIGS_PACKAGES = ("vigs_msgs", "tf2_msgs")


def interface_dirs(package: str) -> list[Path]:
    """Directories that may hold ``<package>/msg/*.msg``: the repository's ``interfaces/`` and the
    install prefix's ``share/`` (where scripts/build_interfaces.sh installs them)."""
    repo = Path(__file__).resolve().parent.parent / "interfaces" / package / "msg"
    installed = Path(sys.prefix) / "share" / package / "msg"
    return [d for d in (repo, installed) if d.is_dir()]


class MessageTypes(ABC):
    """Interface of a message-class provider (see :class:`RclpyTypes`, :class:`RosbagsTypes`)."""

    @abstractmethod
    def new(self, typename: str, **fields: Any):
        """A message of ``typename`` (e.g. ``"sensor_msgs/msg/Image"``) with ``fields`` set."""

    @abstractmethod
    def sequence(self, values, dtype) -> Any:
        """An unbounded numeric sequence field holding ``values`` as ``dtype``."""

    @abstractmethod
    def serialize(self, msg, typename: str) -> bytes:
        """CDR bytes of ``msg`` (what a bag stores and DDS carries)."""

    @abstractmethod
    def deserialize(self, data: bytes, typename: str):
        """The message of ``typename`` encoded in CDR ``data``."""


class RclpyTypes(MessageTypes):
    """Message classes of the rclpy message packages importable in this interpreter."""

    def __init__(self) -> None:
        self._classes: dict[str, type] = {}

    def message_class(self, typename: str) -> type:
        cls = self._classes.get(typename)
        if cls is None:
            try:
                package, kind, name = typename.split("/")
            except ValueError:
                raise ValueError(f"message type {typename!r} is not of the form 'package/msg/Name'") from None
            try:
                module = importlib.import_module(f"{package}.{kind}")
                cls = getattr(module, name)
            except (ImportError, AttributeError) as exc:
                hint = " (run scripts/build_interfaces.sh)" if package in VIGS_PACKAGES else ""
                raise ValueError(f"message type {typename!r} is not importable in rclpy: {exc}{hint}") from None
            self._classes[typename] = cls
        return cls

    def new(self, typename: str, **fields: Any):
        return self.message_class(typename)(**fields)

    def sequence(self, values, dtype) -> Any:
        arr = np.ascontiguousarray(values, dtype=dtype).reshape(-1)
        return array.array(_ARRAY_CODES[arr.dtype], arr.tobytes())

    def serialize(self, msg, typename: str) -> bytes:
        from rclpy.serialization import serialize_message

        return serialize_message(msg)

    def deserialize(self, data: bytes, typename: str):
        from rclpy.serialization import deserialize_message

        return deserialize_message(bytes(data), self.message_class(typename))


class RosbagsTypes(MessageTypes):
    """Message classes of a rosbags typestore (default: ROS 2 Jazzy) plus the VIGS messages.

    Args:
        typestore: a rosbags ``Typestore``; ``None`` makes ``get_typestore(Stores.ROS2_JAZZY)``.
        register_vigs: register vigs_msgs (and tf2_msgs if the store lacks it) from their ``.msg`` files.
    """

    def __init__(self, typestore=None, register_vigs: bool = True) -> None:
        if typestore is None:
            from rosbags.typesys import Stores, get_typestore

            typestore = get_typestore(Stores.ROS2_JAZZY)
        self.typestore = typestore
        if register_vigs:
            register_interfaces(typestore)

    def new(self, typename: str, **fields: Any):
        try:
            cls = self.typestore.types[typename]
        except KeyError:
            raise ValueError(f"message type {typename!r} is not in the rosbags typestore") from None
        return cls(**fields)

    def sequence(self, values, dtype) -> Any:
        return np.ascontiguousarray(values, dtype=dtype).reshape(-1)

    def serialize(self, msg, typename: str) -> bytes:
        return bytes(self.typestore.serialize_cdr(msg, typename))

    def deserialize(self, data: bytes, typename: str):
        return self.typestore.deserialize_cdr(bytes(data), typename)


def register_interfaces(typestore, packages: tuple[str, ...] = VIGS_PACKAGES) -> None:
    """Register the ``.msg`` definitions of ``packages`` (see :func:`interface_dirs`) in a rosbags
    typestore, skipping types it already has (e.g. tf2_msgs in the Jazzy store)."""
    from rosbags.typesys import get_types_from_msg

    types = {}
    for package in packages:
        dirs = interface_dirs(package)
        if not dirs:
            if package == "vigs_msgs":
                raise FileNotFoundError(f"no {package}/msg/*.msg found in interfaces/ or {sys.prefix}/share")
            continue
        for path in sorted(dirs[0].glob("*.msg")):
            name = f"{package}/msg/{path.stem}"
            if name not in typestore.types:
                types.update(get_types_from_msg(path.read_text(), name))
    if types:
        typestore.register(types)
