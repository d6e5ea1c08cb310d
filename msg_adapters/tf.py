"""TF: ``geometry_msgs/TransformStamped`` and ``tf2_msgs/TFMessage`` <-> (4, 4) transforms.

A TransformStamped with ``header.frame_id = parent`` and ``child_frame_id = child`` carries
``T_parent_child`` (it maps points in the child frame into the parent frame).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msg_adapters.common import field, header_stamp_ns, make_header, transform_msg, transform_to_matrix
from msg_adapters.types import MessageTypes


@dataclass
class StampedTransform:
    """``T_parent_child`` (4, 4) at ``t_ns``."""

    t_ns: int
    parent: str
    child: str
    T: np.ndarray


def transform_stamped(types: MessageTypes, T, t_ns: int, parent: str, child: str):
    """A ``geometry_msgs/TransformStamped`` of ``T_parent_child``."""
    if not parent or not child or parent == child:
        raise ValueError(f"TransformStamped: need two distinct non-empty frames, got {parent!r} -> {child!r}")
    return types.new(
        "geometry_msgs/msg/TransformStamped",
        header=make_header(types, t_ns, parent),
        child_frame_id=child,
        transform=transform_msg(types, T),
    )


def transform_stamped_to_matrix(msg) -> StampedTransform:
    """The StampedTransform of a TransformStamped."""
    parent = str(field(field(msg, "header", "TransformStamped"), "frame_id", "TransformStamped"))
    child = str(field(msg, "child_frame_id", "TransformStamped"))
    if not parent or not child:
        raise ValueError(f"TransformStamped: empty frame id (parent {parent!r}, child {child!r})")
    T = transform_to_matrix(field(msg, "transform", "TransformStamped"), "TransformStamped.transform")
    return StampedTransform(header_stamp_ns(msg, "TransformStamped"), parent, child, T)


def tf_message(types: MessageTypes, transforms: list[StampedTransform]):
    """A ``tf2_msgs/TFMessage`` holding ``transforms``."""
    return types.new(
        "tf2_msgs/msg/TFMessage",
        transforms=[transform_stamped(types, t.T, t.t_ns, t.parent, t.child) for t in transforms],
    )


def tf_message_to_transforms(msg) -> list[StampedTransform]:
    """The StampedTransforms of a TFMessage."""
    return [transform_stamped_to_matrix(t) for t in field(msg, "transforms", "TFMessage")]
