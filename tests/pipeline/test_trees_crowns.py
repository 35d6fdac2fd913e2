"""Tree tops and crowns: exact canopy cells, the CHM, and segmentation of known crowns."""

import math

import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.grid import Raster
from pipeline.trees import (
    TreeParams,
    canopy_cells,
    chm_raster,
    find_trees,
    merge_cells,
    segment_crowns,
)
from pipeline.trees.cells import unpack_keys
from pipeline.trees.crowns import find_tops

#: Cone crowns (x, y, height, radius) apart from each other, radii within the default bound.
CONES = [(10.0, 10.0, 20.0, 3.5), (22.0, 11.0, 12.0, 2.2), (14.0, 24.0, 30.0, 4.5),
         (27.0, 25.0, 8.0, 1.8), (6.0, 30.0, 16.0, 3.0)]


def cone_forest(seed, cones=CONES, density=40.0, size=36.0):
    """A flat ground at z = 100 under cone crowns: xyz (N, 3), height (N,), canopy (N,).

    Points are uniform in XY; a point under a crown lies on it (canopy), else on the ground.
    """
    rng = np.random.default_rng(seed)
    n = int(density * size * size)
    xy = rng.uniform(0.0, size, size=(n, 2))
    height = np.zeros(n)
    for x, y, h, r in cones:
        height = np.maximum(height, h * (1.0 - np.hypot(xy[:, 0] - x, xy[:, 1] - y) / r))
    canopy = height > 0.0
    xyz = np.column_stack((xy, 100.0 + height))
    return xyz, height, canopy


def crowns_of(xyz, height, canopy, params=TreeParams()):
    cells = canopy_cells(xyz, height, canopy, params.resolution)
    return segment_crowns(chm_raster(cells, params.resolution), params)


def _fields_equal(a, b):
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=f == "second")
               for f in ("keys", "height", "x", "y", "z", "second"))


# --- canopy cells --------------------------------------------------------------------------

def test_canopy_cells_keep_the_highest_canopy_point_of_each_cell():
    xyz = np.array([[0.1, 0.1, 5.0], [0.4, 0.2, 7.0], [0.3, 0.3, 9.0], [1.2, 0.1, 3.0],
                    [1.3, 0.2, 3.0], [2.2, 0.2, 4.0]])
    height = xyz[:, 2] - 1.0
    canopy = np.array([True, True, False, True, True, True])
    height[5] = -0.5  # below the ground: left out
    cells = canopy_cells(xyz, height, canopy, 1.0)
    kx, ky = unpack_keys(cells.keys)
    assert kx.tolist() == [0, 1] and ky.tolist() == [0, 0]
    assert cells.z.tolist() == [7.0, 3.0]
    assert cells.x.tolist() == [0.4, 1.2]  # a tie in height and z goes to the smallest x


def test_canopy_cells_against_a_loop():
    rng = np.random.default_rng(8)
    xyz = rng.uniform([-3.0, 5.0, 0.0], [3.0, 9.0, 4.0], size=(400, 3))
    xyz[:100, 2] = np.round(xyz[:100, 2])
    height, canopy = xyz[:, 2] - 0.5, rng.random(400) < 0.7
    best, heights = {}, {}
    for (x, y, z), h, c in zip(xyz, height, canopy):
        if c and h >= 0.0:
            key = (math.floor(x / 0.7), math.floor(y / 0.7))
            rank = (h, z, -x, -y)
            heights.setdefault(key, []).append(h)
            if key not in best or rank > best[key][0]:
                best[key] = (rank, (x, y, z))
    cells = canopy_cells(xyz, height, canopy, 0.7)
    kx, ky = unpack_keys(cells.keys)
    found = {(int(i), int(j)): (x, y, z) for i, j, x, y, z in zip(kx, ky, cells.x, cells.y,
                                                                 cells.z)}
    assert found == {key: point for key, (_, point) in best.items()}
    seconds = {(int(i), int(j)): s for i, j, s in zip(kx, ky, cells.second)}
    for key, hs in heights.items():  # the second highest height of the cell, NaN for one
        want = sorted(hs)[-2] if len(hs) > 1 else None
        assert (np.isnan(seconds[key]) if want is None else seconds[key] == want), key
    assert list(zip(ky.tolist(), kx.tolist())) == sorted(zip(ky.tolist(), kx.tolist()))


@pytest.mark.parametrize("n_chunks", [2, 5, 17])
def test_merged_cells_of_random_chunks_equal_all_at_once(n_chunks):
    xyz, height, canopy = cone_forest(1, density=10.0)
    xyz[::7, 2] = np.round(xyz[::7, 2])  # ties in z are broken by x and y
    whole = canopy_cells(xyz, height, canopy, 0.5)
    rng = np.random.default_rng(n_chunks)
    parts = np.array_split(rng.permutation(xyz.shape[0]), n_chunks)
    cells = [canopy_cells(xyz[p], height[p], canopy[p], 0.5) for p in parts]
    assert _fields_equal(merge_cells(cells), whole)
    assert _fields_equal(merge_cells(cells[::-1]), whole)
    assert _fields_equal(merge_cells([merge_cells(cells[:2]), *cells[2:]]), whole)


def test_chm_raster_puts_each_cell_at_its_row_and_column():
    xyz = np.array([[-1.2, 3.4, 0.0], [0.7, 5.1, 0.0]])
    cells = canopy_cells(xyz, np.array([4.0, 6.0]), np.ones(2, bool), 0.5)
    chm = chm_raster(cells, 0.5)
    assert (chm.x0, chm.y0, chm.shape) == (-1.5, 3.0, (5, 5))
    assert chm.values[0, 0] == 4.0 and chm.values[4, 4] == 6.0
    assert np.isnan(chm.values).sum() == 23


# --- tops and crowns -----------------------------------------------------------------------

def _matched_tops(crowns, cones):
    """Index of the nearest true top of each found top, and its distance."""
    found = crowns.top_xy
    truth = np.array([(x, y) for x, y, _, _ in cones])
    distance = np.hypot(*(found[:, None, :] - truth[None, :, :]).transpose(2, 0, 1))
    return distance.argmin(axis=1), distance.min(axis=1)


def test_tops_against_a_loop_over_every_cell():
    from scipy import ndimage

    rng = np.random.default_rng(9)
    values = ndimage.gaussian_filter(rng.normal(size=(40, 50)), 2.0) * 60.0 + 8.0
    values[rng.random(values.shape) < 0.05] = np.nan
    params = TreeParams(smoothing=0.0, window=(2.0, 0.15))
    rows, cols = find_tops(values, values, 0.5, params)
    expected = []
    for i, j in zip(*np.nonzero(values >= params.min_height)):
        r = max(int(np.rint((2.0 + 0.15 * values[i, j]) / 1.0)), 1)
        di, dj = np.mgrid[-r:r + 1, -r:r + 1]
        disk = (di**2 + dj**2 <= r * r) & (i + di >= 0) & (i + di < 40) & (j + dj >= 0) \
            & (j + dj < 50)
        around = values[(i + di)[disk], (j + dj)[disk]]
        if values[i, j] >= np.nanmax(around):
            expected.append((i, j))
    assert len(expected) > 5
    assert list(zip(rows.tolist(), cols.tolist())) == expected


@pytest.mark.parametrize("second, tops", [("cone", 2), ("bump", 1)])
def test_a_blob_with_two_apexes_of_distinct_height_is_two_trees(second, tops):
    """A 20 m cone and, 2 m away (within one top window), a 17 m cone: its apex rises
    above the saddle between them and is a tree of its own; a bump of 0.3 m on the first
    cone's flank (less than APEX_PROMINENCE) is part of that crown."""
    x, y = np.meshgrid(np.arange(0.25, 20.0, 0.5), np.arange(0.25, 20.0, 0.5))
    values = 20.0 * (1.0 - np.hypot(x - 10.0, y - 10.0) / 4.0)
    if second == "cone":
        values = np.maximum(values, 17.0 * (1.0 - np.hypot(x - 12.0, y - 10.0) / 3.0))
    else:
        values += 0.3 * np.exp(-np.hypot(x - 12.0, y - 10.0) ** 2 / 0.1)
    values[values <= 0.0] = np.nan
    params = TreeParams(smoothing=0.0)
    assert len(find_tops(values, values, 0.5, params)[0]) == 1  # one window holds both
    crowns = segment_crowns(Raster(values, 0.0, 0.0, 0.5), params)
    assert len(crowns) == tops
    assert np.all(crowns.crown_cells() > 4)


def test_every_cone_top_is_found_once_and_nothing_else():
    crowns = crowns_of(*cone_forest(2))
    nearest, distance = _matched_tops(crowns, CONES)
    assert len(crowns) == len(CONES)
    assert sorted(nearest.tolist()) == list(range(len(CONES)))
    assert distance.max() < 0.75


def _cells_reaching(x, y, radius, cell, size):
    """Area of the cells of a grid some part of which lies within ``radius`` of (x, y): the
    crown of a CHM that keeps each cell's highest point."""
    edges = np.arange(0.0, size, cell)
    left, bottom = np.meshgrid(edges, edges)
    dx = np.maximum(np.maximum(left - x, x - left - cell), 0.0)
    dy = np.maximum(np.maximum(bottom - y, y - bottom - cell), 0.0)
    return np.count_nonzero(np.hypot(dx, dy) < radius) * cell**2


def test_crown_areas_are_close_to_the_cones_above_min_height():
    params = TreeParams()
    crowns = crowns_of(*cone_forest(3), params)
    nearest, _ = _matched_tops(crowns, CONES)
    area = crowns.crown_cells() * params.resolution**2
    for k, (x, y, h, r) in enumerate(CONES[i] for i in nearest):
        truth = _cells_reaching(x, y, r * (1.0 - params.min_height / h), 0.5, 36.0)
        assert area[k] == pytest.approx(truth, rel=0.15, abs=1.5), ((x, y, h, r), area[k], truth)


def test_touching_crowns_are_split_between_their_tops():
    cones = [(10.0, 10.0, 20.0, 3.5), (15.0, 10.0, 18.0, 3.5)]  # overlapping by 2 m
    crowns = crowns_of(*cone_forest(4, cones=cones, size=24.0))
    nearest, distance = _matched_tops(crowns, cones)
    assert sorted(nearest.tolist()) == [0, 1] and distance.max() < 0.75
    area = crowns.crown_cells() * 0.25
    assert area.min() > 0.6 * area.max()


def test_a_small_tree_gets_no_bigger_crown_than_its_radius_bound():
    # a 5 m tree standing on a wide low skirt of canopy: without the bound the watershed
    # would give the tree the whole skirt above min_height (4.3 m around it)
    params = TreeParams()
    cones = [(12.0, 12.0, 5.0, 1.2), (12.0, 12.0, 3.5, 10.0)]
    crowns = crowns_of(*cone_forest(5, cones=cones, size=24.0), params)
    assert len(crowns) == 1
    bound = params.crown_radius[0] + params.crown_radius[1] * crowns.top_height[0]
    rows, cols = np.nonzero(crowns.labels)
    reach = np.hypot(rows - crowns.top_row[0], cols - crowns.top_col[0]) * params.resolution
    assert reach.max() <= bound
    di, dj = np.mgrid[-10:11, -10:11] * params.resolution
    in_bound = np.count_nonzero(np.hypot(di, dj) <= bound)
    assert 0.7 * in_bound <= crowns.crown_cells()[0] <= in_bound


def test_a_flat_top_keeps_one_seed():
    values = np.full((21, 21), 1.0)  # below min_height
    values[8:13, 8:13] = 10.0
    crowns = segment_crowns(Raster(values, 0.0, 0.0, 0.5), TreeParams(smoothing=0.0))
    assert len(crowns) == 1
    assert (crowns.top_row[0], crowns.top_col[0]) == (8, 8)


def test_a_scene_without_canopy_has_no_trees():
    xyz = np.array([[3.0, 4.0, 100.0]])
    cells = canopy_cells(xyz, np.zeros(1), np.zeros(1, bool), 0.5)
    chm = chm_raster(cells, 0.5)
    assert len(cells) == 0 and chm.shape == (1, 1) and np.isnan(chm.values).all()
    assert len(segment_crowns(chm, TreeParams())) == 0


def test_no_canopy_above_min_height_gives_no_crowns():
    crowns = segment_crowns(Raster(np.full((5, 5), 1.0), 0.0, 0.0, 0.5), TreeParams())
    assert len(crowns) == 0 and not crowns.labels.any()


def test_segmentation_is_deterministic_and_ignores_the_points_order():
    xyz, height, canopy = cone_forest(6)
    first = crowns_of(xyz, height, canopy)
    order = np.random.default_rng(0).permutation(xyz.shape[0])
    again = crowns_of(xyz[order], height[order], canopy[order])
    assert np.array_equal(first.labels, again.labels)
    assert np.array_equal(first.top_keys, again.top_keys)


def test_tops_are_in_the_order_of_their_cell_keys():
    crowns = crowns_of(*cone_forest(7))
    assert np.all(np.diff(crowns.top_keys) > 0)


# --- real scans ----------------------------------------------------------------------------

def _scan_tops(path):
    """Tops (x, y) and heights of the crowns of a scan, classes 3-5 as canopy."""
    import laspy

    from pipeline.terrain import ground_elevation, terrain_model

    las = laspy.read(path)
    code = np.asarray(las.classification)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)[code != 7]
    code = code[code != 7]
    height = xyz[:, 2] - ground_elevation(terrain_model(xyz).dtm, xyz[:, :2])
    crowns = crowns_of(xyz, height, np.isin(code, (3, 4, 5)))
    return crowns.top_xy, crowns.top_height


@pytest.mark.data
def test_the_airborne_and_drone_scans_of_one_patch_find_the_same_trees(shared_data):
    from scipy.spatial import cKDTree

    als = shared_data / "trees" / "ALS_Clip.laz"
    uas = shared_data / "trees" / "UAS_Clip.laz"
    if not (als.is_file() and uas.is_file()):
        pytest.skip("the trees scans are not in the shared data")
    (als_xy, als_h), (uas_xy, uas_h) = _scan_tops(als), _scan_tops(uas)
    assert 12 <= len(als_xy) <= 40 and 12 <= len(uas_xy) <= 40
    assert 25.0 < als_h.max() < 40.0 and abs(als_h.max() - uas_h.max()) < 1.0
    distance, _ = cKDTree(uas_xy).query(als_xy)
    assert np.mean(distance <= 2.0) >= 0.8


# --- parameters ----------------------------------------------------------------------------

@pytest.mark.parametrize("key, value", [
    ("method", "lidar"), ("min_height", -1.0), ("resolution", 0.0), ("smoothing", "a"),
    ("window", (0.0, 0.1)), ("window", (3.0,)), ("crown_radius", (1.0, -0.1)),
    ("breast_height", math.nan), ("fallback_offsets", (0.3, math.inf)),
    ("stem_min_points", 2), ("stem_min_points", 10.5), ("max_dbh", 0.0),
])
def test_tree_params_refuse_bad_values_naming_the_key(key, value):
    with pytest.raises(ConfigError, match=rf"^trees\.{key} "):
        TreeParams(**{key: value})


def test_tree_params_take_lists_from_a_config_file():
    params = TreeParams(window=[4, 0.1], fallback_offsets=[0.2], resolution=1)
    assert params.window == (4.0, 0.1) and params.fallback_offsets == (0.2,)
    assert params.resolution == 1.0 and isinstance(params.resolution, float)


# --- stray points above the canopy ------------------------------------------------------

def test_a_bird_over_the_canopy_sets_no_cell_and_makes_no_tree():
    """Two stray points 60 m above the canopy (one over a crown, one over open ground),
    predicted as canopy: the CHM is that of the forest without them, cell for cell, and the
    trees are the same."""
    xyz, height, canopy = cone_forest(3)
    birds = np.array([[10.2, 10.3, 190.0], [30.0, 5.0, 160.0]])
    with_birds = (np.vstack([xyz, birds]), np.concatenate([height, birds[:, 2] - 100.0]),
                  np.concatenate([canopy, [True, True]]))
    params = TreeParams(method="crowns")
    clean = chm_raster(canopy_cells(xyz, height, canopy, params.resolution), params.resolution)
    chm = chm_raster(canopy_cells(*with_birds, params.resolution), params.resolution)
    assert np.nanmax(chm.values) <= max(h for _, _, h, _ in CONES)
    # cell for cell (the bird over the ground widens the raster by empty cells)
    i0, j0 = round((clean.y0 - chm.y0) / chm.cell), round((clean.x0 - chm.x0) / chm.cell)
    inner = chm.values[i0:i0 + clean.shape[0], j0:j0 + clean.shape[1]]
    np.testing.assert_array_equal(inner, clean.values)
    assert np.isfinite(chm.values).sum() == np.isfinite(clean.values).sum()
    # chunked: the birds in one chunk, the canopy under them in another
    parts = [canopy_cells(xyz, height, canopy, params.resolution),
             canopy_cells(birds, birds[:, 2] - 100.0, np.ones(2, bool), params.resolution)]
    merged = chm_raster(merge_cells(parts), params.resolution)
    np.testing.assert_array_equal(merged.values, chm.values)
    # the same trees, and the birds in none (the one over a crown stands far above it)
    ids, table, _, _ = find_trees(*with_birds, np.zeros(len(with_birds[0]), bool), params)
    want_ids, want, _, _ = find_trees(xyz, height, canopy, np.zeros(len(xyz), bool), params)
    assert len(table) == len(CONES) and table.dtype == want.dtype
    for name in want.dtype.names:
        np.testing.assert_array_equal(table[name], want[name])
    np.testing.assert_array_equal(ids[:len(xyz)], want_ids)
    assert (ids[len(xyz):] == 0).all() and table["height"].max() <= 30.0
