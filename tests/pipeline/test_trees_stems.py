"""Stems: the exact per-chunk slice, circles at breast height and their fallbacks, sees_stems."""

import numpy as np
import pytest

from pipeline.trees import TreeParams
from pipeline.trees.stems import (
    QUALITY_FALLBACK,
    QUALITY_GOOD,
    find_stems,
    merge_slices,
    sees_stems,
    stem_slice,
    thin_slice,
)

PARAMS = TreeParams()
ORIGIN = np.array([500_000.0, 5_500_000.0, 400.0])  # survey-like coordinates


def bark(rng, centre, dbh, heights=(0.8, 2.2), n=600, arc=(0.0, 2 * np.pi), noise=0.002):
    """(n, 4) [x, y, z, height] points on a vertical cylinder over flat ground at ORIGIN z."""
    theta = rng.uniform(*arc, n)
    h = rng.uniform(*heights, n)
    r = dbh / 2 + rng.normal(0.0, noise, n)
    x = ORIGIN[0] + centre[0] + r * np.cos(theta)
    y = ORIGIN[1] + centre[1] + r * np.sin(theta)
    return np.column_stack((x, y, ORIGIN[2] + h, h))


def blob(rng, centre, n=400):
    """(n, 4) scattered points of a shrub or a clump of branches, 0.8-2.2 m high."""
    xy = ORIGIN[:2] + centre + rng.normal(0.0, 0.25, (n, 2))
    h = rng.uniform(0.8, 2.2, n)
    return np.column_stack((xy, ORIGIN[2] + h, h))


def as_slice(points):
    return stem_slice(points[:, :3], points[:, 3], np.ones(len(points), bool), PARAMS)


def same_stems(a, b):
    return all(np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True)
               for f in ("x", "y", "z_base", "dbh", "quality", "fit_height"))


def test_thinning_keeps_the_smallest_point_of_each_voxel_sorted():
    rng = np.random.default_rng(1)
    points = np.round(rng.uniform(0, 0.05, (400, 4)), 3)  # many points share voxels
    points[:50] = points[50:100]  # and some are duplicates
    got = thin_slice(points, 0.01)
    best = {}
    for row in map(tuple, points):
        key = tuple(np.floor(np.array(row[:3]) / 0.01).astype(int))
        best[key] = min(best.get(key, row), row)
    assert np.array_equal(got, np.array(sorted(best.values())))


@pytest.mark.parametrize("n_chunks", [1, 3, 7])
def test_merged_chunk_slices_equal_the_slice_of_all_points(n_chunks):
    rng = np.random.default_rng(n_chunks)
    xyz = ORIGIN + rng.uniform([0, 0, 0], [3, 3, 3], (20_000, 3))
    xyz[:5000] = np.round(xyz[:5000], 2)  # points on voxel edges
    height = xyz[:, 2] - ORIGIN[2]
    mask = rng.random(len(xyz)) < 0.8
    whole = stem_slice(xyz, height, mask, PARAMS)
    chunk = rng.integers(0, n_chunks, len(xyz))
    parts = [stem_slice(xyz[chunk == c], height[chunk == c], mask[chunk == c], PARAMS)
             for c in rng.permutation(n_chunks)]
    assert np.array_equal(merge_slices(parts, PARAMS), whole)
    kept = np.abs(whole[:, 3][:, None] - (1.3 + np.array([0, 0.3, -0.3, 0.6]))).min(axis=1)
    assert len(whole) > 1000 and kept.max() <= PARAMS.slice_half_width
    assert merge_slices([], PARAMS).shape == (0, 4)


def test_circles_at_breast_height_despite_branches_and_noise():
    rng = np.random.default_rng(2)
    truth = [((0.0, 0.0), 0.30), ((3.0, 1.0), 0.12), ((1.0, 4.0), 0.55)]
    parts = [bark(rng, c, d) for c, d in truth]
    for (cx, cy), d in truth:  # a branch leaving each stem at 1.3 m
        t = rng.uniform(0, 0.8, 60)
        parts.append(np.column_stack((ORIGIN[0] + cx + d / 2 + t, ORIGIN[1] + cy + 0 * t,
                                      ORIGIN[2] + 1.3 + 0.2 * t, 1.3 + 0.2 * t)))
    parts.append(blob(rng, (6.0, 6.0)))  # a shrub: no circle
    stems = find_stems(as_slice(np.concatenate(parts)), PARAMS)
    assert len(stems) == 3 and np.all(stems.quality == QUALITY_GOOD)
    for (cx, cy), d in truth:  # stems are sorted by x then y
        i = int(np.argmin(np.hypot(stems.x - ORIGIN[0] - cx, stems.y - ORIGIN[1] - cy)))
        assert stems.dbh[i] == pytest.approx(d, abs=0.005)
        assert np.hypot(stems.x[i] - ORIGIN[0] - cx, stems.y[i] - ORIGIN[1] - cy) < 0.005
    assert np.all(np.diff(stems.x) > 0)
    assert np.allclose(stems.z_base, ORIGIN[2]) and np.all(stems.fit_height == 1.3)


def test_a_hidden_breast_height_falls_back_to_the_section_above():
    rng = np.random.default_rng(3)
    lower = bark(rng, (0.0, 0.0), 0.25, heights=(0.8, 1.12), n=150)
    upper = bark(rng, (0.0, 0.0), 0.24, heights=(1.45, 2.2), n=400)
    stems = find_stems(as_slice(np.concatenate((lower, upper))), PARAMS)
    assert len(stems) == 1 and stems.quality[0] == QUALITY_FALLBACK
    assert stems.fit_height[0] == pytest.approx(1.6) and stems.dbh[0] == pytest.approx(0.24,
                                                                                        abs=0.005)


def test_implausible_circles_are_refused():
    rng = np.random.default_rng(4)
    too_wide = bark(rng, (0.0, 0.0), 2.0, n=4000)  # dbh above max_dbh (1.5 m)
    thin_arc = bark(rng, (10.0, 0.0), 0.4, arc=(0.0, 0.5), n=400)  # 29 degrees of bark
    rough = bark(rng, (20.0, 0.0), 0.2, n=600, noise=0.05)  # most points off any circle
    for points in (too_wide, thin_arc, rough):
        assert len(find_stems(as_slice(points), PARAMS)) == 0
    assert len(find_stems(np.empty((0, 4)), PARAMS)) == 0


def test_same_points_in_any_order_give_the_same_stems_bit_for_bit():
    rng = np.random.default_rng(5)
    points = np.concatenate([bark(rng, (3.0 * i, 0.5 * i), 0.1 + 0.05 * i, n=500)
                             for i in range(5)] + [blob(rng, (1.5, 3.0))])
    slice_ = as_slice(points)
    first = find_stems(slice_, PARAMS)
    assert len(first) == 5
    for seed in range(3):
        shuffled = slice_[np.random.default_rng(seed).permutation(len(slice_))]
        assert same_stems(find_stems(shuffled, PARAMS), first)
    reordered = as_slice(points[rng.permutation(len(points))])
    assert same_stems(find_stems(reordered, PARAMS), first)


def test_sees_stems_where_a_scan_shows_stems_at_breast_height():
    rng = np.random.default_rng(6)
    stems = np.concatenate([bark(rng, (4.0 * i, 4.0 * j), 0.3, n=300)
                            for i in range(3) for j in range(3)])
    area = 12.0 * 12.0  # nine stems on 144 m2: 625 per hectare
    assert sees_stems(as_slice(stems), area, PARAMS)
    assert not sees_stems(as_slice(stems), 10_000.0 * 9 / 20, PARAMS)  # 20 per hectare
    # an airborne scan: a few points per stem at 1.3 m, scattered
    sparse = np.concatenate([bark(rng, (4.0 * i, 4.0 * j), 0.3, n=4)
                             for i in range(3) for j in range(3)])
    assert not sees_stems(as_slice(np.concatenate((sparse, blob(rng, (5.0, 5.0))))), area,
                          PARAMS)
    assert not sees_stems(as_slice(stems), 0.0, PARAMS)


def test_stems_of_a_synthetic_plot_match_its_trees():
    from pipeline.synth import synthetic_scene
    from pipeline.trees.instances import match_tables, matched_errors

    scene = synthetic_scene(1)
    xyz = scene.xyz
    height = xyz[:, 2] - scene.ground_height(xyz[:, 0], xyz[:, 1])
    stems = find_stems(stem_slice(xyz, height, scene.labels == 5, PARAMS), PARAMS)
    ox, oy, _ = scene.origin
    truth = scene.trees[(scene.trees["x"] >= ox) & (scene.trees["x"] < ox + scene.size)
                        & (scene.trees["y"] >= oy) & (scene.trees["y"] < oy + scene.size)]
    found = np.zeros(len(stems), dtype=[("tree_id", "u4"), ("x", "f8"), ("y", "f8"),
                                        ("dbh", "f8")])
    found["tree_id"] = np.arange(1, len(stems) + 1)
    found["x"], found["y"], found["dbh"] = stems.x, stems.y, stems.dbh
    matching = match_tables(truth, found, max_distance=0.3)
    assert matching.precision == 1.0 and matching.recall >= 0.75
    assert matched_errors(matching, truth, found, ("dbh",))["dbh"]["rmse"] <= 0.01


def test_overlapping_circles_keep_the_better_stem():
    rng = np.random.default_rng(7)
    # a stem seen at breast height inside a ring of branch ends fitted at 1.9 m (two clusters:
    # the rings lie 0.3 m apart), and a lone stem seen at 1.9 m only
    stem = bark(rng, (0.0, 0.0), 0.20, n=600)
    whorl = bark(rng, (0.05, 0.0), 0.80, heights=(1.75, 2.05), n=600)
    lone = bark(rng, (3.0, 0.0), 0.20, heights=(1.75, 2.05), n=300)
    stems = find_stems(as_slice(np.concatenate((stem, whorl, lone))), PARAMS)
    assert stems.quality.tolist() == [QUALITY_GOOD, QUALITY_FALLBACK]
    assert stems.dbh == pytest.approx([0.20, 0.20], abs=0.005)
    assert stems.fit_height.tolist() == pytest.approx([1.3, 1.9])


def _candidates(path):
    """xyz, heights above the ground model, and every point but ground and noise."""
    import laspy

    from pipeline.terrain import ground_elevation, terrain_model

    las = laspy.read(path)
    xyz = np.column_stack((las.x, las.y, las.z)).astype(np.float64)
    height = xyz[:, 2] - ground_elevation(terrain_model(xyz).dtm, xyz[:, :2])
    return xyz, height, ~np.isin(np.asarray(las.classification), (2, 7))


def test_a_real_terrestrial_plot_in_chunks_and_an_airborne_scan(shared_data):
    xyz, height, mask = _candidates(shared_data / "trees" / "TreeLS_pine_plot.laz")
    whole = stem_slice(xyz, height, mask, PARAMS)
    chunk = np.floor((xyz[:, 0] - xyz[:, 0].min()) / 2.5).astype(int)  # strips of 2.5 m
    parts = [stem_slice(xyz[chunk == c], height[chunk == c], mask[chunk == c], PARAMS)
             for c in np.unique(chunk)[::-1]]
    assert np.array_equal(merge_slices(parts, PARAMS), whole)
    stems = find_stems(whole, PARAMS)
    good = stems.quality == QUALITY_GOOD
    assert good.sum() >= 12  # 17 on the 10 m x 10 m plot when measured
    assert np.all((stems.dbh[good] > 0.08) & (stems.dbh[good] < 0.45))
    area = float(np.ptp(xyz[:, 0]) * np.ptp(xyz[:, 1]))
    assert sees_stems(whole, area, PARAMS)
    xyz, height, mask = _candidates(shared_data / "trees" / "ALS_Clip.laz")
    area = float(np.ptp(xyz[:, 0]) * np.ptp(xyz[:, 1]))
    assert not sees_stems(stem_slice(xyz, height, mask, PARAMS), area, PARAMS)
