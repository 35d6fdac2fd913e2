"""Thinned copies of a cloud, to train at the densities a model will meet.

A model trained at 25-58 points/m² sees a 5 points/m² crown as a sheet. Learned airborne
classifiers therefore also train on thinned copies of their tiles. Here a copy keeps a point
when the hash of its global id (:func:`pipeline.cascade.sampling.id_hash`) is below the kept
fraction: the same points every run and whatever the chunking (the choice of a point looks at
no other point), and the copies of one seed are nested (an 8 % copy is a subset of the 20 %
one). The hash is seeded apart from the training sample's, so the rows a thinned copy keeps
are independent of the rows that then train the forests.

The density of a cloud (:func:`point_density`) is its number of points over the area of the
square XY cells of ``cell`` metres it occupies (anchored at 0): the holes and the ragged edge
of a tile do not dilute it, and the cells are wide enough to be rarely empty inside a sparse
survey (at 1 point/m², a 2 m cell is empty 2 % of the time).
"""

import numpy as np

from pipeline import grid
from pipeline.cascade.sampling import id_hash
from pipeline.checks import finite_number
from pipeline.errors import InputError

#: Mixed into the seed of the thinning hash, so that it is not the training sample's.
THINNING_STREAM = 0x7417
#: Default cell side (metres) of :func:`point_density`.
DEFAULT_DENSITY_CELL = 2.0


def _check_positive(value, name: str) -> float:
    return finite_number(value, name, error=InputError)


def thinning_seed(seed: int) -> int:
    """The seed of the thinning hash for a run's ``seed`` (a stream apart from sampling)."""
    state = np.random.SeedSequence([int(seed), THINNING_STREAM]).generate_state(1)[0]
    return int(state) & 0x7FFFFFFF


def thinned_mask(ids, fraction: float, seed: int = 0) -> np.ndarray:
    """bool (N,): the points a copy thinned to ``fraction`` of the cloud keeps.

    ``ids`` int64 (N,) global point ids; ``fraction`` in (0, 1]; the same (id, seed) is
    always kept or always dropped, and a smaller fraction keeps a subset of a larger one.
    """
    fraction = _check_positive(fraction, "fraction")
    if fraction > 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    ids = np.asarray(ids)
    if ids.ndim != 1 or not (ids.size == 0 or np.issubdtype(ids.dtype, np.integer)):
        raise InputError(f"ids must be 1-D integer global ids, got {ids.dtype} {ids.shape}")
    return id_hash(ids, thinning_seed(seed)) < fraction


def point_density(xy, cell: float = DEFAULT_DENSITY_CELL) -> float:
    """Points per m² of ``xy`` (float64 (N, 2+), only the first two columns are read) over
    the area of the cells of side ``cell`` metres that hold a point; 0.0 for no points."""
    keys = cell_keys(xy, cell)
    if len(keys) == 0:
        return 0.0
    cell = float(cell)
    return len(keys) / (len(np.unique(keys)) * cell * cell)


def cell_keys(xy, cell: float = DEFAULT_DENSITY_CELL) -> np.ndarray:
    """int64 (N,): one key per point of ``xy`` (float64 (N, 2+)) for the XY cell of side
    ``cell`` metres it falls in, as :func:`point_density` counts the cells: the cells a cloud
    read in pieces occupies are the union of its pieces' keys (``np.union1d``); the keys of
    :func:`pipeline.grid.cell_keys`."""
    cell = _check_positive(cell, "cell")
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise InputError(f"xy must be of shape (N, 2) or (N, 3), got {xy.shape}")
    if not np.isfinite(xy[:, :2]).all():
        raise InputError("xy holds NaN or infinite coordinates")
    return grid.cell_keys(xy[:, 0], xy[:, 1], cell)


def cells_density(n_points: int, n_cells: int, cell: float = DEFAULT_DENSITY_CELL) -> float:
    """Points per m² of ``n_points`` in ``n_cells`` occupied cells of side ``cell`` metres
    (:func:`point_density` of a cloud counted in pieces); 0.0 for no points."""
    cell = _check_positive(cell, "cell")
    return n_points / (n_cells * cell * cell) if n_points else 0.0


def thinning_fraction(density: float, target: float) -> float:
    """The fraction of points that brings a cloud of ``density`` points/m² to ``target``
    points/m²: target / density, at most 1 (a copy is never denser than its cloud)."""
    density = _check_positive(density, "density")
    target = _check_positive(target, "target")
    return min(1.0, target / density)


def thinned_to_density(xyz, ids, target: float, seed: int = 0,
                       cell: float = DEFAULT_DENSITY_CELL) -> np.ndarray:  # fmt: skip
    """int64 rows of ``xyz`` (float64 (N, 3)) a copy keeps to reach ``target`` points/m².

    The fraction is taken from the density of the whole cloud given (:func:`point_density`,
    a scene or a tile, never a chunk: a chunk's density would change the fraction), then
    each point is kept by :func:`thinned_mask` of its id in ``ids`` (int64 (N,)).
    """
    ids = np.asarray(ids)
    if len(ids) != len(xyz):
        raise InputError(f"ids must have one entry per point ({len(xyz)}), got {len(ids)}")
    if len(ids) == 0:
        return np.zeros(0, dtype=np.int64)
    fraction = thinning_fraction(point_density(xyz, cell), target)
    return np.flatnonzero(thinned_mask(ids, fraction, seed))
