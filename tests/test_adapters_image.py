"""Image and CompressedImage adapters: every encoding, padded rows, byte order, malformed messages."""
from __future__ import annotations

import numpy as np
import pytest
from adapters_helpers import cdr_round_trip, types  # noqa: F401  (types is a fixture)

from msg_adapters.image import (
    any_image_to_numpy,
    compressed_to_numpy,
    image_to_numpy,
    numpy_to_compressed,
    numpy_to_image,
    to_mono8,
)

RNG = np.random.default_rng(7)
SAMPLES = {
    "mono8": RNG.integers(0, 256, (5, 7), dtype=np.uint8),
    "rgb8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "bgr8": RNG.integers(0, 256, (5, 7, 3), dtype=np.uint8),
    "16UC1": RNG.integers(0, 65536, (5, 7), dtype=np.uint16),
    "32FC1": RNG.standard_normal((5, 7)).astype(np.float32),
}


@pytest.mark.parametrize("encoding", sorted(SAMPLES))
@pytest.mark.parametrize("pad", [0, 5])
def test_image_round_trip_every_encoding_with_padding(types, encoding, pad):
    array = SAMPLES[encoding]
    row = array.shape[1] * array.itemsize * (3 if array.ndim == 3 else 1)
    msg = numpy_to_image(types, array, encoding, 1_500_000_123, "cam0", step=row + pad)
    assert msg.step == row + pad
    back = cdr_round_trip(types, msg, "sensor_msgs/msg/Image")
    t_ns, out, enc = any_image_to_numpy(back)
    assert t_ns == 1_500_000_123 and enc == encoding
    assert out.dtype == array.dtype and out.shape == array.shape
    np.testing.assert_array_equal(out, array)


def test_big_endian_16bit_image_is_byte_swapped(types):
    depth = np.array([[1, 258], [65535, 4096]], dtype=np.uint16)
    msg = numpy_to_image(types, depth, "16UC1", 0, "cam")
    msg.is_bigendian = 1
    msg.data = types.sequence(depth.astype(">u2").view(np.uint8), np.uint8)
    out, _ = image_to_numpy(msg)
    np.testing.assert_array_equal(out, depth)


def test_padding_bytes_are_ignored(types):
    img = SAMPLES["mono8"]
    msg = numpy_to_image(types, img, "mono8", 0, "cam", step=16)
    raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(5, 16).copy()
    raw[:, 7:] = 255  # garbage in the padding must not leak into the image
    msg.data = types.sequence(raw, np.uint8)
    np.testing.assert_array_equal(image_to_numpy(msg)[0], img)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda m, t: setattr(m, "encoding", "yuv422"), "unsupported encoding"),
        (lambda m, t: setattr(m, "step", 3), "smaller than"),
        (lambda m, t: setattr(m, "data", t.sequence(np.zeros(10, np.uint8), np.uint8)), "expected at least"),
        (lambda m, t: setattr(m, "width", 0), "empty image"),
    ],
)
def test_malformed_image_raises_value_error(types, mutate, message):
    msg = numpy_to_image(types, SAMPLES["mono8"], "mono8", 0, "cam")
    mutate(msg, types)
    with pytest.raises(ValueError, match=message):
        image_to_numpy(msg)


def test_building_with_wrong_array_raises(types):
    with pytest.raises(ValueError, match="rgb8 needs"):
        numpy_to_image(types, SAMPLES["mono8"], "rgb8", 0, "cam")
    with pytest.raises(ValueError, match="unsupported encoding"):
        numpy_to_image(types, SAMPLES["mono8"], "mono16", 0, "cam")


@pytest.mark.parametrize("encoding", ["mono8", "bgr8", "16UC1"])
def test_compressed_png_is_lossless(types, encoding):
    array = SAMPLES[encoding]
    msg = cdr_round_trip(types, numpy_to_compressed(types, array, encoding, 42, "cam"),
                         "sensor_msgs/msg/CompressedImage")
    t_ns, out, enc = any_image_to_numpy(msg)
    assert (t_ns, enc) == (42, encoding)
    np.testing.assert_array_equal(out, array)


def test_compressed_rgb8_comes_back_as_bgr8(types):
    rgb = SAMPLES["rgb8"]
    out, enc = compressed_to_numpy(numpy_to_compressed(types, rgb, "rgb8", 0, "cam"))
    assert enc == "bgr8"
    np.testing.assert_array_equal(out[..., ::-1], rgb)


def test_compressed_jpeg_is_close(types):
    smooth = np.tile(np.linspace(0, 255, 32, dtype=np.uint8), (32, 1))
    out, enc = compressed_to_numpy(numpy_to_compressed(types, smooth, "mono8", 0, "cam", fmt="jpeg"))
    assert enc == "mono8"
    assert np.abs(out.astype(int) - smooth).max() <= 8


def test_malformed_compressed_raises(types):
    msg = numpy_to_compressed(types, SAMPLES["mono8"], "mono8", 0, "cam")
    msg.data = types.sequence(np.frombuffer(b"not an image at all", np.uint8), np.uint8)
    with pytest.raises(ValueError, match="do not decode"):
        compressed_to_numpy(msg)
    msg.data = types.sequence(np.zeros(0, np.uint8), np.uint8)
    with pytest.raises(ValueError, match="empty data"):
        compressed_to_numpy(msg)
    with pytest.raises(ValueError, match="needs png"):
        numpy_to_compressed(types, SAMPLES["16UC1"], "16UC1", 0, "cam", fmt="jpeg")


def test_to_mono8():
    rgb = SAMPLES["rgb8"]
    grey_rgb = to_mono8(rgb, "rgb8")
    np.testing.assert_array_equal(grey_rgb, to_mono8(rgb[..., ::-1].copy(), "bgr8"))
    assert grey_rgb.shape == rgb.shape[:2]
    with pytest.raises(ValueError, match="8-bit intensity"):
        to_mono8(SAMPLES["32FC1"], "32FC1")
