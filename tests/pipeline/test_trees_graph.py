"""Trees grown from their stems through the voxels of the tree points: two trees whose crowns
overlap seen from above are told apart, the voxels of any chunking are those of the whole, and
the model built on them assigns every tree point and round-trips through arrays."""

import numpy as np

from pipeline.trees import TreeParams, assign_trees, chm_raster, canopy_cells, segment_crowns
from pipeline.trees.graph import VOXEL, VoxelTrees, grow_from_stems, merge_voxels, tree_voxels
from pipeline.trees.model import TreeModel, tree_model, with_voxels
from pipeline.trees.stems import Stems


def tree_points(rng, base, height, crown_radius, lean=(0.0, 0.0), n=6000):
    """A stem (a vertical line of points) and a conical crown of scattered points."""
    z = rng.uniform(0.0, height, n // 3)
    stem = np.column_stack([base[0] + lean[0] * z, base[1] + lean[1] * z, z])
    u = rng.uniform(0.35, 1.0, n - n // 3)
    radius = crown_radius * (1.0 - u) / 0.65 * rng.uniform(0, 1, u.size) ** 0.5
    angle = rng.uniform(0, 2 * np.pi, u.size)
    zc = u * height
    crown = np.column_stack([base[0] + lean[0] * zc + radius * np.cos(angle),
                             base[1] + lean[1] * zc + radius * np.sin(angle), zc])
    return np.concatenate([stem, crown])


def two_trees():
    """A tall tree and a short one under its crown's edge, 2 m apart."""
    rng = np.random.default_rng(3)
    tall = tree_points(rng, (10.0, 10.0), 20.0, 3.0)
    short = tree_points(rng, (12.0, 10.0), 8.0, 1.2, n=3000)
    xyz = np.concatenate([tall, short]) + [500000.0, 5500000.0, 0.0]
    truth = np.r_[np.ones(len(tall), int), np.full(len(short), 2)]
    return xyz, truth


def test_voxels_of_chunks_merge_to_those_of_the_whole():
    xyz, _ = two_trees()
    height, mask = xyz[:, 2], np.ones(len(xyz), bool)
    whole = tree_voxels(xyz, height, mask)
    strips = np.floor((xyz[:, 0] - xyz[:, 0].min()) / 1.3).astype(int) % 3
    parts = [tree_voxels(xyz[strips == k], height[strips == k], mask[strips == k])
             for k in range(3)]
    assert np.array_equal(merge_voxels(parts[::-1]), whole)
    assert len(whole) < len(xyz)


def test_each_tree_is_grown_from_its_own_stem():
    xyz, truth = two_trees()
    voxels = tree_voxels(xyz, xyz[:, 2], np.ones(len(xyz), bool))
    seeds = np.array([[500010.0, 5500010.0, 1.3], [500012.0, 5500010.0, 1.3]])
    grown = grow_from_stems(voxels, seeds, np.array([7, 9], np.uint32))
    ids = grown.lookup(xyz)
    assert set(np.unique(ids)) <= {0, 7, 9}
    for tree, label in ((1, 7), (2, 9)):
        share = np.mean(ids[truth == tree] == label)
        assert share > 0.9, (tree, share)
    # seen from above, most of the short tree lies under the tall one's crown
    under = np.hypot(xyz[truth == 2, 0] - 500010.0, xyz[truth == 2, 1] - 5500010.0) < 3.0
    assert under.mean() > 0.5


def test_no_seed_leaves_every_voxel_without_a_tree():
    xyz, _ = two_trees()
    voxels = tree_voxels(xyz, xyz[:, 2], np.ones(len(xyz), bool))
    grown = grow_from_stems(voxels, np.empty((0, 3)), np.empty(0, np.uint32))
    assert not grown.lookup(xyz).any()
    far = grow_from_stems(voxels, [[0.0, 0.0, 0.0]], np.array([1], np.uint32))
    assert not far.lookup(xyz).any()  # a seed farther than SEED_REACH from every voxel


def test_a_model_with_voxels_assigns_tree_points_and_round_trips():
    xyz, truth = two_trees()
    params = TreeParams(method="stems")
    height = xyz[:, 2]
    canopy = np.ones(len(xyz), bool)
    chm = chm_raster(canopy_cells(xyz, height, canopy, params.resolution), params.resolution)
    stems = Stems(x=np.array([500010.0, 500012.0]), y=np.array([5500010.0, 5500010.0]),
                  z_base=np.zeros(2), dbh=np.array([0.3, 0.15]),
                  quality=np.array([2, 2], np.uint8), fit_height=np.array([1.3, 1.3]))
    crowns = segment_crowns(chm, params, seeds=np.column_stack([stems.x, stems.y]))
    model = tree_model(crowns, stems, params)
    trees = np.flatnonzero(np.isfinite(model.stem_x))
    seeds = np.column_stack([model.stem_x[trees], model.stem_y[trees], np.full(2, 1.3)])
    grown = grow_from_stems(tree_voxels(xyz, height, canopy), seeds,
                            (trees + 1).astype(np.uint32), VOXEL)
    full = with_voxels(model, grown)
    ids = assign_trees(full, xyz, height, canopy, None, params)
    assert np.array_equal(np.unique(ids[ids > 0]), [1, 2])
    assert full.crown_cells.sum() == np.count_nonzero(full.labels)
    assert (full.crown_cells > 0).all()
    arrays, attrs = full.to_arrays()
    back = TreeModel.from_arrays(arrays, attrs)
    assert isinstance(back.voxels, VoxelTrees)
    assert np.array_equal(assign_trees(back, xyz, height, canopy, None, params), ids)
    # the points of each true tree mostly carry one ID
    for tree in (1, 2):
        assert np.bincount(ids[truth == tree]).max() / np.sum(truth == tree) > 0.9


def test_the_inputs_of_any_split_give_the_trees_of_the_whole_cloud():
    from pipeline.trees import assign_trees, find_trees, merge_inputs, scene_model, tree_inputs
    from pipeline.trees.model import TREE_ARRAYS

    xyz, _ = two_trees()
    height = xyz[:, 2]
    trees = np.ones(len(xyz), bool)
    stem = trees.copy()  # every point may be stem or canopy
    params = TreeParams(method="auto", stem_min_points=6)
    ids, table, model, method = find_trees(xyz, height, trees, stem, params, area=100.0)
    strips = np.floor(xyz[:, 1] * 3.1).astype(int) % 4
    parts = [tree_inputs(xyz[strips == k], height[strips == k], trees[strips == k],
                         stem[strips == k], params) for k in (2, 0, 3, 1)]
    split, _, split_method = scene_model(merge_inputs(parts, params), params, 100.0)
    assert split_method == method
    for name in TREE_ARRAYS:  # the per-tree arrays; the crowns' rasters stay in blocks
        assert np.array_equal(getattr(model, name), getattr(split, name), equal_nan=True), name
    assert np.array_equal(assign_trees(split, xyz, height, trees, stem, params), ids)
    assert len(table) == len(model) and ids.max() <= len(model)


def test_a_crown_seen_in_patches_stays_with_its_stem():
    """A gap of a voxel or so between the stem and its crown (the scanner saw neither
    between them) does not cut the crown from the tree."""
    rng = np.random.default_rng(8)
    z = rng.uniform(0.0, 5.95, 3000)  # the stem up to 5.95 m, the crown from 6.25 m
    stem = np.column_stack([0.1 * np.cos(z * 40), 0.1 * np.sin(z * 40), z])
    zc = rng.uniform(6.25, 10.0, 3000)
    r = (10.0 - zc) / 3.75 * np.sqrt(rng.uniform(0, 1, zc.size))
    crown = np.column_stack([r * np.cos(zc * 17), r * np.sin(zc * 17), zc])
    xyz = np.concatenate([stem, crown]) + [500000.05, 5500000.05, 0.0]
    voxels = tree_voxels(xyz, xyz[:, 2], np.ones(len(xyz), bool))
    grown = grow_from_stems(voxels, [[500000.05, 5500000.05, 1.3]], np.array([1], np.uint32))
    assert np.all(grown.lookup(xyz) == 1)
