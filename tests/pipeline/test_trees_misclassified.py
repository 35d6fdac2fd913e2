"""Trees grown from their stems through every point that may be a tree: a stem section the
classifier calls dead wood does not cut the tree, and a stump or shrub whose section looks
like a stem grows nothing tall and is no tree."""

import numpy as np

from pipeline.trees import TreeParams, find_trees

ORIGIN = np.array([500_000.0, 5_500_000.0, 0.0])


def cylinder(rng, centre, dbh, top, n, lean=(0.0, 0.0)):
    """(n, 3) points on a stem of diameter ``dbh`` from the ground to ``top`` metres, its
    axis leaning by ``lean`` metres per metre of height."""
    theta = rng.uniform(0.0, 2 * np.pi, n)
    z = rng.uniform(0.0, top, n)
    r = dbh / 2 + rng.normal(0.0, 0.002, n)
    return np.column_stack([centre[0] + lean[0] * z + r * np.cos(theta),
                            centre[1] + lean[1] * z + r * np.sin(theta), z]) + ORIGIN


def crown(rng, centre, low, high, radius, n):
    """(n, 3) points scattered in a cone of ``radius`` from ``low`` to ``high`` metres."""
    z = rng.uniform(low, high, n)
    r = radius * (high - z) / (high - low) * np.sqrt(rng.uniform(0, 1, n))
    a = rng.uniform(0, 2 * np.pi, n)
    return np.column_stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a), z]) + ORIGIN


def tree(rng, centre, height=12.0, dbh=0.3):
    """A stem from the ground to its top and a crown over its upper half."""
    return np.concatenate([cylinder(rng, centre, dbh, height, 6000),
                           crown(rng, centre, height / 2, height, 2.0, 6000)])


def test_a_stem_section_called_dead_wood_does_not_cut_the_tree():
    rng = np.random.default_rng(5)
    xyz = tree(rng, (5.0, 5.0))
    height = xyz[:, 2] - ORIGIN[2]
    dead = (height > 2.0) & (height < 4.0)  # the classifier's mistake, above breast height
    live = ~dead
    params = TreeParams(method="stems")
    # through the live-classified points alone, the tree stops at 2 m
    cut, *_ = find_trees(xyz, height, live, live, params, area=100.0)
    assert np.count_nonzero(cut[height > 4.0]) == 0
    ids, table, _, method = find_trees(xyz, height, live, live, params, area=100.0,
                                       candidates=np.ones(len(xyz), bool))
    assert method == "stems" and len(table) == 1
    assert np.all(ids == 1)
    assert table["height"][0] > 11.5 and table["points"][0] == len(xyz)


def test_a_stump_or_a_shrub_is_no_tree():
    rng = np.random.default_rng(6)
    stump = cylinder(rng, (9.0, 5.0), 0.4, 1.6, 2000)
    xyz = np.concatenate([tree(rng, (5.0, 5.0)), stump])
    height = xyz[:, 2] - ORIGIN[2]
    everything = np.ones(len(xyz), bool)
    params = TreeParams(method="stems")
    ids, table, _, _ = find_trees(xyz, height, everything, everything, params, area=100.0,
                                  candidates=everything)
    assert len(table) == 1
    assert np.hypot(table["x"][0] - ORIGIN[0] - 5.0, table["y"][0] - ORIGIN[1] - 5.0) < 0.05
    assert not ids[-len(stump):].any()
