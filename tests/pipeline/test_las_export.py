"""LAS export of files other tools wrote: COPC tiles and GeoTIFF CRS keys."""

import importlib.metadata
import struct

import laspy
import numpy as np
import pyproj
import pytest
from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr
from laspy.vlrs.vlrlist import VLRList

from pipeline.errors import InputError
from pipeline.io import ExtraDim, export_with_extra_dims, read_info
from pipeline.io.crs import check_same_crs

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


# -- CRS: point formats 6-10 carry one WKT record, never GeoTIFF keys ----------------------


def _geokeys(*keys):
    """A GeoKeyDirectoryVlr holding (key id, value) pairs."""
    vlr = GeoKeyDirectoryVlr()
    vlr.geo_keys_header.key_directory_version = 1
    vlr.geo_keys_header.key_revision = 1
    vlr.geo_keys_header.number_of_keys = len(keys)
    vlr.geo_keys = [GeoKeyEntryStruct(key, 0, 1, value) for key, value in keys]
    return vlr


def _keyed_tile(path, *keys, version="1.4", point_format=6, n=200):
    header = laspy.LasHeader(version=version, point_format=point_format)
    header.scales, header.offsets = [0.01] * 3, [500_000.0, 4_000_000.0, 0.0]
    header.vlrs.append(_geokeys(*keys))
    las = laspy.LasData(header)
    rng = np.random.default_rng(1)
    las.x = rng.uniform(500_000, 500_100, n)
    las.y = rng.uniform(4_000_000, 4_000_100, n)
    las.z = rng.uniform(0, 30, n)
    las.write(path)
    return path


def _crs_records(path):
    with laspy.open(path) as reader:
        header = reader.header
        records = [*header.vlrs, *(header.evlrs or [])]
        return header, records


@pytest.mark.parametrize("version, point_format", [("1.4", 6), ("1.2", 1), ("1.2", 3)])
def test_geotiff_keys_become_one_wkt_record(tmp_path, version, point_format):
    src = _keyed_tile(tmp_path / "keys.las", (3072, 32610), version=version,
                      point_format=point_format)
    dst = export_with_extra_dims(src, tmp_path / "out.laz", DIMS, _confidence)
    header, records = _crs_records(dst)
    assert header.point_format.id >= 6 and header.global_encoding.wkt
    assert not [v for v in records if isinstance(v, GeoKeyDirectoryVlr)]
    wkts = [v for v in records if isinstance(v, WktCoordinateSystemVlr)]
    assert len(wkts) == 1
    assert pyproj.CRS.from_wkt(wkts[0].string.rstrip("\0")).to_epsg() == 32610
    assert read_info(dst).crs_wkt == read_info(src).crs_wkt


def test_vertical_geotiff_key_gives_a_compound_crs(tmp_path):
    src = _keyed_tile(tmp_path / "keys.las", (3072, 32610), (4096, 5703), version="1.2",
                      point_format=1)
    crs = pyproj.CRS.from_wkt(read_info(src).crs_wkt)
    assert crs.is_compound
    assert [c.to_epsg() for c in crs.sub_crs_list] == [32610, 5703]


def test_user_defined_geotiff_keys_are_one_clear_error(tmp_path):
    src = _keyed_tile(tmp_path / "custom.las", (3072, 32767), version="1.2", point_format=1)
    with pytest.raises(InputError, match=r"GeoTIFF CRS keys of .*custom\.las.*EPSG"):
        read_info(src)


def test_pyproj_is_a_dependency():
    """Converting GeoTIFF keys must not depend on an optional install."""
    requirements = [r.split(";")[0] for r in importlib.metadata.requires("silva")]
    assert any(r.replace(" ", "").startswith("pyproj") for r in requirements)


def test_tiles_of_different_crss_are_refused_naming_both():
    utm10, utm11 = (pyproj.CRS.from_epsg(c).to_wkt() for c in (32610, 32611))
    tiles = [("a.laz", utm10), ("b.laz", None), ("c.laz", utm11)]
    with pytest.raises(InputError) as err:
        check_same_crs(tiles, "data.train")
    message = str(err.value)
    assert "a.laz (EPSG:32610) and c.laz (EPSG:32611) of data.train" in message
    assert "\n" not in message


def test_the_same_crs_in_two_wkt_versions_is_one_crs():
    crs = pyproj.CRS.from_epsg(32610)
    tiles = [("a.laz", crs.to_wkt("WKT1_GDAL")), ("b.laz", crs.to_wkt("WKT2_2019")),
             ("c.laz", None)]
    assert check_same_crs(tiles, "data.test") == tiles[0][1]
    assert check_same_crs([("a.laz", None)], "data.test") is None


@pytest.mark.data
def test_topography_tile_gets_a_wkt_crs(shared_data, tmp_path):
    src = shared_data / "als" / "Topography.laz"
    if not src.is_file():
        pytest.skip(f"{src} not found")
    dst = export_with_extra_dims(src, tmp_path / "topo.laz", DIMS, _confidence)
    header, records = _crs_records(dst)
    assert str(header.version) == "1.4" and header.global_encoding.wkt
    assert not [v for v in records if isinstance(v, GeoKeyDirectoryVlr)]
    assert header.parse_crs().to_epsg() == 2949  # NAD83(CSRS) / MTM zone 7, as its keys say
    assert header.point_count == read_info(src).n_points


# -- keep_point_format: the input's version and point format -------------------------------


def _legacy_tile(path, version="1.2", point_format=3, n=300):
    """A LAS tile of a legacy point format with GeoTIFF keys and varied dimension values."""
    path = _keyed_tile(path, (3072, 32610), version=version, point_format=point_format, n=n)
    las = laspy.read(path)
    rng = np.random.default_rng(2)
    las.classification = rng.integers(0, 32, n).astype(np.uint8)
    las.intensity = rng.integers(0, 65535, n).astype(np.uint16)
    if point_format < 6:
        las.scan_angle_rank = rng.integers(-90, 90, n).astype(np.int8)
    las.withheld = rng.integers(0, 2, n).astype(np.uint8)
    las.write(path)
    return path


@pytest.mark.parametrize("version, point_format", [("1.2", 1), ("1.2", 3), ("1.4", 6)])
def test_keep_point_format_round_trips_every_dimension(tmp_path, version, point_format):
    src = _legacy_tile(tmp_path / "legacy.las", version, point_format)
    seen = {}

    def compute(batch):
        seen["withheld"] = batch.fields["withheld"]
        return _confidence(batch)

    dst = export_with_extra_dims(src, tmp_path / "kept.laz", DIMS, compute,
                                 keep_point_format=True)
    original, out = laspy.read(src), laspy.read(dst)
    assert str(out.header.version) == version and out.point_format.id == point_format
    for name in original.point_format.dimension_names:
        assert np.array_equal(np.asarray(out[name]), np.asarray(original[name])), name
    assert np.allclose(out["Confidence"], 0.5)
    assert np.array_equal(seen["withheld"], np.asarray(original.withheld).astype(bool))
    if point_format < 6:  # the GeoTIFF keys of a legacy format stay as they are
        assert [v for v in out.header.vlrs if isinstance(v, GeoKeyDirectoryVlr)]
    assert read_info(dst).crs_wkt == read_info(src).crs_wkt


def test_keep_point_format_refuses_a_class_its_format_cannot_hold(tmp_path):
    src = _legacy_tile(tmp_path / "legacy.las", "1.2", 1)

    def compute(batch):
        return {**_confidence(batch), "classification": np.full(len(batch), 64, np.uint8)}

    dst = tmp_path / "kept.las"
    with pytest.raises(InputError, match=r"'classification'.*0\.\.31"):
        export_with_extra_dims(src, dst, DIMS, compute, set_classification=True,
                               keep_point_format=True)
    assert not dst.exists()
    # without keep, the same values go to a LAS 1.4 point format that holds them
    auto = export_with_extra_dims(src, dst, DIMS, compute, set_classification=True)
    out = laspy.read(auto)
    assert out.point_format.id == 6 and np.all(out.classification == 64)
