"""GeoTIFF rasters: write-then-read round trip, orientation, cells of the points, hillshade."""

import numpy as np
import pytest

from pipeline.grid import Raster, cell_index, tile_grid
from pipeline.io.raster import NODATA, hillshade, read_geotiff, write_geotiff

UTM32 = 'PROJCS["ETRS89 / UTM zone 32N",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_System_1989",SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",9],PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1],AUTHORITY["EPSG","25832"]]'


def test_round_trip_keeps_values_orientation_crs_and_nodata(tmp_path):
    values = np.arange(12, dtype=np.float64).reshape(3, 4)  # row 0 is the south
    values[1, 2] = np.nan
    raster = Raster(values, 500010.0, 5500020.0, 0.5)
    write_geotiff(tmp_path / "r.tif", raster, UTM32)
    back, wkt = read_geotiff(tmp_path / "r.tif")
    assert np.array_equal(back.values, values.astype(np.float32), equal_nan=True)
    assert (back.x0, back.y0, back.cell) == (500010.0, 5500020.0, 0.5)
    assert "25832" in wkt
    import rasterio

    with rasterio.open(tmp_path / "r.tif") as src:
        assert src.nodata == NODATA and src.dtypes == ("float32",)
        # north-up: the first row read is the northern one, at the top of the bounds
        assert src.read(1)[0, 0] == values[-1, 0]
        assert src.bounds.top == 5500020.0 + 3 * 0.5
        assert src.xy(2, 0) == (500010.25, 5500020.25)  # centre of the south-west cell


def test_without_a_crs(tmp_path):
    write_geotiff(tmp_path / "r.tif", Raster(np.ones((2, 2)), 0.0, 0.0, 1.0), None)
    assert read_geotiff(tmp_path / "r.tif")[1] is None


def test_tile_grid_is_anchored_at_multiples_of_the_cell():
    assert tile_grid((10.2, 20.7), (12.0, 21.1), 1.0) == (10.0, 20.0, 2, 2)  # x up to 12, open
    assert tile_grid((-0.5, -0.5), (-0.5, -0.5), 2.0) == (-2.0, -2.0, 1, 1)
    assert tile_grid((4.0, 4.0), (4.0, 4.0), 1.0) == (4.0, 4.0, 1, 1)  # one point on a corner


@pytest.mark.parametrize("cell", [0.1, 0.3, 0.5, 1.0, 2.5])
@pytest.mark.parametrize("first", [0, 5_000_003, -12_345])
def test_neighbouring_tiles_grids_abut_and_hold_their_own_points(cell, first):
    """Tiles that end on a cell boundary: the next tile's grid starts where this one's ends
    (no cell in both), and every point of a tile, its highest on the boundary too, falls in
    its own grid."""
    rng = np.random.default_rng(int(cell * 10))
    edges = cell * (first + np.array([0, 37, 80, 121]))  # tile boundaries, on cell boundaries
    origin = edges[0]
    starts = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        xy = np.column_stack((rng.uniform(lo, hi, 300), rng.uniform(origin, origin + 5.0, 300)))
        xy[0] = (hi, origin + 5.0)  # a tile's highest point on its upper edges
        xy[1] = (lo, origin)
        mins, maxs = xy.min(axis=0), xy.max(axis=0)
        x0, y0, nx, ny = tile_grid(mins, maxs, cell)
        assert (cell_index(xy, x0, y0, cell, (ny, nx)) >= 0).all()
        starts.append((round(x0 / cell), round(x0 / cell) + nx))
    for (_, end), (start, _) in zip(starts[:-1], starts[1:]):
        assert end == start


def test_points_outside_the_grid_have_no_cell():
    outside = cell_index(np.array([[-1.0, 5.0], [5.0, 10.5]]), 0.0, 0.0, 1.0, (10, 10))
    assert list(outside) == [-1, -1]


@pytest.mark.parametrize("azimuth", [0.0, 90.0, 315.0])
def test_hillshade_of_a_flat_dem_is_sin_altitude_and_slopes_face_the_light(azimuth):
    flat = hillshade(np.full((5, 5), 10.0), 1.0, azimuth, 45.0)
    assert np.allclose(flat, np.sin(np.radians(45.0)))
    # a slope rising to the east faces west: lit from the west, dark from the east
    ramp = np.tile(np.arange(6, dtype=float), (6, 1))
    west, east = hillshade(ramp, 1.0, 270.0), hillshade(ramp, 1.0, 90.0)
    assert west.mean() > flat.mean() > east.mean()
    # rows go north: a slope rising to the north is lit from the south
    assert hillshade(ramp.T, 1.0, 180.0).mean() > hillshade(ramp.T, 1.0, 0.0).mean()
