"""The tree table as CSV and as a GeoPackage of tops and crowns, read back."""

import csv
import math
import warnings

import numpy as np
import pyogrio
import pyogrio.raw
import pytest
import shapely
from pyproj import CRS

from pipeline.io.vector import crown_polygons, write_tree_csv, write_tree_gpkg
from pipeline.trees import TABLE_DTYPE

CRS_WKT = CRS.from_epsg(32611).to_wkt()


@pytest.fixture
def trees():
    """Three trees on a 6 x 8 grid of 0.5 m cells at (100, 200): tree 1 a 2 x 3 block, tree 2
    an L of 4 cells, tree 3 a stem without crown; a crown tree has a NaN DBH."""
    labels = np.zeros((6, 8), dtype=np.uint32)
    labels[0:2, 0:3] = 1
    labels[3:6, 5] = 2
    labels[5, 6] = 2
    table = np.zeros(3, dtype=TABLE_DTYPE)
    table["tree_id"] = [1, 2, 3]
    table["x"], table["y"] = [100.7, 102.8, 103.95], [200.4, 202.6, 200.2]
    table["z"], table["height"] = [321.1234, 318.5, math.nan], [21.1234, 18.5, math.nan]
    table["crown_area"] = [1.5, 1.0, math.nan]
    table["crown_diameter"] = 2 * np.sqrt(table["crown_area"] / np.pi)
    table["points"] = [120, 80, 0]
    table["dbh"], table["dbh_quality"] = [0.4123, math.nan, 0.21], [2, 0, 1]
    return table, labels


def test_the_csv_round_trips_with_empty_fields_for_unknown_values(tmp_path, trees):
    table, _ = trees
    path = tmp_path / "trees.csv"
    write_tree_csv(path, table)
    lines = path.read_text().splitlines()
    assert lines[0] == ("tree_id,x,y,z,height,crown_area,crown_diameter,points,dbh,"
                        "dbh_quality")
    assert lines[1] == "1,100.700,200.400,321.123,21.123,1.50,1.382,120,0.412,2"
    assert lines[2].endswith(",80,,0")
    rows = list(csv.DictReader(path.open()))
    assert [int(r["tree_id"]) for r in rows] == [1, 2, 3]
    for name in ("x", "y", "z", "height", "crown_area", "dbh"):
        back = np.array([float(r[name]) if r[name] else math.nan for r in rows])
        assert np.allclose(back, table[name], atol=5e-3, equal_nan=True), name
    assert [int(r["points"]) for r in rows] == [120, 80, 0]
    assert not list(tmp_path.glob(".*part"))


def test_crown_polygons_cover_each_trees_cells(trees):
    _, labels = trees
    polygons = crown_polygons(labels, 100.0, 200.0, 0.5)
    assert sorted(polygons) == [1, 2]
    assert polygons[1].area == pytest.approx(6 * 0.25)
    assert polygons[2].area == pytest.approx(4 * 0.25)
    assert polygons[1].bounds == pytest.approx((100.0, 200.0, 101.5, 201.0))
    # row 0 is the south edge: tree 2's cells span rows 3-5, y 201.5-203
    assert polygons[2].bounds == pytest.approx((102.5, 201.5, 103.5, 203.0))
    assert all(p.is_valid and p.geom_type == "Polygon" for p in polygons.values())


def test_the_geopackage_holds_tops_and_crowns_in_the_crs(tmp_path, trees):
    table, labels = trees
    path = tmp_path / "trees.gpkg"
    write_tree_gpkg(path, table, labels, 100.0, 200.0, 0.5, CRS_WKT)
    assert pyogrio.list_layers(path).tolist() == [["tops", "Point"], ["crowns", "MultiPolygon"]]
    meta, _, geometry, fields = pyogrio.raw.read(path, layer="tops")
    assert CRS.from_user_input(meta["crs"]) == CRS.from_epsg(32611)
    tops = shapely.from_wkb(geometry)
    assert np.allclose(shapely.get_x(tops), table["x"]) and len(tops) == 3
    values = dict(zip(meta["fields"], fields))
    assert values["tree_id"].tolist() == [1, 2, 3]
    assert np.allclose(values["dbh"], table["dbh"], equal_nan=True)
    assert values["dbh_quality"].tolist() == [2, 0, 1]
    meta, _, geometry, fields = pyogrio.raw.read(path, layer="crowns")
    crowns = shapely.from_wkb(geometry)
    values = dict(zip(meta["fields"], fields))
    assert values["tree_id"].tolist() == [1, 2]
    assert shapely.is_valid(crowns).all()
    assert np.allclose(shapely.area(crowns), values["crown_area"])
    assert CRS.from_user_input(meta["crs"]) == CRS.from_epsg(32611)
    assert not list(tmp_path.glob(".*part"))


def test_a_tile_without_a_crs_gives_layers_without_one_and_no_warning(tmp_path, trees):
    table, labels = trees
    path = tmp_path / "local.gpkg"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the user's terminal shows none
        write_tree_gpkg(path, table, labels, 100.0, 200.0, 0.5, None)
    assert pyogrio.read_info(path, layer="tops")["crs"] is None
    assert pyogrio.read_info(path, layer="crowns")["features"] == 2


def test_a_model_without_crowns_writes_an_empty_crowns_layer(tmp_path, trees):
    table, _ = trees
    path = tmp_path / "stems.gpkg"
    write_tree_gpkg(path, table[2:], np.zeros((0, 0), np.uint32), 0.0, 0.0, 0.5, CRS_WKT)
    assert pyogrio.read_info(path, layer="tops")["features"] == 1
    assert pyogrio.read_info(path, layer="crowns")["features"] == 0


def test_a_tiles_rows_get_only_their_own_crowns(tmp_path, trees):
    table, labels = trees
    path = tmp_path / "tile.gpkg"
    write_tree_gpkg(path, table[1:2], labels, 100.0, 200.0, 0.5, CRS_WKT)
    meta, _, geometry, fields = pyogrio.raw.read(path, layer="crowns")
    values = dict(zip(meta["fields"], fields))
    assert values["tree_id"].tolist() == [2] and values["points"].tolist() == [80]
    assert shapely.from_wkb(geometry[0]).area == pytest.approx(1.0)


def test_crown_polygons_keep_ids_beyond_the_int32_range(trees):
    _, labels = trees
    big = np.where(labels == 2, np.uint32(3_000_000_000), labels).astype(np.uint32)
    polygons = crown_polygons(big, 100.0, 200.0, 0.5)
    assert sorted(polygons) == [1, 3_000_000_000]
    assert polygons[3_000_000_000].area == pytest.approx(1.0)
    assert list(crown_polygons(big, 100.0, 200.0, 0.5, trees=np.array([1]))) == [1]
