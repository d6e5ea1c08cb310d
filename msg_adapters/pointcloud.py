"""``sensor_msgs/PointCloud2`` <-> coloured points (N, 3) xyz + (N, 3) RGB.

Layout written (what RViz's PointCloud2 display and PCL's ``PointXYZRGB`` read): one row (``height`` 1,
``width`` N), little-endian, fields ``x``, ``y``, ``z`` as FLOAT32 at offsets 0, 4, 8 and ``rgb`` at offset 12, a
FLOAT32 whose four bytes are the packed integer ``0x00RRGGBB`` (the PCL convention); ``point_step`` 16.

Reading accepts any field order, extra fields, padding (``point_step`` larger than the fields) and both byte
orders; ``x``, ``y``, ``z`` must be FLOAT32 or FLOAT64. Points with a non-finite coordinate are dropped (clouds
with ``is_dense`` false may hold them).
"""
from __future__ import annotations

import numpy as np

from msg_adapters.common import field, header_stamp_ns, make_header
from msg_adapters.types import MessageTypes

# sensor_msgs/PointField datatype constants -> numpy scalar type (byte order applied per message)
POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
FLOAT32 = 7
POINT_STEP = 16


def points_to_pointcloud2(types: MessageTypes, xyz, rgb, t_ns: int, frame_id: str):
    """A PointCloud2 of ``xyz`` (N, 3) in ``frame_id`` coloured by ``rgb`` (N, 3) in [0, 1] (clipped)."""
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not np.all(np.isfinite(xyz)):
        raise ValueError(f"points must be a finite (N, 3) array, got shape {xyz.shape}")
    rgb = np.asarray(rgb, dtype=np.float64)
    if rgb.shape != xyz.shape:
        raise ValueError(f"colours have shape {rgb.shape}, points {xyz.shape}")
    n = xyz.shape[0]
    channels = np.round(np.clip(np.nan_to_num(rgb), 0.0, 1.0) * 255.0).astype(np.uint32)
    packed = (channels[:, 0] << 16) | (channels[:, 1] << 8) | channels[:, 2]
    rows = np.empty(n, dtype=np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")]))
    rows["x"], rows["y"], rows["z"], rows["rgb"] = xyz[:, 0], xyz[:, 1], xyz[:, 2], packed
    fields = [types.new("sensor_msgs/msg/PointField", name=name, offset=4 * k, datatype=FLOAT32, count=1)
              for k, name in enumerate(("x", "y", "z", "rgb"))]
    return types.new(
        "sensor_msgs/msg/PointCloud2",
        header=make_header(types, t_ns, frame_id),
        height=1, width=n, fields=fields, is_bigendian=False, point_step=POINT_STEP, row_step=POINT_STEP * n,
        data=types.sequence(rows.view(np.uint8), np.uint8), is_dense=True,
    )


def _field_dtype(msg) -> np.dtype:
    """The numpy structured dtype of one point of ``msg`` (its fields at their offsets, ``point_step`` bytes)."""
    order = ">" if bool(field(msg, "is_bigendian", "PointCloud2")) else "<"
    names, formats, offsets = [], [], []
    for f in field(msg, "fields", "PointCloud2"):
        kind = POINTFIELD_DTYPES.get(int(f.datatype))
        if kind is None:
            raise ValueError(f"PointCloud2 field {f.name!r} has unknown datatype {f.datatype}")
        count = int(f.count) if int(f.count) > 0 else 1
        names.append(str(f.name))
        formats.append((order + kind, (count,)) if count > 1 else order + kind)
        offsets.append(int(f.offset))
    step = int(field(msg, "point_step", "PointCloud2"))
    try:
        return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    except ValueError as exc:
        raise ValueError(f"PointCloud2 fields do not fit its point_step {step}: {exc}") from None


def pointcloud2_to_points(msg) -> tuple[int, np.ndarray, np.ndarray | None]:
    """``(t_ns, xyz (N, 3) float64, rgb (N, 3) in [0, 1] or None)`` of a PointCloud2; ``rgb`` is None when
    the cloud has no ``rgb`` field. Non-finite points are dropped."""
    dtype = _field_dtype(msg)
    for name in ("x", "y", "z"):
        if name not in dtype.names:
            raise ValueError(f"PointCloud2 has no {name!r} field (fields: {', '.join(dtype.names)})")
        if dtype[name].kind != "f":
            raise ValueError(f"PointCloud2 field {name!r} is {dtype[name]}, expected FLOAT32 or FLOAT64")
    height, width = int(msg.height), int(msg.width)
    row_step, step = int(msg.row_step), dtype.itemsize
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if row_step < width * step or raw.size < row_step * height:
        raise ValueError(f"PointCloud2 data has {raw.size} bytes, expected {height} rows of {row_step} "
                         f"(>= {width} points x {step} bytes)")
    rows = raw[: row_step * height].reshape(height, row_step)[:, : width * step]
    points = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    xyz = np.stack([points[n].astype(np.float64) for n in ("x", "y", "z")], axis=1)
    keep = np.isfinite(xyz).all(axis=1)
    rgb = None
    if "rgb" in dtype.names:
        packed = np.ascontiguousarray(points["rgb"]).view(np.uint32) if dtype["rgb"].itemsize == 4 else None
        if packed is None:
            raise ValueError(f"PointCloud2 field 'rgb' is {dtype['rgb']}, expected a 4-byte packed colour")
        rgb = np.stack([(packed >> s) & 0xFF for s in (16, 8, 0)], axis=1).astype(np.float64)[keep] / 255.0
    return header_stamp_ns(msg, "PointCloud2"), xyz[keep], rgb
