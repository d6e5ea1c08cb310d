"""PointCloud2 adapter: round trip through CDR for both providers, foreign layouts, malformed clouds."""
from __future__ import annotations

import numpy as np
import pytest
from adapters_helpers import cdr_round_trip, types  # noqa: F401  (types is a fixture)

from msg_adapters.pointcloud import pointcloud2_to_points, points_to_pointcloud2


def coloured_points(n: int = 50, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(scale=3.0, size=(n, 3)), rng.uniform(size=(n, 3))


def test_round_trip_keeps_points_and_8bit_colours(types):
    xyz, rgb = coloured_points()
    msg = points_to_pointcloud2(types, xyz, rgb, 1_500_000_123, "map")
    back = cdr_round_trip(types, msg, "sensor_msgs/msg/PointCloud2")
    assert (back.width, back.height, back.point_step, back.row_step) == (50, 1, 16, 800)
    assert [f.name for f in back.fields] == ["x", "y", "z", "rgb"]
    t_ns, xyz2, rgb2 = pointcloud2_to_points(back)
    assert t_ns == 1_500_000_123
    np.testing.assert_allclose(xyz2, xyz, rtol=1e-6, atol=1e-6)  # float32 storage
    np.testing.assert_allclose(rgb2, np.round(rgb * 255) / 255, atol=1e-12)


def test_packed_colour_follows_the_pcl_convention(types):
    msg = points_to_pointcloud2(types, [[0.0, 0.0, 1.0]], [[1.0, 0.5, 0.0]], 0, "map")
    packed = np.frombuffer(bytes(msg.data), dtype="<u4")[3]
    assert packed == (255 << 16) | (128 << 8) | 0


def test_foreign_layout_with_padding_float64_and_nan_points(types):
    """A cloud laid out by another producer: float64 z first, padding, big-endian, no colour, a NaN point."""
    dtype = np.dtype({"names": ["z", "x", "y"], "formats": [">f8", ">f4", ">f4"], "offsets": [0, 8, 12],
                      "itemsize": 24})
    rows = np.zeros(3, dtype=dtype)
    rows["x"], rows["y"], rows["z"] = [1.0, np.nan, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]
    fields = [types.new("sensor_msgs/msg/PointField", name=n, offset=o, datatype=d, count=1)
              for n, o, d in (("z", 0, 8), ("x", 8, 7), ("y", 12, 7))]
    msg = types.new("sensor_msgs/msg/PointCloud2", header=points_to_pointcloud2(types, [[0, 0, 0]], [[0, 0, 0]], 5,
                                                                                "map").header,
                    height=1, width=3, fields=fields, is_bigendian=True, point_step=24, row_step=72,
                    data=types.sequence(rows.view(np.uint8), np.uint8), is_dense=False)
    _, xyz, rgb = pointcloud2_to_points(msg)
    assert rgb is None
    np.testing.assert_allclose(xyz, [[1.0, 4.0, 7.0], [3.0, 6.0, 9.0]])


def test_malformed_clouds_are_rejected_with_a_reason(types):
    xyz, rgb = coloured_points(4)
    with pytest.raises(ValueError, match="finite"):
        points_to_pointcloud2(types, np.vstack([xyz, [[np.nan, 0, 0]]]), np.vstack([rgb, [[0, 0, 0]]]), 0, "map")
    with pytest.raises(ValueError, match="colours"):
        points_to_pointcloud2(types, xyz, rgb[:3], 0, "map")
    msg = points_to_pointcloud2(types, xyz, rgb, 0, "map")
    msg.width = 5  # claims more points than the data holds
    with pytest.raises(ValueError, match="bytes"):
        pointcloud2_to_points(msg)
    msg = points_to_pointcloud2(types, xyz, rgb, 0, "map")
    msg.fields = msg.fields[1:]
    with pytest.raises(ValueError, match="no 'x' field"):
        pointcloud2_to_points(msg)
