"""The export's surface rasters: a stray point far above the canopy (a bird left unclassified
as noise) sets no cell of the DSM or of the canopy height model."""

import numpy as np
import pytest

from pipeline.io.raster import read_geotiff
from pipeline.terrain import scene_terrain
from tests.workflows.conftest import a_tile
from workflows.steps.export import RasterRequest, _TileRasters


def _forest(seed=6, size=20.0):
    """Ground at z = 100 with a canopy 15-20 m up over most of it: xyz (N, 3), canopy (N,)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, size, (int(30 * size * size), 2))
    crown = rng.random(len(xy)) < 0.6
    z = 100.0 + np.where(crown, 15.0 + 5.0 * np.abs(np.sin(xy[:, 0] / 3.0)), 0.0)
    return np.column_stack([xy, z]), crown


def _rasters(tmp_path, name, xyz, canopy, dtm, batches):
    tile = a_tile(maxs=(20.0, 20.0, 200.0), name=name)
    rasters = _TileRasters(tile, RasterRequest(("dsm", "chm"), 1.0, (0,), str(tmp_path)), dtm)
    height = xyz[:, 2] - 100.0
    for rows in np.array_split(np.arange(len(xyz)), batches):
        rasters.add(xyz[rows], height[rows], np.ones(len(rows), bool), canopy[rows])
    rasters.write()
    return (read_geotiff(tmp_path / f"{name}_dsm.tif")[0].values,
            read_geotiff(tmp_path / f"{name}_chm.tif")[0].values)


@pytest.mark.parametrize("batches", [1, 7])
def test_a_bird_over_the_canopy_sets_no_surface_cell(tmp_path, batches):
    xyz, canopy = _forest()
    dtm = scene_terrain(xyz[~canopy])
    birds = np.array([[7.3, 12.6, 180.0],  # over the canopy, predicted as canopy
                      [3.5, 3.5, 150.0]])  # and a second one
    noisy = np.vstack([xyz, birds])
    noisy_canopy = np.concatenate([canopy, [True, True]])
    dsm, chm = _rasters(tmp_path, "noisy", noisy, noisy_canopy, dtm, batches)
    want_dsm, want_chm = _rasters(tmp_path, "clean", xyz, canopy, dtm, batches)
    assert np.nanmax(chm) <= 20.0 and np.nanmax(dsm) <= 120.0
    np.testing.assert_array_equal(dsm, want_dsm)
    np.testing.assert_array_equal(chm, want_chm)
