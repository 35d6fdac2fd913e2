"""The tree model: IDs from where trees are, per-point assignment, exact stats and the table."""

import numpy as np
import pytest

from pipeline.errors import ModelError
from pipeline.trees import (
    Stems,
    TreeModel,
    TreeParams,
    assign_trees,
    canopy_cells,
    chm_raster,
    merge_cells,
    merge_stats,
    segment_crowns,
    tree_model,
    tree_stats,
    tree_table,
)
from pipeline.trees.cells import unpack_keys
from tests.pipeline.test_trees_crowns import CONES, cone_forest

PARAMS = TreeParams()


def stems_at(xy, dbh, quality):
    n = len(xy)
    xy = np.asarray(xy, dtype=np.float64).reshape(n, 2)
    return Stems(xy[:, 0], xy[:, 1], np.full(n, 100.0), np.asarray(dbh, np.float64),
                     np.asarray(quality, np.uint8), np.full(n, 1.3))


def scene_model(xyz, height, canopy, chunks, stems=None):
    """The model of a scene reduced chunk by chunk, as the workflow does."""
    cells = merge_cells(canopy_cells(xyz[c], height[c], canopy[c], PARAMS.resolution)
                        for c in chunks)
    crowns = segment_crowns(chm_raster(cells, PARAMS.resolution), PARAMS)
    return crowns, tree_model(crowns, stems, PARAMS)


def random_chunks(n, k, seed):
    return np.array_split(np.random.default_rng(seed).permutation(n), k)


@pytest.fixture(scope="module")
def forest():
    return cone_forest(11)


def _models_equal(a, b):
    arrays_a, attrs_a = a.to_arrays()
    arrays_b, attrs_b = b.to_arrays()
    return attrs_a == attrs_b and all(np.array_equal(arrays_a[k], arrays_b[k], equal_nan=True)
                                      for k in arrays_a)


@pytest.mark.parametrize("k", [1, 3, 8])
def test_the_model_does_not_depend_on_how_the_points_were_chunked(forest, k):
    xyz, height, canopy = forest
    _, whole = scene_model(xyz, height, canopy, [np.arange(xyz.shape[0])])
    _, chunked = scene_model(xyz, height, canopy, random_chunks(xyz.shape[0], k, k))
    assert _models_equal(whole, chunked)


def test_ids_follow_the_cell_keys_of_the_tops(forest):
    crowns, model = scene_model(*forest, [np.arange(forest[0].shape[0])])
    assert len(model) == len(CONES)
    ids_at_tops = model.labels[crowns.top_row, crowns.top_col]
    kx, ky = unpack_keys(crowns.top_keys)
    assert np.array_equal(ids_at_tops[np.lexsort((kx, ky))], np.arange(1, len(CONES) + 1))


def test_assigning_chunks_equals_assigning_all(forest):
    xyz, height, canopy = forest
    _, model = scene_model(xyz, height, canopy, [np.arange(xyz.shape[0])])
    stem_mask = ~canopy
    ids = assign_trees(model, xyz, height, canopy, stem_mask, PARAMS)
    for chunk in random_chunks(xyz.shape[0], 6, 1):
        part = assign_trees(model, xyz[chunk], height[chunk], canopy[chunk], stem_mask[chunk],
                            PARAMS)
        assert np.array_equal(part, ids[chunk])
    assert ids.dtype == np.uint32 and set(np.unique(ids)) == set(range(len(CONES) + 1))
    assert not ids[height < PARAMS.min_height].any()


def test_merged_stats_equal_the_stats_of_all_points(forest):
    xyz, height, canopy = forest
    xyz = xyz.copy()
    xyz[::5, 2] = np.round(xyz[::5, 2])  # ties in z
    _, model = scene_model(xyz, height, canopy, [np.arange(xyz.shape[0])])
    ids = assign_trees(model, xyz, height, canopy, None, PARAMS)
    whole = tree_stats(ids, xyz, height)
    chunks = random_chunks(xyz.shape[0], 7, 2)
    parts = [tree_stats(ids[c], xyz[c], height[c]) for c in chunks]
    for merged in (merge_stats(parts), merge_stats(parts[::-1])):
        for name in ("ids", "points", "x", "y", "z", "height"):
            assert np.array_equal(getattr(merged, name), getattr(whole, name)), name


def test_the_table_counts_the_points_assigned_to_each_tree(forest):
    xyz, height, canopy = forest
    crowns, model = scene_model(xyz, height, canopy, [np.arange(xyz.shape[0])])
    ids = assign_trees(model, xyz, height, canopy, None, PARAMS)
    table = tree_table(model, tree_stats(ids, xyz, height))
    assert np.array_equal(table["tree_id"], np.arange(1, len(CONES) + 1))
    assert np.array_equal(table["points"], np.bincount(ids, minlength=len(CONES) + 1)[1:])
    # the highest point of a sharp cone lies a little below its apex
    found, truth = np.sort(table["height"]), np.sort([h for _, _, h, _ in CONES])
    assert np.all((found <= truth) & (found > 0.9 * truth))
    assert np.allclose(table["z"] - table["height"], 100.0)
    cells = np.bincount(model.labels.ravel(), minlength=len(CONES) + 1)[1:]
    assert np.array_equal(table["crown_area"], cells * 0.25)
    assert np.allclose(np.pi * (table["crown_diameter"] / 2) ** 2, table["crown_area"])
    assert np.isnan(table["dbh"]).all() and not table["dbh_quality"].any()


def test_a_stem_in_a_crown_gives_its_tree_a_dbh_and_a_lone_stem_is_a_tree(forest):
    xyz, height, canopy = forest
    # a stem under the first cone's top, one under no crown (x = 33, y = 3)
    stems = stems_at([(10.1, 10.0), (33.0, 3.0)], [0.4, np.nan], [2, 1])
    crowns, model = scene_model(xyz, height, canopy, [np.arange(xyz.shape[0])], stems)
    assert len(model) == len(CONES) + 1
    crown_tree = model.labels[crowns.top_row[np.argmin(np.hypot(*(crowns.top_xy - 10.0).T))],
                              crowns.top_col[np.argmin(np.hypot(*(crowns.top_xy - 10.0).T))]]
    assert model.dbh[crown_tree - 1] == 0.4 and model.dbh_quality[crown_tree - 1] == 2
    lone = np.flatnonzero(model.crown_cells == 0)
    assert lone.size == 1 and model.stem_x[lone[0]] == 33.0 and np.isnan(model.dbh[lone[0]])
    # stem points around the lone stem (radius 0 + margin) get its tree, others nothing
    points = np.array([[33.05, 3.0, 100.5], [33.5, 3.0, 100.5]])
    ids = assign_trees(model, points, np.array([0.5, 0.5]), np.zeros(2, bool),
                       np.ones(2, bool), PARAMS)
    assert ids.tolist() == [lone[0] + 1, 0]
    table = tree_table(model, tree_stats(ids, points, np.array([0.5, 0.5])))
    row = table[lone[0]]
    assert (row["x"], row["y"], row["points"], row["dbh_quality"]) == (33.0, 3.0, 1, 1)
    assert np.isnan(row["crown_area"])


def test_stem_trees_alone_are_numbered_by_where_they_stand():
    stems = stems_at([(5.0, 9.0), (7.0, 1.0), (3.0, 1.0)], [0.3, 0.2, 0.5], [2, 2, 2])
    model = tree_model(None, stems, PARAMS)
    assert model.labels.shape == (0, 0)
    assert model.stem_x.tolist() == [3.0, 7.0, 5.0]
    shuffled = stems_at([(7.0, 1.0), (5.0, 9.0), (3.0, 1.0)], [0.2, 0.3, 0.5], [2, 2, 2])
    assert _models_equal(tree_model(None, shuffled, PARAMS), model)


def test_of_two_stems_in_a_crown_the_one_nearest_the_top_joins_it(forest):
    xyz, height, canopy = forest
    crowns = segment_crowns(chm_raster(canopy_cells(xyz, height, canopy, 0.5), 0.5), PARAMS)
    top = crowns.top_xy[np.argmin(np.hypot(*(crowns.top_xy - 10.0).T))]
    near, far = (top[0] + 0.2, top[1]), (top[0] - 1.5, top[1] + 0.5)
    stems = stems_at([far, near], [0.3, 0.5], [2, 2])
    model = tree_model(crowns, stems, PARAMS)
    assert len(model) == len(CONES) + 1
    joined = np.flatnonzero(model.crown_cells > 0)[np.isfinite(model.stem_x[model.crown_cells > 0])]
    assert joined.size == 1 and model.dbh[joined[0]] == 0.5
    alone = np.flatnonzero(model.crown_cells == 0)
    assert alone.size == 1 and model.dbh[alone[0]] == 0.3
    swapped = tree_model(crowns, stems_at([near, far], [0.5, 0.3], [2, 2]), PARAMS)
    assert _models_equal(swapped, model)


def test_the_model_round_trips_through_plain_arrays(forest):
    stems = stems_at([(10.1, 10.0), (33.0, 3.0)], [0.4, np.nan], [2, 1])
    _, model = scene_model(*forest, [np.arange(forest[0].shape[0])], stems)
    arrays, attrs = model.to_arrays()
    assert all(isinstance(v, np.ndarray) for v in arrays.values())
    assert all(isinstance(v, float) for v in attrs.values())
    again = TreeModel.from_arrays({k: v.tolist() for k, v in arrays.items()}, attrs)
    assert _models_equal(again, model)
    assert again.labels.dtype == np.uint32 and again.dbh_quality.dtype == np.uint8
    del arrays["dbh"]
    with pytest.raises(ModelError, match="dbh"):
        TreeModel.from_arrays(arrays, attrs)


def test_the_table_refuses_ids_the_model_does_not_have(forest):
    _, model = scene_model(*forest, [np.arange(forest[0].shape[0])])
    ids = np.full(3, len(model) + 1, dtype=np.uint32)
    with pytest.raises(ModelError, match="tree ID"):
        tree_table(model, tree_stats(ids, np.zeros((3, 3)), np.zeros(3)))
