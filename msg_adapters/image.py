"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` <-> numpy images.

Supported encodings (REP-104 / sensor_msgs image_encodings names) and the arrays they map to:

=========  ==============  ========
encoding   array shape      dtype
=========  ==============  ========
mono8      (H, W)          uint8
rgb8       (H, W, 3)       uint8
bgr8       (H, W, 3)       uint8
16UC1      (H, W)          uint16   (e.g. depth in mm)
32FC1      (H, W)          float32  (e.g. depth in m, disparity in 1/m)
=========  ==============  ========

Row ``i`` of the image starts at byte ``i * step`` of ``data``; ``step >= W * bytes_per_pixel`` (rows may
be padded) and ``is_bigendian`` gives the byte order of multi-byte pixels.
"""
from __future__ import annotations


import cv2
import numpy as np

from msg_adapters.common import field, header_stamp_ns, make_header, numeric
from msg_adapters.types import MessageTypes

# encoding -> (channels, dtype)
ENCODINGS = {
    "mono8": (1, np.dtype(np.uint8)),
    "rgb8": (3, np.dtype(np.uint8)),
    "bgr8": (3, np.dtype(np.uint8)),
    "16UC1": (1, np.dtype(np.uint16)),
    "32FC1": (1, np.dtype(np.float32)),
}


def image_to_numpy(msg) -> tuple[np.ndarray, str]:
    """``(array, encoding)`` of a ``sensor_msgs/Image`` (a copy, native byte order; see module table).

    Raises:
        ValueError: unsupported encoding, zero size, ``step`` smaller than a row, or ``data`` shorter
            than ``step * height``.
    """
    encoding = str(field(msg, "encoding", "Image"))
    if encoding not in ENCODINGS:
        raise ValueError(f"Image: unsupported encoding {encoding!r}; expected one of {sorted(ENCODINGS)}")
    channels, dtype = ENCODINGS[encoding]
    height = int(field(msg, "height", "Image"))
    width = int(field(msg, "width", "Image"))
    step = int(field(msg, "step", "Image"))
    if height <= 0 or width <= 0:
        raise ValueError(f"Image: empty image ({width}x{height}); expected width and height > 0")
    row_bytes = width * channels * dtype.itemsize
    if step < row_bytes:
        raise ValueError(f"Image: step {step} B is smaller than a {encoding} row of width {width} ({row_bytes} B)")
    data = numeric(field(msg, "data", "Image"), np.uint8, "Image.data")
    if data.size < step * (height - 1) + row_bytes:
        raise ValueError(
            f"Image: data has {data.size} B, expected at least {step * (height - 1) + row_bytes} B "
            f"for {height} rows of step {step}"
        )
    rows = np.lib.stride_tricks.as_strided(data, shape=(height, row_bytes), strides=(step, 1))
    big = bool(field(msg, "is_bigendian", "Image"))
    pixel_dtype = dtype.newbyteorder(">" if big else "<") if dtype.itemsize > 1 else dtype
    array = np.ascontiguousarray(rows).view(pixel_dtype).astype(dtype, copy=False)
    shape = (height, width) if channels == 1 else (height, width, channels)
    return array.reshape(shape).copy(), encoding


def numpy_to_image(types: MessageTypes, array: np.ndarray, encoding: str, t_ns: int, frame_id: str,
                   step: int | None = None):
    """A ``sensor_msgs/Image`` holding ``array`` (see module table) in little-endian byte order.

    Args:
        step: row stride in bytes; default (and minimum) ``W * bytes_per_pixel``. Larger values pad rows.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"Image: unsupported encoding {encoding!r}; expected one of {sorted(ENCODINGS)}")
    channels, dtype = ENCODINGS[encoding]
    array = np.asarray(array)
    expected_ndim = 2 if channels == 1 else 3
    if array.ndim != expected_ndim or (channels == 3 and array.shape[2] != 3) or array.dtype != dtype:
        raise ValueError(
            f"Image: {encoding} needs a {'(H, W)' if channels == 1 else '(H, W, 3)'} {dtype} array, "
            f"got shape {array.shape} {array.dtype}"
        )
    height, width = array.shape[:2]
    row_bytes = width * channels * dtype.itemsize
    step = row_bytes if step is None else int(step)
    if step < row_bytes:
        raise ValueError(f"Image: step {step} B is smaller than a row ({row_bytes} B)")
    little = np.ascontiguousarray(array, dtype=dtype.newbyteorder("<")).reshape(height, row_bytes // dtype.itemsize)
    raw = little.view(np.uint8).reshape(height, row_bytes)
    if step > row_bytes:
        raw = np.concatenate([raw, np.zeros((height, step - row_bytes), np.uint8)], axis=1)
    return types.new(
        "sensor_msgs/msg/Image",
        header=make_header(types, t_ns, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=types.sequence(raw, np.uint8),
    )


def compressed_to_numpy(msg) -> tuple[np.ndarray, str]:
    """``(array, encoding)`` of a ``sensor_msgs/CompressedImage`` (JPEG or PNG): mono8 for grey images,
    bgr8 for colour ones, 16UC1 for 16-bit PNGs.

    Raises:
        ValueError: empty data or data that does not decode as an image.
    """
    fmt = str(field(msg, "format", "CompressedImage"))
    data = numeric(field(msg, "data", "CompressedImage"), np.uint8, "CompressedImage.data")
    if data.size == 0:
        raise ValueError(f"CompressedImage: empty data (format {fmt!r})")
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"CompressedImage: {data.size} B of format {fmt!r} do not decode as JPEG or PNG")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.dtype == np.uint16:
        if image.ndim != 2:
            raise ValueError(f"CompressedImage: 16-bit colour images are not supported (shape {image.shape})")
        return image, "16UC1"
    return image, ("mono8" if image.ndim == 2 else "bgr8")


def numpy_to_compressed(types: MessageTypes, array: np.ndarray, encoding: str, t_ns: int, frame_id: str,
                        fmt: str = "png", jpeg_quality: int = 95):
    """A ``sensor_msgs/CompressedImage`` of ``array`` (mono8, rgb8, bgr8 or 16UC1 for png; 8-bit for jpeg).

    ``format`` is ``"png"`` or ``"jpeg"``; decoders here (and image_transport's) read the data's magic bytes.
    """
    if fmt not in ("png", "jpeg"):
        raise ValueError(f"CompressedImage: format must be 'png' or 'jpeg', got {fmt!r}")
    if encoding not in ("mono8", "rgb8", "bgr8", "16UC1"):
        raise ValueError(f"CompressedImage: cannot compress encoding {encoding!r}; expected mono8, rgb8, bgr8, 16UC1")
    if encoding == "16UC1" and fmt == "jpeg":
        raise ValueError("CompressedImage: 16UC1 needs png (jpeg is 8-bit)")
    array = np.asarray(array)
    if encoding == "rgb8":
        array = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode("." + ("jpg" if fmt == "jpeg" else "png"), array, params)
    if not ok:
        raise ValueError(f"CompressedImage: OpenCV could not encode a {array.shape} {array.dtype} image as {fmt}")
    return types.new(
        "sensor_msgs/msg/CompressedImage",
        header=make_header(types, t_ns, frame_id),
        format=fmt,
        data=types.sequence(buf.reshape(-1), np.uint8),
    )


def to_mono8(array: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W) uint8 grey image of an 8-bit image of ``encoding`` (mono8, rgb8 or bgr8)."""
    if encoding == "mono8":
        return array
    if encoding == "rgb8":
        return cv2.cvtColor(array, cv2.COLOR_RGB2GRAY)
    if encoding == "bgr8":
        return cv2.cvtColor(array, cv2.COLOR_BGR2GRAY)
    raise ValueError(f"to_mono8: expected an 8-bit intensity image (mono8, rgb8, bgr8), got {encoding!r}")


def any_image_to_numpy(msg) -> tuple[int, np.ndarray, str]:
    """``(t_ns, array, encoding)`` of an Image or a CompressedImage (told apart by their fields)."""
    if hasattr(msg, "format") and not hasattr(msg, "encoding"):
        array, encoding = compressed_to_numpy(msg)
        return header_stamp_ns(msg, "CompressedImage"), array, encoding
    array, encoding = image_to_numpy(msg)
    return header_stamp_ns(msg, "Image"), array, encoding


