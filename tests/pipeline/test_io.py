"""LAS/LAZ/Oakland I/O: streamed reads, round-trips, exports, and one-line errors on bad input."""

import sys
import types

import laspy
import numpy as np
import pytest
from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, WktCoordinateSystemVlr
from laspy.vlrs.vlrlist import VLRList

from pipeline.errors import ConfigError, InputError, MissingFileError
from pipeline.io import (
    OAKLAND_CLASSES,
    ExtraDim,
    export_with_extra_dims,
    iter_points,
    map_labels,
    read_info,
    read_oakland,
    read_points,
    reads_ranges,
    write_las,
)

WKT = (
    'PROJCS["WGS 84 / UTM zone 10N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
    '6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
    'PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",-123],'
    'PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],'
    'PARAMETER["false_northing",0],UNIT["metre",1],AUTHORITY["EPSG","32610"]]'
)
EXTRA = [
    ExtraDim("Confidence", "float32", "probability of the class"),
    ExtraDim("Height", "float64", "height above ground"),
    ExtraDim("Segment", "uint32", "segment id"),
    ExtraDim("Offset16", "int16", ""),
    ExtraDim("Flag", "uint8", "a flag"),
]
SCALE = 0.001


def _points(n, seed=0):
    """Random UTM-like points with standard fields and values for every dim of EXTRA."""
    rng = np.random.default_rng(seed)
    xyz = np.column_stack([
        rng.uniform(500_123.0, 500_223.0, n),
        rng.uniform(4_180_456.0, 4_180_556.0, n),
        rng.uniform(-3.0, 40.0, n),
    ])
    fields = {
        "classification": rng.integers(0, 256, n).astype(np.uint8),
        "intensity": rng.integers(0, 65536, n).astype(np.uint16),
        "return_number": rng.integers(1, 16, n).astype(np.uint8),
        "number_of_returns": rng.integers(1, 16, n).astype(np.uint8),
        "gps_time": rng.uniform(0, 1e6, n),
        "user_data": rng.integers(0, 256, n).astype(np.uint8),
        "point_source_id": rng.integers(0, 65536, n).astype(np.uint16),
        "scan_angle": rng.integers(-15000, 15001, n).astype(np.int16),
        "Confidence": rng.random(n).astype(np.float32),
        "Height": rng.normal(0, 10, n),
        "Segment": rng.integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32),
        "Offset16": rng.integers(-32768, 32768, n).astype(np.int16),
        "Flag": rng.integers(0, 256, n).astype(np.uint8),
    }
    return xyz, fields


@pytest.fixture(params=["las", "laz"])
def suffix(request):
    return "." + request.param


@pytest.fixture
def tile(tmp_path, suffix):
    """A LAS 1.4 / format 7 tile (with colour) of 2,500 points, its xyz and its fields."""
    xyz, fields = _points(2_500)
    rng = np.random.default_rng(1)
    for colour in ("red", "green", "blue"):
        fields[colour] = rng.integers(0, 65536, len(xyz)).astype(np.uint16)
    path = write_las(tmp_path / f"tile{suffix}", xyz, fields=fields, extra_dims=EXTRA,
                     crs_wkt=WKT, point_format=7)
    return path, xyz, fields


def _write_oakland(path, rows, header=True):
    lines = ["#File format: x y z label_id confidence", "#  1300 -- foliage"] if header else []
    lines += [" ".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _oakland_rows(n, seed=0, codes=(1004, 1101, 1200, 1300, 1400, 1501)):
    rng = np.random.default_rng(seed)
    xyz = np.round(rng.uniform(100, 300, (n, 3)), 2)
    labels = rng.choice(codes, n)
    conf = rng.integers(0, 3, n)
    return [(x, y, z, int(c), int(f)) for (x, y, z), c, f in zip(xyz, labels, conf)]


def _one_line(exc):
    message = str(exc.value)
    assert "\n" not in message
    return message


# ----------------------------------------------------------------------------- reading


@pytest.mark.parametrize("batch_size", [1, 7, 999, 2_500, 10_000])
def test_chunked_read_equals_full_read(tile, batch_size):
    path, _, _ = tile
    fields = ("classification", "intensity", "Confidence", "Segment")
    full = read_points(path, fields=fields)
    batches = list(iter_points(path, batch_size=batch_size, fields=fields))
    assert [b.start for b in batches] == list(range(0, 2_500, batch_size))
    assert all(len(b) <= batch_size for b in batches)
    assert np.array_equal(np.concatenate([b.xyz for b in batches]), full.xyz)
    for name in fields:
        chunked = np.concatenate([b.fields[name] for b in batches])
        assert chunked.dtype == full.fields[name].dtype
        assert np.array_equal(chunked, full.fields[name])


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_range_of_points_equals_the_slice_of_the_whole(tmp_path, suffix):
    # 120,000 points: a LAZ file of compressed chunks of 50,000, entered in the middle of one
    xyz, fields = _points(120_000)
    path = write_las(tmp_path / f"big{suffix}", xyz, fields=fields, extra_dims=EXTRA)
    names = ("classification", "gps_time", "Segment")
    full = read_points(path, fields=names)
    for start, stop in ((0, 7), (49_999, 100_001), (73_000, 120_000), (5, 5)):
        batches = list(iter_points(path, batch_size=20_000, fields=names, start=start,
                                   stop=stop))
        assert [b.start for b in batches] == list(range(start, stop, 20_000))
        rows = slice(start, stop)
        got = np.concatenate([b.xyz for b in batches]) if batches else np.empty((0, 3))
        assert np.array_equal(got, full.xyz[rows])
        for name in names:
            values = [b.fields[name] for b in batches]
            assert np.array_equal(np.concatenate(values) if values else [],
                                  full.fields[name][rows])
    assert reads_ranges(path)
    with pytest.raises(ValueError, match="are not a range of the 120000 points"):
        iter_points(path, start=100, stop=120_001)


def test_a_format_read_whole_refuses_a_range(tmp_path):
    path = _write_oakland(tmp_path / "a.xyz_label_conf", _oakland_rows(50))
    assert not reads_ranges(path)
    with pytest.raises(ValueError, match="read whole, not by point ranges"):
        iter_points(path, start=10, stop=20)


def test_fields_match_case_and_underscores(tile):
    path, _, fields = tile
    batch = read_points(path, fields=("Classification", "GpsTime"))
    assert np.array_equal(batch.fields["Classification"], fields["classification"])
    assert np.array_equal(batch.fields["GpsTime"], fields["gps_time"])


# ----------------------------------------------------------------------------- writing


def test_write_then_read_round_trips_every_dimension(tile, suffix):
    path, xyz, fields = tile
    batch = read_points(path, fields=tuple(fields))
    assert batch.start == 0 and batch.xyz.dtype == np.float64
    assert np.abs(batch.xyz - xyz).max() <= SCALE / 2 + 1e-9
    for name, values in fields.items():
        assert np.array_equal(batch.fields[name], values), name
    info = read_info(path)
    assert info.format == suffix[1:]
    assert info.n_points == len(xyz)
    assert info.version == "1.4" and info.point_format == 7
    assert info.crs_wkt == WKT
    assert info.scale == (SCALE,) * 3
    assert info.offset == (500_000.0, 4_180_000.0, -1_000.0)  # minimum floored to 1000s
    assert np.allclose(info.mins, xyz.min(axis=0), atol=SCALE)
    assert np.allclose(info.maxs, xyz.max(axis=0), atol=SCALE)
    assert set(fields) <= set(info.dimensions)
    with laspy.open(path) as reader:
        header = reader.header
        assert header.global_encoding.wkt
        stored = {d.name: d for d in header.point_format.extra_dimensions}
    assert list(stored) == [d.name for d in EXTRA]
    for dim in EXTRA:
        assert np.dtype(stored[dim.name].dtype) == np.dtype(dim.dtype)
        assert stored[dim.name].description == dim.description
        assert batch.fields[dim.name].dtype == np.dtype(dim.dtype)


def test_write_refuses_values_that_do_not_fit(tmp_path):
    xyz = np.zeros((3, 3))
    with pytest.raises(InputError, match="classification"):
        write_las(tmp_path / "a.las", xyz, fields={"classification": np.array([1, 2, 300])})
    with pytest.raises(InputError, match="return_number"):
        write_las(tmp_path / "a.las", xyz, fields={"return_number": np.array([1, 2, 16])})
    with pytest.raises(InputError, match="Undeclared"):
        write_las(tmp_path / "a.las", xyz, fields={"Undeclared": np.ones(3)})
    with pytest.raises(InputError, match="do not fit"):
        write_las(tmp_path / "a.las", xyz + [[0, 0, 0], [0, 0, 0], [1e7, 0, 0]])
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- export


def _read_all(path):
    with laspy.open(path) as reader:
        return reader.header, reader.read_points(-1)


def test_export_keeps_points_dimensions_order_and_crs(tile, tmp_path):
    src, xyz, _ = tile
    added = [ExtraDim("Predicted", "uint8", "predicted class"),
             ExtraDim("Index", "uint32", "index in tile")]
    starts = []

    def compute(batch):
        starts.append(batch.start)
        assert batch.xyz.shape == (len(batch), 3)
        return {"Predicted": (batch.xyz[:, 2] > 10).astype(np.uint8),
                "Index": batch.start + np.arange(len(batch))}

    dst = export_with_extra_dims(src, tmp_path / "out" / "classified.laz", added, compute,
                                 batch_size=333)
    assert starts == list(range(0, 2_500, 333))
    src_header, before = _read_all(src)
    header, after = _read_all(dst)
    assert header.are_points_compressed and str(header.version) == "1.4"
    assert header.point_format.id == src_header.point_format.id
    assert len(after) == len(before)
    for name in src_header.point_format.dimension_names:
        assert np.array_equal(np.asarray(after[name]), np.asarray(before[name])), name
    assert np.array_equal(np.asarray(after["Index"]), np.arange(len(before)))
    z = np.asarray(before["Z"]) * src_header.scales[2] + src_header.offsets[2]
    assert np.array_equal(np.asarray(after["Predicted"]), (z > 10).astype(np.uint8))
    assert read_info(dst).crs_wkt == WKT
    assert [d.description for d in header.point_format.extra_dimensions][-2:] == [
        "predicted class", "index in tile"]
    assert sorted(p.name for p in dst.parent.iterdir()) == ["classified.laz"]


def test_export_keeps_a_crs_stored_as_evlr(tmp_path):
    las = laspy.LasData(laspy.LasHeader(version="1.4", point_format=6))
    las.x, las.y, las.z = np.arange(10.0), np.zeros(10), np.zeros(10)
    las.evlrs = VLRList([WktCoordinateSystemVlr(WKT)])
    las.header.global_encoding.wkt = True
    src = tmp_path / "evlr.las"
    las.write(src)
    assert read_info(src).crs_wkt == WKT
    dst = export_with_extra_dims(src, tmp_path / "out.laz", [ExtraDim("A", "uint8")],
                                 lambda b: {"A": np.ones(len(b), np.uint8)})
    assert read_info(dst).crs_wkt == WKT
    assert np.array_equal(read_points(dst).xyz[:, 0], np.arange(10.0))


def _legacy_tile(path, n=1_000):
    """A LAS 1.2 / point format 3 tile with a GeoTIFF CRS key and random values."""
    rng = np.random.default_rng(3)
    header = laspy.LasHeader(version="1.2", point_format=3)
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([600_000.0, 5_000_000.0, 0.0])
    geokeys = GeoKeyDirectoryVlr()
    geokeys.geo_keys_header.key_directory_version = 1
    geokeys.geo_keys_header.key_revision = 1
    geokeys.geo_keys_header.number_of_keys = 1
    geokeys.geo_keys = [GeoKeyEntryStruct(3072, 0, 1, 32610)]  # ProjectedCSType = EPSG:32610
    header.vlrs.append(geokeys)
    points = laspy.ScaleAwarePointRecord.zeros(n, header=header)
    for name in "XYZ":
        points[name] = rng.integers(0, 100_000, n)
    values = {
        "intensity": rng.integers(0, 65536, n), "return_number": rng.integers(1, 8, n),
        "number_of_returns": rng.integers(1, 8, n), "scan_direction_flag": rng.integers(0, 2, n),
        "edge_of_flight_line": rng.integers(0, 2, n), "classification": rng.integers(0, 32, n),
        "synthetic": rng.integers(0, 2, n), "key_point": rng.integers(0, 2, n),
        "withheld": rng.integers(0, 2, n), "scan_angle_rank": rng.integers(-90, 91, n),
        "user_data": rng.integers(0, 256, n), "point_source_id": rng.integers(0, 65536, n),
        "gps_time": rng.uniform(0, 1e5, n), "red": rng.integers(0, 65536, n),
        "green": rng.integers(0, 65536, n), "blue": rng.integers(0, 65536, n),
    }
    for name, array in values.items():
        points[name] = array
    with laspy.open(path, mode="w", header=header) as writer:
        writer.write_points(points)
    return path, geokeys.record_data_bytes()


def test_export_converts_legacy_format_keeping_every_value(tmp_path):
    src, _ = _legacy_tile(tmp_path / "legacy.las")
    added = [ExtraDim("Score", "float32", "score")]
    dst = export_with_extra_dims(
        src, tmp_path / "out.las", added,
        lambda b: {"Score": b.xyz[:, 0].astype(np.float32)}, batch_size=300)
    src_header, before = _read_all(src)
    header, after = _read_all(dst)
    assert str(header.version) == "1.4" and header.point_format.id == 7
    assert len(after) == len(before)
    for name in src_header.point_format.dimension_names:
        if name == "scan_angle_rank":
            continue
        assert np.array_equal(np.asarray(after[name]), np.asarray(before[name])), name
    degrees = np.asarray(before["scan_angle_rank"], dtype=float)
    assert np.array_equal(np.asarray(after["scan_angle"]), np.round(degrees / 0.006))
    assert np.array_equal(np.round(np.asarray(after["scan_angle"]) * 0.006), degrees)
    x = np.asarray(before["X"]) * 0.01 + 600_000.0
    assert np.array_equal(np.asarray(after["Score"]), x.astype(np.float32))
    # point format 7 holds its CRS as WKT: the GeoTIFF key became the same CRS in WKT
    assert not [v for v in header.vlrs if isinstance(v, GeoKeyDirectoryVlr)]
    assert header.global_encoding.wkt and header.parse_crs().to_epsg() == 32610


def test_export_set_classification_replaces_only_the_class(tile, tmp_path):
    src, _, fields = tile
    added = [ExtraDim("Original", "uint8", "input class")]

    def compute(batch):
        old = batch.fields["classification"]
        return {"Original": old, "classification": 255 - old}

    dst = export_with_extra_dims(src, tmp_path / "c.las", added, compute,
                                 batch_size=1_000, set_classification=True)
    out = read_points(dst, fields=("classification", "Original", "intensity", "Segment"))
    assert np.array_equal(out.fields["classification"], 255 - fields["classification"])
    assert np.array_equal(out.fields["Original"], fields["classification"])
    assert np.array_equal(out.fields["intensity"], fields["intensity"])
    assert np.array_equal(out.fields["Segment"], fields["Segment"])


def test_export_from_oakland_text(tmp_path):
    rows = _oakland_rows(700)
    src = _write_oakland(tmp_path / "scene.xyz_label_conf", rows)
    added = [ExtraDim("Prediction", "uint16", "predicted code")]
    dst = export_with_extra_dims(src, tmp_path / "scene.laz", added,
                                 lambda b: {"Prediction": b.fields["label"]}, batch_size=128)
    table = np.array(rows, dtype=float)
    out = read_points(dst, fields=("classification", "label", "confidence", "Prediction"))
    assert len(out) == len(rows)
    assert np.abs(out.xyz - table[:, :3]).max() <= SCALE / 2 + 1e-9
    assert np.array_equal(out.fields["label"], table[:, 3])  # codes > 255: extra dim
    assert out.fields["label"].dtype == np.uint16
    assert not out.fields["classification"].any()
    assert np.array_equal(out.fields["confidence"], table[:, 4].astype(np.float32))
    assert np.array_equal(out.fields["Prediction"], table[:, 3])


def test_export_from_oakland_with_small_codes_uses_classification(tmp_path):
    rows = _oakland_rows(50, codes=(2, 5, 6))
    src = _write_oakland(tmp_path / "small.txt", rows)
    dst = export_with_extra_dims(src, tmp_path / "small.las", [], lambda b: {})
    info = read_info(dst)
    assert "label" not in info.dimensions and "confidence" in info.dimensions
    out = read_points(dst)
    assert np.array_equal(out.fields["classification"], [r[3] for r in rows])


def test_interrupted_export_leaves_no_file(tile, tmp_path):
    src, _, _ = tile
    outdir = tmp_path / "out"
    outdir.mkdir()
    calls = []

    def compute(batch):
        calls.append(batch.start)
        if len(calls) == 3:
            raise RuntimeError("worker lost")
        return {"Flag2": np.zeros(len(batch), np.uint8)}

    with pytest.raises(RuntimeError, match="worker lost"):
        export_with_extra_dims(src, outdir / "x.laz", [ExtraDim("Flag2", "uint8")], compute,
                               batch_size=500)
    assert len(calls) == 3
    assert list(outdir.iterdir()) == []
    # values that do not fit the declared dtype stop the export the same way
    with pytest.raises(InputError, match="Flag2"):
        export_with_extra_dims(src, outdir / "x.las", [ExtraDim("Flag2", "uint8")],
                               lambda b: {"Flag2": np.full(len(b), 300)}, batch_size=500)
    with pytest.raises(InputError, match="Typo"):
        export_with_extra_dims(src, outdir / "x.las", [ExtraDim("Flag2", "uint8")],
                               lambda b: {"Typo": np.zeros(len(b))}, batch_size=500)
    assert list(outdir.iterdir()) == []


def test_interrupted_export_keeps_previous_output(tile, tmp_path):
    src, _, _ = tile
    dst = tmp_path / "previous.las"
    dst.write_bytes(b"previous result")

    def compute(batch):
        raise RuntimeError("stop")

    with pytest.raises(RuntimeError):
        export_with_extra_dims(src, dst, [], compute)
    assert dst.read_bytes() == b"previous result"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([src.name, dst.name])


# ----------------------------------------------------------------------------- Oakland


@pytest.mark.data
def test_oakland_validation_scene_has_the_official_size(shared_data):
    path = shared_data / "oakland" / "oakland_part3_am.xyz_label_conf"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    scene = read_oakland(path)
    assert scene.fields["label"].dtype == np.int32
    assert len(scene.fields["confidence"]) == len(scene)
    classes = map_labels(scene.fields["label"], OAKLAND_CLASSES)
    kept = classes[classes >= 0]
    assert len(kept) == 91_515
    assert np.bincount(kept, minlength=5).min() > 0
    assert read_info(path).n_points == len(scene)


def test_oakland_round_trip_and_chunks(tmp_path):
    rows = _oakland_rows(1_000, seed=4)
    path = _write_oakland(tmp_path / "part.xyz_label_conf", rows)
    table = np.array(rows, dtype=float)
    scene = read_oakland(path)
    assert np.array_equal(scene.xyz, table[:, :3])
    assert np.array_equal(scene.fields["label"], table[:, 3].astype(np.int32))
    assert np.array_equal(scene.fields["confidence"], table[:, 4].astype(np.float32))
    batches = list(iter_points(path, batch_size=300, fields=("label",)))
    assert [b.start for b in batches] == [0, 300, 600, 900]
    assert np.array_equal(np.concatenate([b.xyz for b in batches]), scene.xyz)
    assert np.array_equal(np.concatenate([b.fields["label"] for b in batches]),
                          scene.fields["label"])
    info = read_info(path)
    assert info.format == "oakland" and info.n_points == 1_000
    assert info.mins == tuple(table[:, :3].min(axis=0))
    assert info.maxs == tuple(table[:, :3].max(axis=0))


def test_map_labels():
    raw = np.array([[1300, 1101, 7], [1401, 1103, 1202]])
    assert map_labels(raw, OAKLAND_CLASSES).tolist() == [[0, 1, -1], [4, 2, 3]]
    assert map_labels(raw, OAKLAND_CLASSES).dtype == np.int16
    assert map_labels(raw, {"b": [7], "a": [1300, 1401]}).tolist() == [[1, -1, 0], [1, -1, -1]]
    with pytest.raises(ConfigError, match="1300"):
        map_labels(raw, {"a": [1300], "b": [1300]})


# ----------------------------------------------------------------------------- bad input


def test_missing_file(tmp_path):
    path = tmp_path / "absent.laz"
    for call in (read_info, read_points, lambda p: iter_points(p),
                 lambda p: export_with_extra_dims(p, tmp_path / "o.las", [], dict)):
        with pytest.raises(MissingFileError) as exc:
            call(path)
        assert str(path) in _one_line(exc)


@pytest.mark.parametrize("name", ["random.las", "random.laz"])
def test_random_bytes(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(InputError) as exc:
        read_points(path)
    assert _one_line(exc).startswith(f"cannot read {path}: ")


def test_truncated_files(tile, tmp_path):
    path, _, _ = tile
    data = path.read_bytes()
    cut = tmp_path / f"cut{path.suffix}"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError) as exc:
        read_points(cut)
    assert _one_line(exc).startswith(f"cannot read {cut}: ")
    with pytest.raises(InputError):
        export_with_extra_dims(cut, tmp_path / "o.las", [], dict)
    assert not (tmp_path / "o.las").exists()


def test_las_cut_at_a_point_boundary(tmp_path):
    path = write_las(tmp_path / "whole.las", np.random.default_rng(0).random((100, 3)))
    with laspy.open(path) as reader:
        keep = reader.header.offset_to_point_data + 60 * reader.header.point_format.size
    cut = tmp_path / "cut.las"
    cut.write_bytes(path.read_bytes()[:keep])
    for call in (read_info, read_points):
        with pytest.raises(InputError, match="truncated") as exc:
            call(cut)
        assert str(cut) in _one_line(exc)


def _announce(src, dst, n):
    """A copy of ``src`` whose header announces ``n`` points (legacy and LAS 1.4 counts)."""
    data = bytearray(src.read_bytes())
    with laspy.open(src) as reader:
        version = reader.header.version
    data[107:111] = np.uint32(n).tobytes()  # legacy number of point records
    if version.minor >= 4:
        data[247:255] = np.uint64(n).tobytes()  # LAS 1.4 number of point records
    dst.write_bytes(bytes(data))
    return dst


@pytest.mark.parametrize("version, point_format", [("1.2", 3), ("1.4", 6)])
def test_las_holding_more_points_than_its_header_announces(tmp_path, version, point_format):
    las = laspy.LasData(laspy.LasHeader(version=version, point_format=point_format))
    las.x, las.y, las.z = np.arange(100.0), np.zeros(100), np.zeros(100)
    whole = tmp_path / "whole.las"
    las.write(whole)
    assert read_info(whole).n_points == 100
    short = _announce(whole, tmp_path / "plot.v1.las", 60)
    for call in (read_info, read_points, lambda p: iter_points(p, 10)):
        with pytest.raises(InputError) as exc:
            call(short)
        message = _one_line(exc)
        assert message.startswith(f"cannot read {short}: its header announces 60 points "
                                  "but the file holds 100;"), message
        assert "lasinfo -i" in message
    with pytest.raises(InputError, match="announces 60 points"):
        export_with_extra_dims(short, tmp_path / "o.las", [], dict)


def test_records_after_the_points_are_not_counted_as_points(tmp_path):
    """Extended VLRs follow the point data of LAS 1.4: they are no extra points."""
    las = laspy.LasData(laspy.LasHeader(version="1.4", point_format=6))
    las.x, las.y, las.z = np.arange(50.0), np.zeros(50), np.zeros(50)
    las.evlrs = VLRList([WktCoordinateSystemVlr(WKT * 4)])  # longer than a point record
    src = tmp_path / "evlr.las"
    las.write(src)
    assert read_info(src).n_points == 50 and len(read_points(src).xyz) == 50


def test_laz_holding_more_chunks_than_its_header_announces(tmp_path):
    n = 120_000  # three chunks of laszip's default 50,000 points
    las = laspy.LasData(laspy.LasHeader(version="1.4", point_format=6))
    las.x, las.y, las.z = np.arange(n) * 0.001, np.zeros(n), np.zeros(n)
    whole = tmp_path / "whole.laz"
    las.write(whole)
    assert read_info(whole).n_points == n
    short = _announce(whole, tmp_path / "short.laz", 60_000)
    with pytest.raises(InputError) as exc:
        read_info(short)
    assert _one_line(exc).startswith(f"cannot read {short}: its header announces 60000 "
                                     "points but the file holds at least 100001;")
    # within the last chunk a shortfall cannot be seen without decoding: read as announced
    assert len(read_points(_announce(whole, tmp_path / "last.laz", 110_000)).xyz) == 110_000


def test_empty_tiles(tmp_path):
    las = write_las(tmp_path / "empty.las", np.zeros((0, 3)))
    assert read_info(las).n_points == 0
    text = _write_oakland(tmp_path / "empty.xyz_label_conf", [])
    for path in (las, text):
        with pytest.raises(InputError, match="no points") as exc:
            read_points(path, fields=())
        assert str(path) in _one_line(exc)
        with pytest.raises(InputError, match="no points"):
            export_with_extra_dims(path, tmp_path / "o.las", [], dict)


def test_nan_coordinates(tmp_path):
    rows = _oakland_rows(20)
    rows[3] = ("nan",) + rows[3][1:]
    rows[17] = rows[17][:2] + ("inf",) + rows[17][3:]
    path = _write_oakland(tmp_path / "nan.xyz_label_conf", rows)
    for call in (read_oakland, read_info, lambda p: list(iter_points(p, 5, fields=()))):
        with pytest.raises(InputError, match="2 points with NaN") as exc:
            call(path)
        assert str(path) in _one_line(exc)


def test_oakland_bad_lines(tmp_path):
    rows = _oakland_rows(10)
    short = _write_oakland(tmp_path / "short.xyz_label_conf", rows[:4] + [rows[4][:4]] + rows[5:])
    with pytest.raises(InputError, match="line 7 has 4 columns") as exc:  # after 2 comments
        read_oakland(short)
    assert str(short) in _one_line(exc)
    word = _write_oakland(tmp_path / "word.txt", rows[:2] + [("1", "2", "x", "1300", "2")])
    with pytest.raises(InputError, match="line 5"):
        read_info(word)
    fraction = _write_oakland(tmp_path / "frac.txt", rows[:1] + [(1, 2, 3, 1300.5, 2)])
    with pytest.raises(InputError, match="line 4 has label"):
        read_oakland(fraction)
    binary = tmp_path / "binary.txt"
    binary.write_bytes(b"\xff\xfe\x00\x81" * 50)
    with pytest.raises(InputError, match="not a text file"):
        read_oakland(binary)


def test_unknown_field_names_file_and_dimensions(tile, tmp_path):
    path, _, _ = tile
    with pytest.raises(InputError) as exc:
        iter_points(path, fields=("label",))
    message = _one_line(exc)
    assert "'label'" in message and str(path) in message and "classification" in message
    oakland = _write_oakland(tmp_path / "o.xyz_label_conf", _oakland_rows(3))
    with pytest.raises(InputError, match="'classification' not found .* label, confidence"):
        read_points(oakland)


def test_pdal_formats_need_pdal(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pdal", None)  # import pdal fails even where installed
    path = tmp_path / "scan.ply"
    path.write_bytes(b"ply\n")
    for call in (read_info, read_points):
        with pytest.raises(InputError) as exc:
            call(path)
        message = _one_line(exc)
        assert str(path) in message and ".las" in message and "PDAL" in message


def _fake_pdal(arrays, wkt="WKT"):
    """A stand-in for PDAL's Python bindings that reads the given structured arrays."""

    class Pipeline:
        streamable = True
        quickinfo = {"readers.ply": {
            "num_points": sum(len(a) for a in arrays),
            "bounds": {"minx": 0.0, "miny": 0.0, "minz": 0.0, "maxx": 1.0, "maxy": 1.0,
                       "maxz": 1.0},
            "srs": {"wkt": wkt},
            "dimensions": ", ".join(arrays[0].dtype.names),
        }}

        def iterator(self, chunk_size):
            data = np.concatenate(arrays)
            return (data[i:i + chunk_size] for i in range(0, len(data), chunk_size))

    module = types.ModuleType("pdal")
    module.Reader = lambda filename: types.SimpleNamespace(pipeline=Pipeline)
    return module


def test_pdal_formats_through_pdal(tmp_path, monkeypatch):
    dtype = [("X", "f8"), ("Y", "f8"), ("Z", "f8"), ("Classification", "u1")]
    data = np.zeros(10, dtype=dtype)
    data["X"] = np.arange(10)
    data["Classification"] = np.arange(10) % 3
    monkeypatch.setitem(sys.modules, "pdal", _fake_pdal([data]))
    path = tmp_path / "scan.ply"
    path.write_bytes(b"ply\n")
    info = read_info(path)
    assert info.format == "pdal" and info.n_points == 10 and info.crs_wkt == "WKT"
    batches = list(iter_points(path, batch_size=4))
    assert [b.start for b in batches] == [0, 4, 8]
    assert np.array_equal(np.concatenate([b.xyz[:, 0] for b in batches]), data["X"])
    assert np.array_equal(read_points(path).fields["classification"], data["Classification"])
    with pytest.raises(InputError, match="'label' not found"):
        iter_points(path, fields=("label",))
    data["Z"][[2, 5]] = np.nan
    with pytest.raises(InputError, match="2 points with NaN"):
        read_points(path)
    with pytest.raises(InputError, match="convert it to LAS"):
        export_with_extra_dims(path, tmp_path / "o.las", [], dict)
