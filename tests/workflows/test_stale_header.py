"""A tile whose header's box is stale (smaller than its points' box): its rasters, made from
the box of the points ingest reads, still cover every point, and a raster too big for that box
is refused once the points are read, before their features."""

import shutil
import struct

import laspy
import numpy as np
import pytest

from pipeline.grid import cell_index
from pipeline.io.raster import read_geotiff
from tests.workflows.conftest import silva

pytestmark = pytest.mark.slow

#: Offsets in a LAS header of max x, min x, max y, min y, max z, min z (float64 each).
BOX_OFFSET = 179


def shrink_header_box(path, share: float) -> None:
    """Overwrite the XY box of the header of ``path`` (LAS or LAZ) with its central ``share``:
    the points keep their coordinates, a quarter or more of them now lie outside."""
    data = bytearray(path.read_bytes())
    max_x, min_x, max_y, min_y, max_z, min_z = struct.unpack_from("<6d", data, BOX_OFFSET)
    half_x, half_y = (max_x - min_x) * share / 2, (max_y - min_y) * share / 2
    mid_x, mid_y = (max_x + min_x) / 2, (max_y + min_y) / 2
    struct.pack_into("<6d", data, BOX_OFFSET, mid_x + half_x, mid_x - half_x,
                     mid_y + half_y, mid_y - half_y, max_z, min_z)
    path.write_bytes(bytes(data))


def test_rasters_cover_the_points_beyond_a_stale_header_box(survey, tmp_path):
    tile = tmp_path / "stale.laz"
    shutil.copy(sorted(survey["test"].glob("*.laz"))[0], tile)
    las = laspy.read(tile)
    shrink_header_box(tile, 0.5)
    header = laspy.open(tile).header
    outside = ((las.x < header.mins[0]) | (las.x > header.maxs[0])
               | (las.y < header.mins[1]) | (las.y > header.maxs[1]))
    assert outside.mean() > 0.5  # the header is stale indeed
    result = silva("predict", "--model", "forest-tls-synthetic", "--out",
                   tmp_path / "out", tile, "--set", "output.rasters=[dsm]",
                   "--set", "output.raster_resolution=1.0", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    dsm, _ = read_geotiff(tmp_path / "out" / "rasters" / "stale_dsm.tif")
    flat = cell_index(np.c_[las.x, las.y], dsm.x0, dsm.y0, dsm.cell, dsm.values.shape)
    assert (flat >= 0).all()  # every point has its cell
    highest = np.full(dsm.values.size, -np.inf)
    np.maximum.at(highest, flat, np.asarray(las.z))
    highest = highest.reshape(dsm.values.shape)
    seen = np.isfinite(dsm.values)
    assert np.array_equal(seen, np.isfinite(highest))
    assert np.allclose(dsm.values[seen], highest[seen], atol=1e-3)


def test_a_raster_too_big_for_the_points_box_is_refused_before_the_features(survey, tmp_path):
    tile = tmp_path / "stale.laz"
    shutil.copy(sorted(survey["test"].glob("*.laz"))[0], tile)
    shrink_header_box(tile, 0.01)
    # cells of 0.5 mm: the header's box of a few centimetres passes, the points' 7 m do not
    out = tmp_path / "out"
    result = silva("predict", "--model", "forest-tls-synthetic", "--out", out, tile,
                   "--set", "output.rasters=[dsm]", "--set", "output.raster_resolution=0.0005",
                   "--in-process", "-q")
    assert result.exit_code == 1
    line = result.output.strip().splitlines()[-1]
    assert line.startswith("silva: error: config error: output.raster_resolution=0.0005 gives "
                           f"the rasters of {tile} ")
    assert "set a coarser resolution" in line
    log = (out / "silva.log").read_text().splitlines()  # refused once ingested, before work
    assert any(" ingest: " in entry for entry in log)
    assert [entry for entry in log if "features" in entry and " start: " not in entry] == []
    assert not (out / "predictions").exists() or not any((out / "predictions").iterdir())
