"""Every stage of a chunk in one pass equals the cascade computed stage by stage over the
whole cloud, for the chunk's core points, bit for bit, as soon as its halo reaches
:func:`one_pass_halo`; one context radius less, and the border points differ."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from sklearn.ensemble import RandomForestClassifier

from pipeline.cascade import one_pass, one_pass_halo, predict_stage_proba, stage_context
from pipeline.cascade.one_pass import SLACK, context_rows, ring_width, stage_rows
from pipeline.cascade.stage import stage_input
from pipeline.features.density import VOXEL_CAP, VOXELS_PER_RADIUS, capped_halo
from pipeline.tiling import box_distance

R1, R2, REACH, N_CLASSES = 0.6, 0.3, 0.9, 3


def neighbourhood_features(xyz, rows, reach=REACH):
    """Two features of each point of ``rows`` that depend on every point within ``reach``
    of it (and NaN where it has no neighbour): a stand-in for a feature set with that
    reach."""
    tree = cKDTree(xyz)
    out = np.empty((len(rows), 2), np.float32)
    for i, row in enumerate(rows):
        near = [j for j in tree.query_ball_point(xyz[row], reach) if j != row]
        z = xyz[near, 2]
        out[i] = (z.mean() - xyz[row, 2], z.std()) if near else (np.nan, np.nan)
    return out


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(5)
    xyz = rng.uniform([0, 0, 0], [12, 12, 3], size=(3000, 3))
    xyz[:5] = [[20, 20, 0], [30, 30, 0], [40, 40, 0], [50, 50, 0], [60, 60, 0]]  # isolated
    ids = rng.permutation(10 * len(xyz))[:len(xyz)].astype(np.int64)
    labels = (xyz[:, 2] > 1.5).astype(int) + (xyz[:, 0] > 6)
    forests = []
    for stage in range(3):
        x = rng.normal(size=(400, 2 + 2 * N_CLASSES)).astype(np.float32)  # + uniform context
        forests.append(RandomForestClassifier(n_estimators=5, random_state=stage).fit(
            x, rng.integers(0, N_CLASSES, 400)))
    return xyz, ids, labels, forests


def staged_over_the_cloud(xyz, ids, forests, mode, max_neighbors=None):
    """Every stage's probabilities of every point, each stage over the whole cloud."""
    features = neighbourhood_features(xyz, np.arange(len(xyz)))
    probas, context = [], None
    for forest in forests:
        proba = predict_stage_proba(forest, stage_input(features, context, N_CLASSES), N_CLASSES)
        probas.append(proba)
        context = stage_context(xyz, proba, mode, r1=R1, r2=R2, max_neighbors=max_neighbors,
                                ids=ids)
    return probas, np.isnan(features).any(axis=1)


def window_of(xyz, box, halo):
    """Rows of the chunk's core (inside ``box``) and of its halo, cut as ingest cuts them."""
    x0, y0, x1, y1 = box
    x, y = xyz[:, 0], xyz[:, 1]
    core = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
    grown = (x >= x0 - halo) & (x < x1 + halo) & (y >= y0 - halo) & (y < y1 + halo)
    return np.flatnonzero(core), np.flatnonzero(grown & ~core)


@pytest.mark.parametrize("mode, max_neighbors", [("soft", None), ("hard", None), ("soft", 8)])
@pytest.mark.parametrize("n_stages", [1, 2, 3])
def test_one_pass_equals_the_staged_cascade(cloud, mode, max_neighbors, n_stages):
    xyz, ids, _, forests = cloud
    forests = forests[:n_stages]
    expected, undefined = staged_over_the_cloud(xyz, ids, forests, mode, max_neighbors)
    box = (3.0, 4.0, 7.5, 8.0)
    core, halo = window_of(xyz, box, one_pass_halo(REACH, R1, n_stages))
    window = np.concatenate([core, halo])
    probas, flags = one_pass(xyz[window], ids[window], len(core), box,
                             lambda rows: neighbourhood_features(xyz[window], rows), forests,
                             n_classes=N_CLASSES, mode=mode, r1=R1, r2=R2,
                             max_neighbors=max_neighbors)
    assert len(probas) == n_stages
    for stage, proba in enumerate(probas):
        assert np.array_equal(proba, expected[stage][core]), f"stage {stage + 1}"
    assert np.array_equal(flags, undefined[core])


def test_a_narrower_halo_changes_the_last_stage(cloud):
    """The check above can fail: with the features' reach alone for a halo (enough for a
    stage-by-stage cascade) the rings of the earlier stages lack their neighbours."""
    xyz, ids, _, forests = cloud
    expected, _ = staged_over_the_cloud(xyz, ids, forests, "soft")
    box = (3.0, 4.0, 7.5, 8.0)
    core, halo = window_of(xyz, box, REACH)
    window = np.concatenate([core, halo])
    probas, _ = one_pass(xyz[window], ids[window], len(core), box,
                         lambda rows: neighbourhood_features(xyz[window], rows), forests,
                         n_classes=N_CLASSES, mode="soft", r1=R1, r2=R2, max_neighbors=None)
    assert not np.array_equal(probas[2], expected[2][core])


def test_stage_rows_nest_and_hold_every_context_neighbour(cloud):
    """Each stage's rows hold the neighbours within r1 of the next stage's rows, and the
    next stage's context searches every point of their density voxels (which decide
    whether a piled-up point counts); the last stage is the core alone (halo points on the
    box's edge included in no core)."""
    xyz, *_ = cloud
    box = (3.0, 4.0, 7.5, 8.0)
    core, halo = window_of(xyz, box, one_pass_halo(REACH, R1, 4))
    window = xyz[np.concatenate([core, halo])]
    rows = stage_rows(window, len(core), box, R1, 4)
    searched = context_rows(window, len(core), box, R1, 4)
    assert np.array_equal(rows[-1], np.arange(len(core))) and searched[0] is None
    tree = cKDTree(window)
    for outer, inner, search in zip(rows, rows[1:], searched[1:]):
        assert set(inner) <= set(outer) <= set(search) and np.all(np.diff(outer) > 0)
        counted = {j for i in inner for j in tree.query_ball_point(window[i], R1)}
        assert counted <= set(outer)
        # and no other beyond the core than the points the next stage's context counts
        # (within the slack)
        slack = {j for i in inner for j in tree.query_ball_point(window[i], R1 + SLACK)}
        assert set(outer) <= slack | set(range(len(core)))
        needed = {j for i in inner for j in tree.query_ball_point(window[i], capped_halo(R1))}
        assert needed <= set(search)
        assert len(outer) < len(search)  # no stage computed for the voxels' other points
    # fewer than every halo point within the first stage's ring width of the box
    band = box_distance(window[len(core):], box) <= ring_width(R1, 4)
    assert len(rows[0]) - len(core) < np.count_nonzero(band)


class ContextEcho:
    """A stage whose probabilities are the S1 frequencies of its context: any neighbour
    counted or not shows."""

    classes_ = np.arange(N_CLASSES)

    def predict_proba(self, x):
        return x[:, -2 * N_CLASSES:-N_CLASSES]


@pytest.mark.parametrize("mode", ["soft", "hard"])
def test_one_pass_counts_the_piled_voxels_as_the_whole_cloud(cloud, mode):
    """A voxel holding more points than the cap, straddling r1 of the core: which of its
    points count depends on its points beyond r1, which the one pass searches without
    computing a stage for them."""
    xyz, ids, _, forests = cloud
    box = (3.0, 4.0, 7.5, 8.0)
    side = R1 / VOXELS_PER_RADIUS
    # a core point on the box's edge, and 3 caps of points in the voxel whose near third
    # lies within r1 of it and whose far part lies beyond the first stage's ring
    edge = ring_width(R1, 2)
    low = np.ceil((8.0 + edge - side) / side) * side
    assert 8.0 + R1 > low and low + side > 8.0 + edge
    rng = np.random.default_rng(9)
    corner = np.array([np.floor(5.0 / side) * side, low, np.floor(1.0 / side) * side])
    pile = corner + rng.uniform(0.0, side, size=(3 * VOXEL_CAP, 3))
    query = corner + [side / 2, 0.0, side / 2]
    query[1] = 8.0 - 1e-6
    xyz = np.concatenate([xyz, [query], pile])
    ids = np.concatenate([ids, 10 * len(ids) + rng.permutation(len(pile) + 1)])
    forests = [forests[0], ContextEcho()]  # stage 2 answers its context's frequencies
    expected, _ = staged_over_the_cloud(xyz, ids, forests, mode)
    core, halo = window_of(xyz, box, one_pass_halo(REACH, R1, 2))
    window = np.concatenate([core, halo])
    probas, _ = one_pass(xyz[window], ids[window], len(core), box,
                         lambda rows: neighbourhood_features(xyz[window], rows), forests,
                         n_classes=N_CLASSES, mode=mode, r1=R1, r2=R2, max_neighbors=None)
    assert np.array_equal(probas[1], expected[1][core])


def test_box_distance_is_the_halo_measure():
    box = (0.0, 0.0, 2.0, 1.0)
    xy = np.array([[1, 0.5], [2.5, 0.5], [-1, 3], [3, -2], [2, 1]], float)
    assert box_distance(xy, box).tolist() == [0.0, 0.5, 2.0, 2.0, 0.0]
    open_box = (-np.inf, 0.0, np.inf, 1.0)  # an outer chunk, open along x
    assert box_distance(xy, open_box).tolist() == [0.0, 0.0, 2.0, 2.0, 0.0]


def test_one_pass_halo_adds_a_context_reach_per_later_stage():
    reach = capped_halo(0.5)  # r1 and the voxels that decide which points count
    assert one_pass_halo(REACH, R1, 1) == REACH
    assert one_pass_halo(3.5, 0.5, 2) == pytest.approx(3.5 + reach + 0.01)
    assert one_pass_halo(3.5, 0.5, 3) == pytest.approx(3.5 + 2 * (reach + 0.01))
    # the first stage's ring lies within the halo, with the features' reach beyond it
    for stages in (1, 2, 3):
        assert ring_width(0.5, stages) == pytest.approx((stages - 1) * (0.5 + 0.005))
        assert one_pass_halo(3.5, 0.5, stages) >= 3.5 + ring_width(0.5, stages)
