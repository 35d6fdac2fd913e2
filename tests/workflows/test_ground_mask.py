"""The ground rule's mask of a chunk is computed once, with its features, and every stage
reads it; a chunk whose features were stored without it gets the same mask computed."""

import shutil

import numpy as np

from pipeline.cascade import on_ground
from pipeline.store import open_store
from tests.workflows.conftest import GROUND_TOLERANCE
from workflows.exec.engine import ChunkView
from workflows.steps.terrain import GroundRule
from workflows.store.layout import ON_GROUND
from workflows.store.terrain import stored_terrain

RULE = GroundRule(GROUND_TOLERANCE, 0)  # terrain: the first class of the quick configs


def _chunks(out, scene):
    store = out / "store.zarr"
    names = sorted(open_store(store, mode="r")[f"scenes/{scene}/chunks"].group_keys())
    return [ChunkView(str(store), scene, name) for name in names]


def test_each_chunk_stores_the_points_the_rule_takes_with_its_features(survey_run_kept):
    taken = 0
    for view in _chunks(survey_run_kept, "test"):
        terrain = stored_terrain(view.root, view.store_path, view.scene)
        expected = on_ground(terrain, view.read("xyz"), GROUND_TOLERANCE)
        assert np.array_equal(view.read(ON_GROUND), expected)
        assert np.array_equal(RULE.override(view).rows, expected)
        taken += int(expected.sum())
    assert taken > 0


def test_features_stored_without_the_mask_get_it_computed(survey_run_kept, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(survey_run_kept / "store.zarr", out / "store.zarr")
    for view in _chunks(out, "test"):
        stored = view.read(ON_GROUND)
        view.write(features=view.read("features"), undefined=view.read("undefined"))
        assert not view.has(ON_GROUND)
        assert np.array_equal(RULE.override(view).rows, stored)
    assert GroundRule().override(view) is None  # the rule off
