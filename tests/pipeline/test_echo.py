"""Echo features: per-point values, a brute-force oracle, chunk invariance, no returns."""

import math

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.features.echo import (ECHO_NEIGHBOURHOOD_NAMES, ECHO_POINT_NAMES,
                                    echo_halo, echo_names, echo_neighbourhood_features,
                                    echo_point_features, has_returns)  # fmt: skip
from tests.pipeline.conftest import chunk

RADII = (1.0, 2.0)


@pytest.fixture(scope="module")
def canopy():
    """Ground of single returns under crowns of multi-return pulses, in UTM magnitudes; some
    points without returns (rn = 0, or rn above nr)."""
    rng = np.random.default_rng(5)
    n = 6000
    xyz = np.column_stack([rng.uniform(0, 20, n), rng.uniform(0, 20, n), rng.uniform(0, 3, n)])
    xyz = np.round(xyz, 2) + [600_000.0, 4_000_000.0, 100.0]  # centimetre grid: ties
    nr = rng.integers(1, 5, n)
    nr[xyz[:, 0] < 600_008.0] = 1  # a single-return strip, like a roof
    rn = np.minimum(rng.integers(1, 5, n), nr)
    rn[:40] = 0
    rn[40:60] = nr[40:60] + 1
    ids = rng.permutation(n).astype(np.int64) * 7
    return xyz, ids, rn.astype(np.uint8), nr.astype(np.uint8)


def brute_force(xyz, query, rn, nr, radius):
    """Every point tested by the module's distance expression; the statistics in Python."""
    out = []
    for q in query:
        d = xyz - xyz[q]
        inside = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]) <= radius * radius
        pulses = [(int(a), int(b)) for a, b in zip(rn[inside], nr[inside]) if 1 <= a <= b]
        if not pulses:
            out.append([math.nan] * 3)
            continue
        numbers = np.array([a for a, _ in pulses], dtype=np.float64)
        out.append([sum(b > 1 for _, b in pulses) / len(pulses),
                    sum(a == b for a, b in pulses) / len(pulses), numbers.std()])
    return np.array(out)


def test_point_features():
    rn = np.array([1, 2, 3, 1, 0, 3], dtype=np.uint8)
    nr = np.array([1, 3, 3, 2, 2, 2], dtype=np.uint8)
    got = echo_point_features(rn, nr)
    assert got.shape == (6, len(ECHO_POINT_NAMES)) and got.dtype == np.float32
    expected = [[1, 1, 1, 1], [2 / 3, 0, 0, 0], [1, 0, 1, 0], [0.5, 1, 0, 0]]
    np.testing.assert_allclose(got[:4], expected, rtol=1e-7)
    assert np.isnan(got[4:]).all()  # rn 0, rn above nr: no returns


def test_matches_brute_force(canopy):
    xyz, ids, rn, nr = canopy
    query = np.arange(0, len(xyz), 37)
    got = echo_neighbourhood_features(xyz, ids, query, rn, nr, RADII)
    assert got.shape == (len(query), 3 * len(RADII)) and got.dtype == np.float32
    assert echo_names(RADII)[:3] == tuple(f"{n}_r1" for n in ECHO_NEIGHBOURHOOD_NAMES)
    for i, radius in enumerate(RADII):
        expected = brute_force(xyz, query, rn, nr, radius)
        np.testing.assert_allclose(got[:, 3 * i:3 * i + 3], expected, rtol=2e-6, atol=1e-6)
    # the single-return strip: no multi-return pulse and every point a last return
    strip = xyz[query, 0] < 600_008.0 - 2.0
    assert (got[strip, 0] == 0).all() and (got[strip, 1] == 1).all()
    assert got[~strip & (xyz[query, 0] > 600_010.0), 0].mean() > 0.6  # 3 pulses in 4


@pytest.mark.parametrize("shuffle", [False, True])
def test_chunk_invariance(canopy, shuffle):
    xyz, ids, rn, nr = canopy
    whole = echo_neighbourhood_features(xyz, ids, None, rn, nr, RADII)
    box = (600_005.3, 600_012.2, 4_000_004.1, 4_000_011.35)
    members, is_core = chunk(xyz, box, echo_halo(RADII))
    assert len(members) < 0.5 * len(xyz)
    if shuffle:
        perm = np.random.default_rng(3).permutation(len(members))
        members, is_core = members[perm], is_core[perm]
    local = np.flatnonzero(is_core)
    part = echo_neighbourhood_features(xyz[members], ids[members], local, rn[members],
                                       nr[members], RADII)  # fmt: skip
    np.testing.assert_array_equal(part, whole[members[local]])
    # a halo narrower than the largest radius changes some rows
    members, is_core = chunk(xyz, box, 1.0)
    local = np.flatnonzero(is_core)
    part = echo_neighbourhood_features(xyz[members], ids[members], local, rn[members],
                                       nr[members], RADII)  # fmt: skip
    assert not np.array_equal(part, whole[members[local]])


def test_no_returns(canopy):
    xyz, ids, rn, nr = canopy
    assert has_returns(rn, nr) and not has_returns(None, None)
    assert not has_returns(np.zeros(5, np.uint8), np.zeros(5, np.uint8))
    none = echo_neighbourhood_features(xyz, ids, None, None, None, RADII)
    zeros = np.zeros(len(xyz), dtype=np.uint8)
    assert np.isnan(none).all() and none.shape == (len(xyz), 6)
    assert np.isnan(echo_neighbourhood_features(xyz, ids, None, zeros, zeros, RADII)).all()
    assert np.isnan(echo_point_features(None, None, n_points=4)).all()
    # an isolated point without returns among points with returns: NaN at 1 m only
    lone = np.vstack([xyz[:1] + [0.0, 0.0, 50.0], xyz[:1] + [0.0, 0.0, 51.5]])
    got = echo_neighbourhood_features(lone, None, [0], [0, 1], [1, 2], RADII)
    assert np.isnan(got[0, :3]).all()
    np.testing.assert_array_equal(got[0, 3:], [1.0, 0.0, 0.0])


def test_bad_input(canopy):
    xyz, ids, rn, nr = canopy
    with pytest.raises(InputError, match="both"):
        echo_neighbourhood_features(xyz, ids, None, rn, None, RADII)
    with pytest.raises(InputError, match="return_number"):
        echo_neighbourhood_features(xyz, ids, None, rn[:-1], nr, RADII)
    with pytest.raises(InputError, match="number_of_returns"):
        echo_point_features(rn, nr.astype(np.float64))
    with pytest.raises(ValueError, match="radii"):
        echo_names((1.0, 1.0))
    assert echo_halo(RADII) >= 2.0


def test_crowns_return_several_echoes_roofs_one(shared_data):
    """On IGN LiDAR HD, the sphere around a crown point holds far more multi-return pulses
    than the sphere around a roof point."""
    laspy = pytest.importorskip("laspy")
    las = laspy.read(shared_data / "als" / "StBarth_IGN_LiDARHD_100m.laz")
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    classes = np.asarray(las.classification)
    query = np.arange(0, len(xyz), 25)
    got = echo_neighbourhood_features(xyz, None, query, np.asarray(las.return_number),
                                      np.asarray(las.number_of_returns), (1.0,))  # fmt: skip
    vegetation, building = classes[query] == 5, classes[query] == 6
    assert not np.isnan(got).any()
    crowns, roofs = got[vegetation].mean(axis=0), got[building].mean(axis=0)
    assert crowns[0] > 3 * roofs[0]  # multi-return share: 0.42 against 0.09
    assert roofs[1] > 0.9 > 0.75 > crowns[1]  # last-return share: 0.94 against 0.66
    assert crowns[2] > 2 * roofs[2]  # spread of return numbers: 0.22 against 0.06
