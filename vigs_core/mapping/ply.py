"""Gaussian maps as standard 3DGS PLY files plus a JSON sidecar with the keyframes.

The PLY is ``binary_little_endian 1.0`` with one ``vertex`` element per Gaussian and the float32 properties
of the original 3D Gaussian Splatting exporter (Kerbl et al. 2023) at SH degree 3, which common splat loaders
and viewers read:

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_44  opacity  scale_0 scale_1 scale_2
    rot_0 rot_1 rot_2 rot_3

with ``opacity`` the logit, ``scale_*`` the log standard deviations (metres), ``rot_*`` the unit quaternion
``(w, x, y, z)`` (normalised on writing: the map stores it unnormalised), normals zero, and the colour as the
degree-0 spherical-harmonic coefficient ``f_dc = (rgb - 0.5) / C0``, ``C0 = 0.28209479177387814``. The map's
colour is view-independent, so the 45 higher-band coefficients are zero; they are written because loaders
built for the original exporter expect ``3 (degree + 1)^2 - 3`` of them (a header comment states the degree).
Our own property ``int anchor_id`` (the keyframe each Gaussian is anchored to) follows; loaders that look
properties up by name ignore it (checked with PlayCanvas splat-transform in tests/test_mapping_ply.py).

The sidecar ``<name>.json`` holds ``{"format", "version", "keyframes": [{"id", "T_WC" (4x4 rows),
"timestamp_ns"}], "camera": {...} | null, "extra": {...}}``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from vigs_core.mapping.gaussians import GaussianMap

SH_C0 = 0.28209479177387814
SH_DEGREE = 3
F_REST = [f"f_rest_{i}" for i in range(3 * (SH_DEGREE + 1) ** 2 - 3)]
FLOAT_PROPERTIES = (
    "x y z nx ny nz f_dc_0 f_dc_1 f_dc_2".split() + F_REST
    + "opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split()
)
SIDECAR_FORMAT = "vigs-gaussian-map"
SIDECAR_VERSION = 1

# PLY scalar type names -> little-endian numpy types.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
    "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4",
    "float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8",
}  # fmt: skip


def sidecar_path(ply_path: str | Path) -> Path:
    """``map.ply`` -> ``map.json``."""
    return Path(ply_path).with_suffix(".json")


def save_ply(path: str | Path, gmap: GaussianMap) -> None:
    """Write ``gmap`` as a binary 3DGS PLY (layout in the module docstring)."""
    g = gmap.detached().to("cpu")
    n = len(g)
    dtype = np.dtype([(name, "<f4") for name in FLOAT_PROPERTIES] + [("anchor_id", "<i4")])
    rows = np.zeros(n, dtype=dtype)
    means = g.means.numpy()
    dc = ((g.colors - 0.5) / SH_C0).numpy()
    log_s = g.log_scales.numpy()
    q = torch.nn.functional.normalize(g.quats, dim=-1).numpy()
    for i, axis in enumerate("xyz"):
        rows[axis] = means[:, i]
        rows[f"f_dc_{i}"] = dc[:, i]
        rows[f"scale_{i}"] = log_s[:, i]
    for i in range(4):
        rows[f"rot_{i}"] = q[:, i]
    rows["opacity"] = g.opacity_logits.numpy()
    rows["anchor_id"] = g.anchor_ids.numpy().astype(np.int32)
    header = ["ply", "format binary_little_endian 1.0",
              f"comment SH degree {SH_DEGREE}: f_rest_* are zero, the colour is view-independent",
              f"element vertex {n}"]
    header += [f"property float {name}" for name in FLOAT_PROPERTIES] + ["property int anchor_id", "end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(rows.tobytes())


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The ``vertex`` element of a binary little-endian PLY as a numpy structured array (any properties)."""
    with open(path, "rb") as f:
        first = f.readline().strip()
        if first != b"ply":
            raise ValueError(f"{path}: not a PLY file (first line {first!r}, expected b'ply')")
        fmt, elements, current = None, [], None
        while True:
            line = f.readline()
            if not line:
                raise ValueError(f"{path}: PLY header has no 'end_header'")
            words = line.decode("ascii").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                current = [words[1], int(words[2]), []]
                elements.append(current)
            elif words[0] == "property":
                if current is None or words[1] == "list":
                    raise ValueError(
                        f"{path}: unsupported PLY property line {line!r} (scalar vertex properties expected)"
                    )
                if words[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY type {words[1]!r}; known: {sorted(_PLY_TYPES)}")
                current[2].append((words[2], _PLY_TYPES[words[1]]))
        if fmt != "binary_little_endian":
            raise ValueError(f"{path}: PLY format {fmt!r} not supported (expected binary_little_endian)")
        if not elements or elements[0][0] != "vertex":
            raise ValueError(f"{path}: the first PLY element must be 'vertex', got {[e[0] for e in elements]}")
        name, count, props = elements[0]
        dtype = np.dtype(props)
        data = np.frombuffer(f.read(count * dtype.itemsize), dtype=dtype, count=count)
    return data


def load_ply(path: str | Path, dtype: torch.dtype = torch.float32) -> GaussianMap:
    """Read a 3DGS PLY (ours or another exporter's, SH degree >= 0; higher SH bands are ignored).

    Gaussians get ids ``0..N-1``; ``anchor_id`` is -1 when the file has none."""
    v = read_ply_vertices(path)
    needed = [p for p in FLOAT_PROPERTIES if not p.startswith(("n", "f_rest"))]
    missing = [p for p in needed if p not in v.dtype.names]
    if missing:
        raise ValueError(f"{path}: PLY lacks the 3DGS properties {missing}")
    def col(*names: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([v[nm].astype(np.float64) for nm in names], -1)).to(dtype)

    n = len(v)
    anchors = v["anchor_id"].astype(np.int64) if "anchor_id" in v.dtype.names else np.full(n, -1, np.int64)
    return GaussianMap(
        means=col("x", "y", "z"),
        log_scales=col("scale_0", "scale_1", "scale_2"),
        quats=col("rot_0", "rot_1", "rot_2", "rot_3"),
        opacity_logits=col("opacity")[:, 0],
        colors=col("f_dc_0", "f_dc_1", "f_dc_2") * SH_C0 + 0.5,
        anchor_ids=torch.from_numpy(anchors),
        ids=torch.arange(n, dtype=torch.int64),
    )


def save_map(
    path: str | Path,
    gmap: GaussianMap,
    keyframes: dict[int, torch.Tensor],
    timestamps_ns: dict[int, int] | None = None,
    camera: dict | None = None,
    extra: dict | None = None,
) -> Path:
    """Write ``path`` (PLY) and its sidecar ``path.with_suffix('.json')``; returns the sidecar path.

    Args:
        keyframes: ``{kf_id: T_WC (4, 4)}``.
        timestamps_ns: optional ``{kf_id: t_ns}``.
        camera: optional intrinsics dict (e.g. ``{"width", "height", "fx", "fy", "cx", "cy"}``).
        extra: optional JSON-serialisable dict stored as is.
    """
    save_ply(path, gmap)
    timestamps_ns = timestamps_ns or {}
    doc = {
        "format": SIDECAR_FORMAT,
        "version": SIDECAR_VERSION,
        "keyframes": [
            {
                "id": int(k),
                "T_WC": torch.as_tensor(T, dtype=torch.float64).cpu().tolist(),
                "timestamp_ns": None if k not in timestamps_ns else int(timestamps_ns[k]),
            }
            for k, T in sorted(keyframes.items())
        ],
        "camera": camera,
        "extra": extra or {},
    }
    side = sidecar_path(path)
    side.write_text(json.dumps(doc, indent=1))
    return side


def load_map(path: str | Path, dtype: torch.dtype = torch.float32) -> tuple[GaussianMap, dict]:
    """Read a map written by :func:`save_map`: ``(gaussians, sidecar)`` where ``sidecar["keyframes"]`` maps
    keyframe id to ``{"T_WC": (4, 4) float64 tensor, "timestamp_ns": int | None}``."""
    gmap = load_ply(path, dtype)
    side = sidecar_path(path)
    doc = json.loads(side.read_text())
    if doc.get("format") != SIDECAR_FORMAT:
        raise ValueError(f"{side}: not a {SIDECAR_FORMAT} sidecar (format={doc.get('format')!r})")
    doc["keyframes"] = {
        int(k["id"]): {"T_WC": torch.tensor(k["T_WC"], dtype=torch.float64), "timestamp_ns": k["timestamp_ns"]}
        for k in doc["keyframes"]
    }
    return gmap, doc
