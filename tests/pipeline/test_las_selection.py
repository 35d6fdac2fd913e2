"""Reading a few dimensions of a LAZ tile decompresses only their layers, and gives exactly
the values a full read gives."""

import laspy
import numpy as np
import pytest

from pipeline.io import iter_points, read_points
from pipeline.io.las import LAZ_LAYERS, decompression_selection, open_las

N = 5_000


def _random_tile(path, point_format: int) -> laspy.LasData:
    """A LAZ tile of ``point_format`` with random values in every dimension, an extra one
    included; returned as written."""
    rng = np.random.default_rng(point_format)
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.add_extra_dim(laspy.ExtraBytesParams(name="reflectance", type=np.float32))
    header.scales, header.offsets = [0.001] * 3, [1000.0, 2000.0, 0.0]
    las = laspy.LasData(header)
    las.x = rng.uniform(1000, 1010, N)
    las.y = rng.uniform(2000, 2010, N)
    las.z = rng.uniform(0, 30, N)
    for name in header.point_format.dimension_names:
        if name in ("X", "Y", "Z"):
            continue
        dim = las[name]
        info = np.iinfo(dim.dtype) if np.issubdtype(dim.dtype, np.integer) else None
        if name in ("return_number", "number_of_returns"):
            las[name] = rng.integers(1, 8, N)
        elif info is None:
            las[name] = rng.uniform(-1, 1, N).astype(dim.dtype)
        else:
            high = 2 if name in ("synthetic", "key_point", "withheld", "overlap",
                                 "scan_direction_flag", "edge_of_flight_line") else (
                4 if name == "scanner_channel" else min(int(info.max), 250))
            las[name] = rng.integers(0, high, N).astype(dim.dtype)
    las.write(path)
    return laspy.read(path)


@pytest.fixture(scope="module", params=[6, 8, 10])
def tile(request, tmp_path_factory):
    path = tmp_path_factory.mktemp("sel") / f"pf{request.param}.laz"
    return path, _random_tile(path, request.param)


@pytest.mark.parametrize("batch_size", [N, 1234])
def test_each_dimension_read_alone_equals_the_full_read(tile, batch_size):
    path, full = tile
    xyz = np.c_[full.x, full.y, full.z]
    for name in full.point_format.dimension_names:
        batches = list(iter_points(path, batch_size=batch_size, fields=(name,)))
        values = np.concatenate([b.fields[name] for b in batches])
        assert np.array_equal(values, np.asarray(full[name])), name
        assert values.dtype == np.asarray(full[name]).dtype
        assert np.array_equal(np.concatenate([b.xyz for b in batches]), xyz), name


def test_the_ingest_filters_fields_together_equal_the_full_read(tile):
    path, full = tile
    batch = read_points(path, fields=("classification", "withheld", "user_data"))
    for name in ("classification", "withheld", "user_data"):
        assert np.array_equal(batch.fields[name], np.asarray(full[name])), name


def test_the_layers_not_selected_are_not_decompressed(tile):
    # the selection reaches laspy: a dimension left out is not decoded (lazrs repeats the
    # first point's value), one kept is
    path, full = tile
    with open_las(path, decompression_selection(["classification"])) as reader:
        points = reader.read_points(N)
    assert np.array_equal(points["classification"], full["classification"])
    assert np.array_equal(points["Z"], full["Z"])
    for name in ("intensity", "gps_time", "user_data", "reflectance"):
        assert len(np.unique(full[name])) > 1 and len(np.unique(points[name])) == 1, name


def test_every_standard_dimension_has_its_layer():
    for point_format in range(6, 11):
        names = laspy.PointFormat(point_format).dimension_names
        assert set(names) <= LAZ_LAYERS.keys(), point_format
