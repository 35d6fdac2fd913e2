"""Instance scores: IoU matching of point IDs, table matching, height and DBH errors."""

import itertools

import numpy as np
import pytest

from pipeline.trees.instances import match_instances, match_tables, matched_errors

TABLE = [("tree_id", "u4"), ("x", "f8"), ("y", "f8"), ("height", "f8"), ("dbh", "f8")]


def table(rows):
    return np.array([tuple(r) for r in rows], dtype=TABLE)


def test_hand_made_instances():
    true = [0, 1, 1, 1, 2, 2, 0, 3, 0]
    pred = [0, 5, 5, 0, 7, 7, 7, 9, 9]  # 1~5 (2/3), 2~7 (2/3), 3~9 (1/2: not above 0.5)
    m = match_instances(true, pred)
    assert m.true_ids.tolist() == [1, 2] and m.pred_ids.tolist() == [5, 7]
    assert np.allclose(m.score, [2 / 3, 2 / 3])
    assert (m.n_true, m.n_pred) == (3, 3)
    assert m.precision == m.recall == m.f1 == pytest.approx(2 / 3)
    with pytest.raises(ValueError, match="same points"):
        match_instances([1, 2], [1])
    with pytest.raises(ValueError, match="pred_ids must be integer tree IDs"):
        match_instances([1, 2], [1, -1])
    with pytest.raises(ValueError, match="true_ids must be integer tree IDs"):
        match_instances([1.5, 2.0], [1, 1])
    empty = match_instances([0, 0], [0, 0])
    assert len(empty.true_ids) == 0 and np.isnan(empty.precision) and np.isnan(empty.f1)


@pytest.mark.parametrize("seed", range(20))
def test_instances_equal_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    true = rng.integers(0, 5, n)
    pred = np.where(rng.random(n) < 0.7, true * 10 + 3, rng.integers(0, 40, n))
    pred[true == 0] = np.where(rng.random(int((true == 0).sum())) < 0.5, 0, 3)
    expected = []
    for t in sorted(set(true.tolist()) - {0}):
        for p in sorted(set(pred.tolist()) - {0}):
            inter = np.sum((true == t) & (pred == p))
            union = np.sum((true == t) | (pred == p))
            if inter / union > 0.5:
                expected.append((t, p, inter / union))
    m = match_instances(true, pred)
    assert list(zip(m.true_ids.tolist(), m.pred_ids.tolist())) == [e[:2] for e in expected]
    assert np.allclose(m.score, [e[2] for e in expected])
    assert len(set(m.pred_ids.tolist())) == len(m.pred_ids)  # one-to-one
    assert m.n_true == len(set(true.tolist()) - {0})
    assert m.n_pred == len(set(pred.tolist()) - {0})


def brute_force_tables(truth, found, max_distance, tolerance):
    """(pairs, total distance) of the best matching: most pairs, then least distance."""
    best = (0, 0.0, [])
    n, m = len(truth), len(found)
    for k in range(min(n, m), 0, -1):
        for rows in itertools.combinations(range(n), k):
            for cols in itertools.permutations(range(m), k):
                d = [np.hypot(truth["x"][r] - found["x"][c], truth["y"][r] - found["y"][c])
                     for r, c in zip(rows, cols)]
                ok = all(di <= max_distance for di in d) and all(
                    abs(found["height"][c] - truth["height"][r]) <= tolerance
                    * truth["height"][r] for r, c in zip(rows, cols))
                if ok and (k > best[0] or (k == best[0] and sum(d) < best[1] - 1e-12)):
                    best = (k, sum(d), sorted(zip(rows, cols)))
        if best[0] == k:
            break
    return best


@pytest.mark.parametrize("seed", range(15))
def test_tables_equal_brute_force(seed):
    rng = np.random.default_rng(seed)
    n, m = (int(v) for v in rng.integers(1, 6, 2))
    truth = table([(i + 1, *rng.uniform(0, 3, 2), rng.uniform(10, 20), 0.3)
                   for i in range(n)])
    found = table([(50 - i, *rng.uniform(0, 3, 2), rng.uniform(10, 20), 0.3)
                   for i in range(m)])
    k, total, pairs = brute_force_tables(truth, found, 1.5, 0.2)
    got = match_tables(truth, found, 1.5, height_tolerance=0.2)
    assert len(got.true_ids) == k
    assert got.score.sum() == pytest.approx(total)
    assert got.precision == k / m and got.recall == k / n
    assert np.all(np.diff(got.true_ids.astype(int)) > 0)
    if k:
        assert np.all(got.score <= 1.5)


def test_table_rules_distance_height_and_unknown_heights():
    truth = table([(1, 0.0, 0.0, 20.0, 0.30), (2, 5.0, 0.0, 10.0, 0.20)])
    found = table([(8, 0.4, 0.0, 19.0, 0.32), (9, 5.2, 0.0, 14.0, np.nan)])
    both = match_tables(truth, found, 1.0)
    assert both.true_ids.tolist() == [1, 2] and both.pred_ids.tolist() == [8, 9]
    assert np.allclose(both.score, [0.4, 0.2])
    strict = match_tables(truth, found, 1.0, height_tolerance=0.3)  # 14 m is 40 % above 10
    assert strict.true_ids.tolist() == [1]
    assert match_tables(truth, found, 0.3).true_ids.tolist() == [2]
    found["height"][1] = np.nan  # an unknown height does not refuse the pair
    assert match_tables(truth, found, 1.0, height_tolerance=0.3).true_ids.tolist() == [1, 2]
    # one found tree between two true trees goes to the nearer one
    one = match_tables(truth, table([(3, 3.0, 0.0, 15.0, 0.3)]), 3.5)
    assert one.true_ids.tolist() == [2] and one.recall == 0.5 and one.precision == 1.0


def test_errors_of_the_matched_trees():
    truth = table([(1, 0, 0, 20.0, 0.30), (2, 5, 0, 10.0, 0.20), (3, 9, 9, 15.0, 0.25)])
    found = table([(7, 0, 0, 21.0, 0.34), (8, 5, 0, 8.0, np.nan), (9, 30, 30, 5.0, 0.1)])
    errors = matched_errors(match_tables(truth, found, 0.5), truth, found)
    assert errors["height"]["n"] == 2
    assert errors["height"]["rmse"] == pytest.approx(np.sqrt((1 + 4) / 2))
    assert errors["height"]["bias"] == pytest.approx(-0.5)
    assert errors["dbh"]["n"] == 1  # the NaN DBH is left out
    assert errors["dbh"]["rmse"] == pytest.approx(0.04) and errors["dbh"]["bias"] == pytest.approx(
        0.04)
    far = found[2:]  # the tree at (30, 30) only
    none = matched_errors(match_tables(truth, far, 0.5), truth, far, ("dbh",))
    assert none["dbh"]["n"] == 0 and np.isnan(none["dbh"]["rmse"])


def test_pair_counts_of_batches_merge_to_those_of_all_points():
    from pipeline.trees.instances import match_pairs, merge_pairs, pair_counts

    rng = np.random.default_rng(5)
    true_ids = rng.integers(0, 12, 5000)
    pred_ids = np.where(rng.random(5000) < 0.8, true_ids + 100, rng.integers(0, 150, 5000))
    whole = pair_counts(true_ids, pred_ids)
    cuts = np.sort(rng.choice(np.arange(1, 5000), 7, replace=False))
    parts = [pair_counts(t, p) for t, p in zip(np.split(true_ids, cuts), np.split(pred_ids, cuts))]
    merged = merge_pairs(parts[::-1])
    assert np.array_equal(merged, whole)
    assert merged[:, 2].sum() == 5000
    a, b = match_pairs(merged), match_instances(true_ids, pred_ids)
    assert np.array_equal(a.true_ids, b.true_ids) and np.array_equal(a.pred_ids, b.pred_ids)
    assert len(a.true_ids) == 11  # every tree but 0 keeps most of its points


def test_trees_left_out_are_neither_matches_misses_nor_false_trees():
    """The buffer rule: true tree 2 stands outside the plot. Left out, its match (7) is not
    a found tree and it is not a miss; tree 3 (unmatched) stays a miss, 8 a false tree."""
    true = [1, 1, 1, 2, 2, 2, 3, 3, 0, 0]
    pred = [5, 5, 5, 7, 7, 0, 0, 0, 8, 8]
    full = match_instances(true, pred)
    assert (full.n_true, full.n_pred, len(full.true_ids)) == (3, 3, 2)
    m = match_instances(true, pred, left_out=[2, 40])  # 40: in no tree here, no effect
    assert m.true_ids.tolist() == [1] and m.pred_ids.tolist() == [5]
    assert (m.n_true, m.n_pred, m.left_true, m.left_pred) == (2, 2, 1, 1)
    assert m.precision == m.recall == pytest.approx(0.5)
    # a left-out tree that was not matched: out of the true count only
    m = match_instances(true, pred, left_out=[3])
    assert (m.n_true, m.n_pred, len(m.true_ids)) == (2, 3, 2) and m.recall == 1.0
    none, empty = match_instances(true, pred, None), match_instances(true, pred, left_out=[])
    assert (none.n_true, none.n_pred, none.true_ids.tolist()) == (
        empty.n_true, empty.n_pred, empty.true_ids.tolist())


def test_tables_leave_out_after_matching_with_every_tree():
    """A found tree nearest a left-out true tree pairs with it (and leaves with it) rather
    than with the next true tree, whose score is then a miss, as without the rule."""
    truth = table([(1, 0.0, 0.0, 20.0, 0.3), (2, 1.5, 0.0, 20.0, 0.3), (3, 9.0, 9.0, 15.0, 0.2)])
    found = table([(1, 1.4, 0.0, 20.0, np.nan), (2, 9.0, 9.1, 15.0, np.nan)])
    full = match_tables(truth, found, 2.0)
    assert full.true_ids.tolist() == [2, 3] and (full.n_true, full.n_pred) == (3, 2)
    m = match_tables(truth, found, 2.0, left_out=np.array([2]))
    assert m.true_ids.tolist() == [3] and m.pred_ids.tolist() == [2]
    assert (m.n_true, m.n_pred, m.left_true, m.left_pred) == (2, 1, 1, 1)
    assert m.precision == 1.0 and m.recall == 0.5
    with pytest.raises(ValueError, match="left_out must be integer tree IDs"):
        match_tables(truth, found, 2.0, left_out=[-1])


@pytest.mark.parametrize("seed", range(10))
def test_left_out_in_batches_equals_the_rule_on_brute_force_pairs(seed):
    """The buffer rule on pair counts merged from batches equals the rule applied by hand to
    the brute-force matching of all points: matches without the left-out trees, true trees
    less those left out, found trees less those matched to them."""
    from pipeline.trees.instances import match_pairs, merge_pairs, pair_counts

    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 200))
    true = rng.integers(0, 8, n)
    pred = np.where(rng.random(n) < 0.8, true * 3 + 1, rng.integers(0, 30, n))
    left_out = rng.choice(np.arange(1, 8), size=int(rng.integers(0, 4)), replace=False)
    full = match_instances(true, pred)
    cuts = np.sort(rng.integers(0, n, 3))
    parts = [pair_counts(t, p) for t, p in zip(np.split(true, cuts), np.split(pred, cuts))]
    m = match_pairs(merge_pairs(parts[::-1]), left_out)
    keep = ~np.isin(full.true_ids, left_out)
    assert m.true_ids.tolist() == full.true_ids[keep].tolist()
    assert m.pred_ids.tolist() == full.pred_ids[keep].tolist()
    assert m.n_true == len(set(true.tolist()) - {0} - set(left_out.tolist()))
    assert m.n_pred == full.n_pred - int(np.count_nonzero(~keep))
    assert (m.left_true, m.left_pred) == (full.n_true - m.n_true, int(np.count_nonzero(~keep)))
