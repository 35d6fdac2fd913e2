"""LAS export of files other tools wrote: COPC tiles and GeoTIFF CRS keys."""

import struct

import laspy
import numpy as np
import pytest
from laspy.vlrs.known import WktCoordinateSystemVlr
from laspy.vlrs.vlrlist import VLRList

from pipeline.io import ExtraDim, export_with_extra_dims, read_info, write_las

DIMS = [ExtraDim("Confidence", "float32", "probability of the class")]


def _confidence(batch):
    return {"Confidence": np.full(len(batch), 0.5, np.float32)}


def _copc_tile(path, n=500):
    """A LAZ 1.4 tile that carries a COPC info VLR and a COPC hierarchy EVLR."""
    rng = np.random.default_rng(0)
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales, header.offsets = [0.01] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.x, las.y, las.z = (rng.uniform(0, 50, n) for _ in range(3))
    las.classification = rng.integers(1, 6, n).astype(np.uint8)
    info = struct.pack("<5d2Q2d", 25.0, 25.0, 25.0, 25.0, 1.0, 0, 32, 0.0, 0.0) + bytes(88)
    las.vlrs.append(laspy.VLR("copc", 1, "copc info", info))
    las.evlrs = VLRList([laspy.VLR("copc", 1000, "EPT hierarchy", bytes(32))])
    las.write(path)
    return las


def test_copc_tile_exports_without_its_copc_records(tmp_path):
    src = tmp_path / "tile.copc.laz"
    original = _copc_tile(src)
    with laspy.open(src) as reader:  # the fixture really is COPC-flavoured
        ids = {(v.user_id, v.record_id) for v in [*reader.header.vlrs, *reader.header.evlrs]}
    assert {("copc", 1), ("copc", 1000)} <= ids
    dst = export_with_extra_dims(src, tmp_path / "out.laz", DIMS, _confidence)
    out = laspy.read(dst)
    records = [*out.header.vlrs, *(out.header.evlrs or [])]
    assert not [v for v in records if v.user_id.lower() == "copc"]
    assert np.array_equal(out.classification, original.classification)
    assert np.array_equal(out.X, original.X)
    assert np.allclose(out["Confidence"], 0.5)
