"""Groups of small tiles read by one ingest task."""

import numpy as np
import pytest

from pipeline.tiling import group_tiles


def test_small_tiles_of_one_key_share_groups_up_to_the_budget():
    groups = group_tiles([3, 3, 3, 3, 3], [0, 0, 0, 0, 0], budget=7)
    assert groups == [[0, 1], [2, 3], [4]]


def test_a_tile_at_the_budget_or_above_is_alone_and_keys_never_mix():
    groups = group_tiles([2, 10, 2, 2, 7, 2], [0, 0, 1, 0, 1, 1], budget=7)
    assert groups == [[0, 3], [1], [2, 5], [4]]


def test_groups_cover_every_tile_once_in_order_and_hold_at_most_the_budget():
    rng = np.random.default_rng(0)
    n = rng.integers(0, 50, size=2000)
    keys = rng.integers(0, 7, size=2000)
    groups = group_tiles(n, keys, budget=400)
    assert sorted(i for g in groups for i in g) == list(range(2000))
    assert [g[0] for g in groups] == sorted(g[0] for g in groups)
    for g in groups:
        assert g == sorted(g) and len(set(keys[g])) == 1
        assert len(g) == 1 or n[g].sum() <= 400
    # bounded: about the points over the budget, per key
    assert len(groups) <= n.sum() / 400 * 2 + 7


def test_group_tiles_refuses_bad_arguments():
    with pytest.raises(ValueError, match="budget must be an integer >= 1, got 0"):
        group_tiles([1], [0], budget=0)
    with pytest.raises(ValueError, match="keys has 1 entries for 2 tiles"):
        group_tiles([1, 2], [0], budget=5)
