"""Covariance features: a NumPy eigh oracle, invariances, known shapes, chunk invariance."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.errors import InputError
from pipeline.features.covariance import (
    COVARIANCE_NAMES,
    covariance_features,
    multiscale_covariance,
    multiscale_halo,
    multiscale_names,
)
from pipeline.features.neighbors import radius_neighbors
from pipeline.features.voxel import voxel_representatives
from tests.pipeline.conftest import chunk

COL = {name: k for k, name in enumerate(COVARIANCE_NAMES)}
SHAPE = [COL[n] for n in ("linearity", "planarity", "scattering", "omnivariance", "anisotropy",
                          "eigenentropy", "change_of_curvature", "sum_of_eigenvalues")]


def reference(points):
    """The features of one neighbourhood with np.linalg.eigh, in float64."""
    if len(points) < 3:
        return np.full(len(COVARIANCE_NAMES), np.nan)
    centred = points - points.mean(axis=0)
    w, vec = np.linalg.eigh(centred.T @ centred / len(points))
    l3, l2, l1 = np.maximum(w, 0.0)
    e = np.array([l1, l2, l3]) / (l1 + l2 + l3)
    nz = abs(vec[2, 0])
    return np.array([
        (l1 - l2) / l1, (l2 - l3) / l1, l3 / l1, np.prod(e) ** (1 / 3), (l1 - l3) / l1,
        -sum(x * np.log(x) for x in e if x > 0), e[2], 1 - nz, nz, abs(vec[2, 2]), w.sum(),
    ])  # fmt: skip


@pytest.fixture(scope="module")
def scene():
    """A rough ground, a wall, a pole and a bush: planes, lines and volumes."""
    rng = np.random.default_rng(11)
    ground = np.column_stack([rng.uniform(0, 8, (6000, 2)), rng.normal(0, 0.01, 6000)])
    wall = np.column_stack([rng.uniform(0, 8, 800), 6.0 + rng.normal(0, 0.01, 800),
                            rng.uniform(0, 2, 800)])  # fmt: skip
    pole = np.column_stack([1 + rng.normal(0, 0.01, (300, 2)), rng.uniform(0, 3, 300)])
    bush = rng.normal([2.5, 1.5, 0.6], 0.3, (900, 3))
    xyz = np.vstack([ground, wall, pole, bush]) + [640_000.0, 5_200_000.0, 250.0]
    ids = rng.permutation(len(xyz)).astype(np.int64) * 3 + 17
    return xyz, ids


def test_matches_eigh_reference(scene):
    xyz, ids = scene
    query = np.arange(0, len(xyz), 3)
    nbr_idx, nbr_ptr = radius_neighbors(xyz, 0.3, 48, query=query, ids=ids)
    got = covariance_features(xyz, nbr_idx, nbr_ptr, query)
    assert got.dtype == np.float32 and got.shape == (len(query), len(COVARIANCE_NAMES))
    want = np.array([reference(xyz[nbr_idx[nbr_ptr[i]:nbr_ptr[i + 1]]] - xyz[q])
                     for i, q in enumerate(query)])  # fmt: skip
    finite = np.isfinite(want).all(axis=1)
    assert finite.mean() > 0.95
    np.testing.assert_array_equal(np.isnan(got), ~finite[:, None] | np.isnan(want))
    for col in SHAPE:
        scale = np.abs(want[finite, col]).max()
        np.testing.assert_allclose(got[finite, col], want[finite, col], rtol=2e-5,
                                   atol=1e-5 * scale, err_msg=COVARIANCE_NAMES[col])
    # eigenvectors are well defined only where their eigenvalue is apart from the others
    lam = np.sort(np.array([np.linalg.eigvalsh(np.cov((xyz[nbr_idx[nbr_ptr[i]:nbr_ptr[i + 1]]]
                                                        ).T, bias=True))
                            for i in np.flatnonzero(finite)]), axis=1)  # fmt: skip
    gap_normal = (lam[:, 1] - lam[:, 0]) / lam[:, 2] > 1e-3
    gap_principal = (lam[:, 2] - lam[:, 1]) / lam[:, 2] > 1e-3
    vectors = [COL["verticality"], COL["normal_z"]]
    np.testing.assert_allclose(got[finite][gap_normal][:, vectors],
                               want[finite][gap_normal][:, vectors], atol=1e-4)  # fmt: skip
    np.testing.assert_allclose(got[finite][gap_principal][:, COL["principal_z"]],
                               want[finite][gap_principal][:, COL["principal_z"]], atol=1e-4)


def test_rotation_and_translation_invariance(scene):
    xyz, ids = scene
    query = np.arange(0, len(xyz), 5)
    nbr_idx, nbr_ptr = radius_neighbors(xyz, 0.3, 48, query=query, ids=ids)
    base = covariance_features(xyz, nbr_idx, nbr_ptr, query)
    rot = Rotation.from_euler("zyx", [0.7, -0.4, 1.1]).as_matrix()
    moved = (xyz - xyz.mean(axis=0)) @ rot.T
    rotated = covariance_features(moved, nbr_idx, nbr_ptr, query)  # same neighbour lists
    finite = np.isfinite(base).all(axis=1)
    # atol: on a line l3 is rounding noise, whose cube root (omnivariance) is ~1e-6
    np.testing.assert_allclose(rotated[finite][:, SHAPE], base[finite][:, SHAPE],
                               rtol=1e-4, atol=1e-5)  # fmt: skip
    assert not np.allclose(rotated[finite][:, COL["normal_z"]], base[finite][:, COL["normal_z"]],
                           atol=1e-2)  # orientation features do see the rotation


def test_known_shapes():
    rng = np.random.default_rng(4)
    g = np.linspace(-1, 1, 15)
    horizontal = np.column_stack([np.repeat(g, 15), np.tile(g, 15), np.zeros(225)])
    tilt = Rotation.from_euler("x", 0.5).as_matrix()
    pole = np.column_stack([np.zeros((50, 2)), np.linspace(0, 1, 50)])
    wire = np.column_stack([np.linspace(0, 1, 50), np.zeros((50, 2))])
    blob = rng.normal(0, 1, (400, 3))
    parts = [horizontal, horizontal @ tilt.T, pole, wire, blob]
    xyz = np.vstack([p + [10.0 * k, 0, 0] for k, p in enumerate(parts)])
    sizes = np.cumsum([0] + [len(p) for p in parts])
    nbr_idx = np.arange(len(xyz))
    query = sizes[:-1]
    f = covariance_features(xyz, nbr_idx, sizes, query)
    col = COL
    assert f[0, col["planarity"]] == pytest.approx(1.0, abs=1e-6)
    assert f[0, col["change_of_curvature"]] == 0.0 and f[0, col["linearity"]] < 1e-6
    assert f[0, col["normal_z"]] == 1.0 and f[0, col["verticality"]] == 0.0
    assert abs(f[1, col["normal_z"]] - np.cos(0.5)) < 1e-6 and f[1, col["planarity"]] > 0.999
    for row in (2, 3):  # lines
        assert f[row, col["linearity"]] == pytest.approx(1.0, abs=1e-6)
        assert f[row, col["eigenentropy"]] == pytest.approx(0.0, abs=1e-6)
        assert f[row, col["sum_of_eigenvalues"]] == pytest.approx(np.var(np.linspace(0, 1, 50)))
    assert f[2, col["principal_z"]] == 1.0 and f[3, col["principal_z"]] == 0.0
    assert f[4, col["scattering"]] > 0.7 and f[4, col["eigenentropy"]] > 1.0
    assert f[4, col["omnivariance"]] == pytest.approx(1 / 3, abs=0.02)


def test_too_few_or_coincident_neighbours_give_nan():
    xyz = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 2, 2], [2.0, 2, 2], [2.0, 2, 2]])
    nbr_idx = np.array([0, 0, 1, 2, 3, 4])
    nbr_ptr = np.array([0, 0, 1, 3, 6])
    f = covariance_features(xyz, nbr_idx, nbr_ptr, np.array([0, 0, 1, 2]))
    assert np.isnan(f).all()


def test_rejects_bad_input(scene):
    xyz, _ = scene
    nbr_idx, nbr_ptr = radius_neighbors(xyz[:100], 0.3, 8)
    q = np.arange(100)
    with pytest.raises(ValueError, match="xyz"):
        covariance_features(xyz[:100, :2], nbr_idx, nbr_ptr, q)
    with pytest.raises(ValueError, match="nbr_ptr"):
        covariance_features(xyz[:100], nbr_idx, nbr_ptr[:-1], q)
    with pytest.raises(ValueError, match="nbr_ptr"):
        covariance_features(xyz[:100], nbr_idx[:-1], nbr_ptr, q)
    with pytest.raises(ValueError, match="nbr_idx"):
        covariance_features(xyz[:10], nbr_idx, nbr_ptr, q[:10] * 0)
    with pytest.raises(InputError, match="query"):
        covariance_features(xyz[:100], nbr_idx, nbr_ptr, q + 1)
    for radii in ([], [0.3, -1.0], [0.3, 0.3], [np.nan]):
        with pytest.raises(ValueError, match="radii"):
            multiscale_covariance(xyz, None, None, radii)
    with pytest.raises(ValueError, match="voxel_ratio"):
        multiscale_covariance(xyz, None, None, [0.3], voxel_ratio=0)


def test_names_and_halo():
    names = multiscale_names([0.3, 0.6, 1.2, 2.4])
    assert len(names) == 4 * len(COVARIANCE_NAMES) and len(set(names)) == len(names)
    assert names[0] == "linearity_r0.3" and names[len(COVARIANCE_NAMES)] == "linearity_r0.6"
    assert multiscale_halo([0.6, 2.4]) == pytest.approx(2.4 * (1 + 3**0.5 / 4), rel=1e-5)
    assert multiscale_halo([2.4], voxel_ratio=8) == pytest.approx(2.4 * (1 + 3**0.5 / 8), rel=1e-5)


@pytest.mark.parametrize("ratio", [2.0, 4.0])
def test_multiscale_equals_brute_force_on_representatives(scene, ratio):
    """Bit for bit: every representative within r, ordered by (d2, id), then the CSR kernel."""
    xyz, ids = scene
    radii = [0.25, 0.7]
    query = np.arange(0, len(xyz), 37)
    got = multiscale_covariance(xyz, ids, query, radii, voxel_ratio=ratio)
    assert got.shape == (len(query), 2 * len(COVARIANCE_NAMES)) and got.dtype == np.float32
    for k, r in enumerate(radii):
        reps = voxel_representatives(xyz, ids, r / ratio)
        rows = []
        for q in query:
            d = xyz[reps] - xyz[q]
            d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
            inside = np.flatnonzero(d2 <= r * r)
            rows.append(reps[inside[np.lexsort((ids[reps[inside]], d2[inside]))]])
        nbr_ptr = np.cumsum([0] + [len(row) for row in rows])
        want = covariance_features(xyz, np.concatenate(rows), nbr_ptr, query)
        block = got[:, k * len(COVARIANCE_NAMES) : (k + 1) * len(COVARIANCE_NAMES)]
        np.testing.assert_array_equal(block, want)


@pytest.mark.parametrize("shuffle", [False, True])
def test_multiscale_chunk_invariance(scene, shuffle):
    xyz, ids = scene
    radii = [0.2, 0.5, 1.0]
    whole = multiscale_covariance(xyz, ids, None, radii)
    box = (640_002.0, 640_004.5, 5_200_001.0, 5_200_006.5)
    members, is_core = chunk(xyz, box, multiscale_halo(radii))
    assert len(members) < 0.75 * len(xyz)
    if shuffle:
        perm = np.random.default_rng(2).permutation(len(members))
        members, is_core = members[perm], is_core[perm]
    local = np.flatnonzero(is_core)
    part = multiscale_covariance(xyz[members], ids[members], local, radii)
    np.testing.assert_array_equal(part, whole[members[local]])
    assert np.isfinite(part).all(axis=1).mean() > 0.95


def test_multiscale_is_bounded_on_dense_surfaces():
    """Subsampling makes a dense and a sparse scan of the same plane look alike."""
    rng = np.random.default_rng(9)
    dense = np.column_stack([rng.uniform(0, 3, (60_000, 2)), rng.normal(0, 0.005, 60_000)])
    sparse = dense[::20]
    query = np.flatnonzero((np.abs(sparse[:, :2] - 1.5) < 0.5).all(axis=1))
    a = multiscale_covariance(dense, None, query * 20, [0.5])
    b = multiscale_covariance(sparse, None, query, [0.5])
    np.testing.assert_allclose(np.nanmedian(a, axis=0), np.nanmedian(b, axis=0), atol=0.03)
    assert np.nanmedian(a[:, COL["planarity"]]) > 0.9
