"""PLY round trip in the standard 3DGS layout, readable by a generic PLY parser and by PlayCanvas splat-transform
(the PLY reader of the SuperSplat editor, from npm; installed by scripts/setup.sh), plus the sidecar."""
from __future__ import annotations

import csv
import json
import subprocess
from pathlib import Path

import numpy as np
import torch

from vigs_core.mapping.gaussians import GaussianMap
from vigs_core.mapping.ply import SH_C0, load_map, load_ply, save_map, save_ply

STANDARD = ("x y z nx ny nz f_dc_0 f_dc_1 f_dc_2".split() + [f"f_rest_{i}" for i in range(45)]
            + "opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3".split())
SPLAT_TRANSFORM = Path(__file__).resolve().parent.parent / "tools/splat_transform/node_modules/.bin/splat-transform"


def _random_map(n: int) -> GaussianMap:
    g = torch.Generator().manual_seed(0)
    return GaussianMap(
        means=torch.randn(n, 3, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3,
        quats=torch.randn(n, 4, generator=g),
        opacity_logits=torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        anchor_ids=torch.randint(0, 40, (n,), generator=g),
        ids=torch.arange(100, 100 + n),
    )


def _parse_header(raw: bytes) -> tuple[list[str], int]:
    """Header lines and the byte offset of the body, the way any PLY reader finds them."""
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    return raw[:end].decode("ascii").splitlines(), end


def test_ply_header_and_body_follow_the_3dgs_layout(tmp_path):
    gmap = _random_map(37)
    path = tmp_path / "map.ply"
    save_ply(path, gmap)
    raw = path.read_bytes()
    lines, body = _parse_header(raw)
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"] and lines[2].startswith("comment SH degree 3")
    assert lines[3] == "element vertex 37"
    assert lines[4:-2] == [f"property float {p}" for p in STANDARD]
    assert lines[-2:] == ["property int anchor_id", "end_header"]
    assert len(raw) - body == 37 * (len(STANDARD) * 4 + 4)
    # decode with a dtype built from the header alone
    types = {"float": "<f4", "int": "<i4"}
    dtype = np.dtype([(ln.split()[2], types[ln.split()[1]]) for ln in lines if ln.startswith("property")])
    rows = np.frombuffer(raw[body:], dtype=dtype)
    np.testing.assert_allclose(rows["x"], gmap.means[:, 0].numpy())
    np.testing.assert_allclose(rows["f_dc_1"], ((gmap.colors[:, 1] - 0.5) / SH_C0).numpy(), rtol=1e-6)
    np.testing.assert_allclose(rows["opacity"], gmap.opacity_logits.numpy())
    np.testing.assert_allclose(rows["scale_2"], gmap.log_scales[:, 2].numpy())
    q = gmap.quats / gmap.quats.norm(dim=-1, keepdim=True)   # unit, w first
    np.testing.assert_allclose(np.stack([rows[f"rot_{i}"] for i in range(4)], -1), q.numpy(), rtol=1e-6)
    assert np.all(rows["nx"] == 0) and all(np.all(rows[f"f_rest_{i}"] == 0) for i in range(45))
    np.testing.assert_array_equal(rows["anchor_id"], gmap.anchor_ids.numpy())


def test_ply_round_trip_and_sidecar(tmp_path):
    gmap = _random_map(25)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    poses = {3: torch.eye(4, dtype=torch.float64), 8: flip}
    poses[8][:3, 3] = torch.tensor([0.5, 1.0, -2.0])
    side = save_map(tmp_path / "map.ply", gmap, poses, {3: 123}, {"width": 10}, {"note": "x"})
    assert side == tmp_path / "map.json"
    back, doc = load_map(tmp_path / "map.ply")
    for name in ("means", "log_scales", "opacity_logits"):
        torch.testing.assert_close(getattr(back, name), getattr(gmap, name))
    torch.testing.assert_close(back.quats, gmap.quats / gmap.quats.norm(dim=-1, keepdim=True))
    torch.testing.assert_close(back.colors, gmap.colors, rtol=1e-6, atol=1e-6)
    assert torch.equal(back.anchor_ids, gmap.anchor_ids)
    assert sorted(doc["keyframes"]) == [3, 8]
    assert torch.equal(doc["keyframes"][8]["T_WC"], poses[8])
    assert doc["keyframes"][3]["timestamp_ns"] == 123 and doc["keyframes"][8]["timestamp_ns"] is None
    assert doc["camera"] == {"width": 10} and doc["extra"] == {"note": "x"}
    assert json.loads(side.read_text())["format"] == "vigs-gaussian-map"


def test_empty_map_round_trip(tmp_path):
    save_ply(tmp_path / "e.ply", GaussianMap.empty())
    assert len(load_ply(tmp_path / "e.ply")) == 0


def test_splat_transform_reads_the_map(tmp_path):
    """PlayCanvas splat-transform converts map.ply to CSV: it finds the Gaussians with degree-3 harmonics, the
    values we wrote, and carries our extra ``anchor_id`` along without tripping over it."""
    gmap = _random_map(9)
    save_ply(tmp_path / "map.ply", gmap)
    run = subprocess.run([str(SPLAT_TRANSFORM), str(tmp_path / "map.ply"), str(tmp_path / "map.csv")],
                         capture_output=True, text=True, timeout=120)
    log = run.stdout + run.stderr
    assert run.returncode == 0, log
    assert "9 gaussians" in log and "3 SH bands" in log, log
    with open(tmp_path / "map.csv") as f:
        rows = list(csv.DictReader(f))
    col = lambda name: np.array([float(r[name]) for r in rows])   # noqa: E731
    assert len(rows) == 9
    np.testing.assert_allclose(col("y"), gmap.means[:, 1].numpy(), rtol=1e-6)
    np.testing.assert_allclose(col("f_dc_2"), ((gmap.colors[:, 2] - 0.5) / SH_C0).numpy(), rtol=1e-5)
    q = np.stack([col(f"rot_{i}") for i in range(4)], -1)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(col("anchor_id"), gmap.anchor_ids.numpy())


def test_plyfile_reads_the_map(tmp_path):
    """The generic reader most Python 3DGS code uses (plyfile) sees one vertex element with the standard
    properties, ours after them."""
    from plyfile import PlyData

    gmap = _random_map(11)
    save_ply(tmp_path / "map.ply", gmap)
    vertex = PlyData.read(str(tmp_path / "map.ply"))["vertex"]
    assert vertex.count == 11
    assert [p.name for p in vertex.properties] == STANDARD + ["anchor_id"]
    np.testing.assert_allclose(vertex["scale_1"], gmap.log_scales[:, 1].numpy())
    np.testing.assert_array_equal(vertex["f_rest_44"], 0.0)
