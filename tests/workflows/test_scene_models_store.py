"""Scene models in the store: a block written is done with its fingerprint only, read back
array for array; a scene without its model says how to fix it; overviews are thinned."""

import numpy as np
import pytest

from pipeline.errors import StoreError
from pipeline.grid import Raster
from pipeline.store import open_store
from workflows.store.marks import mark_done
from workflows.store.models import SceneModels, thinned

MODELS = SceneModels("things", "thing model")


def test_a_block_round_trips_and_is_done_with_its_fingerprint_only(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    arrays = {"values": np.arange(6.0).reshape(2, 3), "ids": np.array([3, 1], np.uint32)}
    MODELS.write_block(root, "s", (-1, 2), arrays, "fp1", counts={"n": 2})
    assert MODELS.block_path("s", (-1, 2)) == "scenes/s/things/blocks/-1_2"
    assert MODELS.block_done(root, "s", (-1, 2), "fp2") is None
    assert MODELS.block_done(root, "s", (0, 2), "fp1") is None
    assert dict(MODELS.block_done(root, "s", (-1, 2), "fp1").attrs["counts"]) == {"n": 2}
    read = MODELS.block_arrays(root, "s", (-1, 2), ("values", "ids"))
    for name, array in arrays.items():
        assert read[name].dtype == array.dtype and np.array_equal(read[name], array)


def test_a_scene_is_done_once_marked_and_says_the_fix_when_not(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    assert MODELS.done(root, "s") is None
    with pytest.raises(StoreError, match="^scene 's' has no thing model in the store; run the "
                                         "same command again"):
        MODELS.scene_group(root, "s")
    mark_done(root.require_group(MODELS.path("s")), "things", "fp")
    assert MODELS.done(root, "s") == "fp" and MODELS.scene_group(root, "s").path == "scenes/s/things"


def test_an_overview_takes_every_kth_cell_to_stay_within_its_cells():
    rasters = [Raster(np.arange(100.0).reshape(10, 10), 0.0, 0.0, 1.0)] * 4
    drawn = thinned(iter(rasters), 400, max_cells=100)
    assert [r.shape for r in drawn] == [(5, 5)] * 4 and drawn[0].cell == 2.0
    assert np.array_equal(drawn[0].values, rasters[0].values[::2, ::2])
    assert thinned(rasters, 400)[0].shape == (10, 10)


def test_an_overview_keeps_none_of_the_rasters_it_thins_alive():
    """A survey's overview reads its blocks one by one: were the thinned cells views, every
    block's whole raster would stay in memory (1.2 GiB for the report of 100 km²)."""
    import gc
    import weakref

    alive = []

    def blocks():
        for _ in range(3):
            values = np.zeros((40, 40))
            alive.append(weakref.ref(values))
            yield Raster(values, 0.0, 0.0, 1.0)

    drawn = thinned(blocks(), 4_800, max_cells=300)
    gc.collect()
    assert [r.shape for r in drawn] == [(10, 10)] * 3
    assert all(ref() is None for ref in alive)
