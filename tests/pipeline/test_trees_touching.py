"""Stems that touch or lean: two stems a few centimetres apart are two stems and two trees,
each with its own DBH; a leaning stem is fitted across its axis, where it stands at breast
height, and its tree follows it."""

import numpy as np
import pytest

from pipeline.trees import TreeParams, find_trees
from pipeline.trees.stems import find_stems, stem_slice

PARAMS = TreeParams()
ORIGIN = np.array([500_000.0, 5_500_000.0, 400.0])


def leaning_stem(rng, base, dbh, lean=(0.0, 0.0), top=2.2, n=3000, arc=(0.0, 2 * np.pi)):
    """(n, 3) bark points of a cylinder of diameter ``dbh`` standing at ``base`` (x, y) on
    flat ground at ORIGIN, its axis leaning by ``lean`` metres per metre of height, from the
    ground to ``top`` metres high; ``arc`` the angles the scanner sees."""
    axis = np.array([lean[0], lean[1], 1.0])
    axis /= np.linalg.norm(axis)
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    theta = rng.uniform(*arc, n)
    z = rng.uniform(0.0, top, n)
    ring = (dbh / 2 + rng.normal(0.0, 0.002, n))[:, None] * (
        np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2)
    # the ring's point sits at height z: its axis point lies at z - ring_z
    along = z - ring[:, 2]
    centre = np.column_stack([base[0] + lean[0] * along, base[1] + lean[1] * along, along])
    return centre + ring + ORIGIN


def slice_of(xyz):
    return stem_slice(xyz, xyz[:, 2] - ORIGIN[2], np.ones(len(xyz), bool), PARAMS)


@pytest.mark.parametrize("arc", [(0.0, 2 * np.pi), (-np.pi / 2, np.pi / 2)])
def test_two_stems_five_centimetres_apart_are_two_stems(arc):
    rng = np.random.default_rng(11)
    # bark 5 cm apart: centres 0.15 + 0.05 + 0.125 m apart; ``arc``: all round, or the
    # half that one scanner on the +x side sees
    xyz = np.concatenate([leaning_stem(rng, (0.0, 0.0), 0.30, arc=arc),
                          leaning_stem(rng, (0.0, 0.325), 0.25, arc=arc)])
    stems = find_stems(slice_of(xyz), PARAMS)
    assert len(stems) == 2
    order = np.argsort(stems.y)
    assert stems.dbh[order] == pytest.approx([0.30, 0.25], abs=0.01)
    assert stems.y[order] - ORIGIN[1] == pytest.approx([0.0, 0.325], abs=0.01)
    assert stems.x[order] - ORIGIN[0] == pytest.approx([0.0, 0.0], abs=0.01)


@pytest.mark.parametrize("lean, arc", [
    ((0.4, 0.2), (-np.pi / 2, np.pi / 2)),  # 24 degrees, seen from one side
    ((0.6, 0.0), (0.0, 2 * np.pi)),  # 31 degrees
    ((0.8, 0.3), (-np.pi / 2, np.pi / 2)),  # 40 degrees
])
def test_a_leaning_stem_keeps_its_axis(lean, arc):
    rng = np.random.default_rng(12)
    xyz = leaning_stem(rng, (0.0, 0.0), 0.30, lean=lean, arc=arc)
    stems = find_stems(slice_of(xyz), PARAMS)
    assert len(stems) == 1
    at = stems.fit_height[0]
    assert stems.x[0] - ORIGIN[0] == pytest.approx(lean[0] * at, abs=0.005)
    assert stems.y[0] - ORIGIN[1] == pytest.approx(lean[1] * at, abs=0.005)
    assert stems.dbh[0] == pytest.approx(0.30, abs=0.005)  # across the axis, not along


def test_two_touching_stems_grow_two_trees():
    rng = np.random.default_rng(13)
    parts, truth, stem = [], [], []
    for k, (y, dbh) in enumerate(((0.0, 0.30), (0.325, 0.25)), start=1):  # bark 5 cm apart
        bark = leaning_stem(rng, (0.0, y), dbh, top=12.0, n=8000)
        z = rng.uniform(6.0, 12.0, 4000)
        r = 1.2 * (12.0 - z) / 6.0 * np.sqrt(rng.uniform(0, 1, z.size))
        a = rng.uniform(0, 2 * np.pi, z.size)
        crown = np.column_stack([r * np.cos(a), y + r * np.sin(a), z]) + ORIGIN
        parts += [bark, crown]
        truth.append(np.full(len(bark) + len(crown), k))
        stem.append(np.r_[np.ones(len(bark), bool), np.zeros(len(crown), bool)])
    xyz, truth, stem = np.concatenate(parts), np.concatenate(truth), np.concatenate(stem)
    height = xyz[:, 2] - ORIGIN[2]
    everything = np.ones(len(xyz), bool)
    ids, table, _, method = find_trees(xyz, height, everything, everything,
                                       TreeParams(method="stems"), area=100.0)
    assert method == "stems" and len(table) == 2
    assert np.sort(table["dbh"]) == pytest.approx([0.25, 0.30], abs=0.01)
    own = [np.bincount(ids[stem & (truth == k)]).argmax() for k in (1, 2)]
    assert sorted(own) == [1, 2]  # each stem its own tree
    for k in (1, 2):
        share = np.mean(ids[stem & (truth == k)] == own[k - 1])
        assert share > 0.9, (k, share)


def test_a_shred_of_bark_beside_a_stem_at_one_height_is_no_second_stem():
    rng = np.random.default_rng(14)
    stem = leaning_stem(rng, (0.0, 0.0), 0.20)
    # a small ring of points around breast height only (a branch stub, a loose shred)
    shred = leaning_stem(rng, (0.0, 0.17), 0.07, n=400)
    shred = shred[np.abs(shred[:, 2] - ORIGIN[2] - 1.3) < 0.12]
    stems = find_stems(slice_of(np.concatenate([stem, shred])), PARAMS)
    assert len(stems) == 1 and stems.dbh[0] == pytest.approx(0.20, abs=0.01)
    # the same ring all the way up is a second stem
    sapling = leaning_stem(rng, (0.0, 0.17), 0.07, n=2000)
    assert len(find_stems(slice_of(np.concatenate([stem, sapling])), PARAMS)) == 2
