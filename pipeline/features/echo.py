"""Echo features: what a point's return number and number of returns say about its surface.

A laser pulse that meets a crown comes back several times (leaves, branches, the ground under
them); a roof returns it once. Airborne LAS files record, for each point, its return number
rn (1 = first) and the number of returns nr of its pulse. From them:

- per point (:data:`ECHO_POINT_NAMES`): return_ratio rn / nr, first_return (rn == 1),
  last_return (rn == nr) and single_return (nr == 1), the flags as 0.0 / 1.0;
- per neighbourhood at each radius r (:func:`echo_names`, e.g. ``multi_return_share_r1``):
  over every point within r of the query (the sphere of
  :meth:`pipeline.features.neighbors.RadiusIndex.sphere_sums`, with the pile-up cap of
  :mod:`pipeline.features.density`, as the other features), the share of points of
  multi-return pulses (nr > 1), the share of last returns and the standard deviation of the
  return numbers.

A point has returns when 1 <= rn <= nr. A point without (a terrestrial scan, a text file, a
LAS writer that left the fields at 0, an rn above nr) gets NaN in its per-point columns and
counts in no neighbourhood; a neighbourhood without a point with returns gets NaN. A cloud
without the fields at all is passed as ``None``: every column is then NaN.

The neighbourhood values come from exact integer sums (points, multi-return points, last
returns, sum of rn, sum of rn^2) over the sphere, taken in any order; the shares are one
division and the spread sqrt(n * S2 - S1^2) / n of integers. A point's values therefore
depend only on the points within r of it: a chunk with a halo of :func:`echo_halo` gives the
same values as the whole cloud, bit for bit.
"""

import numpy as np

from pipeline.checks import finite_numbers
from pipeline.errors import InputError
from pipeline.features.density import capped_halo, neighbourhood_members
from pipeline.features.neighbors import RadiusIndex, _check_cloud, _check_ids, _check_query

#: Per-point columns of :func:`echo_point_features`.
ECHO_POINT_NAMES: tuple[str, ...] = ("return_ratio", "first_return", "last_return",
                                     "single_return")  # fmt: skip
#: Per-neighbourhood columns of :func:`echo_neighbourhood_features`, repeated per radius.
ECHO_NEIGHBOURHOOD_NAMES: tuple[str, ...] = ("multi_return_share", "last_return_share",
                                             "return_number_std")  # fmt: skip
#: The integer weights summed over a sphere: points with returns, of multi-return pulses,
#: last returns, rn and rn^2.
_N_SUMS = 5


def _check_returns(return_number, number_of_returns, n_points: int):
    """int64 (N,) rn and nr, or (None, None) for a cloud without return fields."""
    if (return_number is None) != (number_of_returns is None):
        raise InputError("give both return_number and number_of_returns, or neither")
    if return_number is None:
        return None, None
    arrays = []
    for name, values in (("return_number", return_number),
                         ("number_of_returns", number_of_returns)):  # fmt: skip
        arr = np.asarray(values)
        integer = arr.size == 0 or np.issubdtype(arr.dtype, np.integer)
        if arr.shape != (n_points,) or not integer:
            raise InputError(f"{name} must be integers of shape ({n_points},), got "
                             f"{arr.dtype} {arr.shape}")  # fmt: skip
        arrays.append(arr.astype(np.int64))
    return arrays[0], arrays[1]


def _valid(rn, nr) -> np.ndarray:
    """bool (N,): which points have returns (1 <= rn <= nr)."""
    return (rn >= 1) & (rn <= nr)


def has_returns(return_number, number_of_returns) -> bool:
    """Whether any point of a cloud has returns (1 <= rn <= nr); False for ``None`` fields."""
    n = 0 if return_number is None else len(return_number)
    rn, nr = _check_returns(return_number, number_of_returns, n)
    return rn is not None and bool(_valid(rn, nr).any())


def return_counts(return_number, number_of_returns) -> tuple[int, int, int]:
    """How many points of a cloud have returns (1 <= rn <= nr), have empty fields (rn or nr
    0, as a writer that left them leaves them) and have rn > nr >= 1, as (valid, empty,
    above) ints; (0, 0, 0) for ``None`` fields."""
    n = 0 if return_number is None else len(return_number)
    rn, nr = _check_returns(return_number, number_of_returns, n)
    if rn is None:
        return 0, 0, 0
    empty = (rn == 0) | (nr == 0)
    return int(_valid(rn, nr).sum()), int(empty.sum()), int(((rn > nr) & ~empty).sum())


def echo_point_features(return_number, number_of_returns, n_points=None) -> np.ndarray:
    """Per-point echo columns (:data:`ECHO_POINT_NAMES`).

    ``return_number`` and ``number_of_returns``: integer (N,) LAS fields, or both ``None``
    (then ``n_points`` gives N). Returns float32 (N, 4): rn / nr and the first / last / single
    flags as 0.0 or 1.0; NaN rows for points without returns (module docstring).
    """
    if return_number is None and n_points is None:
        raise InputError("n_points is needed when the return fields are None")
    n = len(return_number) if return_number is not None else int(n_points)
    rn, nr = _check_returns(return_number, number_of_returns, n)
    out = np.full((n, len(ECHO_POINT_NAMES)), np.nan, dtype=np.float32)
    if rn is None:
        return out
    valid = _valid(rn, nr)
    rn, nr = rn[valid], nr[valid]
    out[valid, 0] = rn / nr
    out[valid, 1] = rn == 1
    out[valid, 2] = rn == nr
    out[valid, 3] = nr == 1
    return out


def _check_radii(radii) -> tuple[float, ...]:
    return finite_numbers(radii, "radii", error=InputError)


def echo_names(radii) -> tuple[str, ...]:
    """Column names of :func:`echo_neighbourhood_features`: radius by radius, each in
    :data:`ECHO_NEIGHBOURHOOD_NAMES` order, e.g. ``"multi_return_share_r1"``."""
    return tuple(f"{name}_r{r:g}" for r in _check_radii(radii)
                 for name in ECHO_NEIGHBOURHOOD_NAMES)  # fmt: skip


def echo_halo(radii) -> float:
    """Halo width (metres) for chunk-invariant :func:`echo_neighbourhood_features`: the
    capped-neighbourhood halo of the largest radius."""
    return capped_halo(max(_check_radii(radii)))


def _echo_weights(rn: np.ndarray, nr: np.ndarray) -> np.ndarray:
    """int64 (N, 5): the per-point terms summed over a sphere (points with returns, of
    multi-return pulses, last returns, rn, rn^2); zeros for points without returns."""
    valid = _valid(rn, nr)
    weights = np.zeros((len(rn), _N_SUMS), dtype=np.int64)
    weights[:, 0] = valid
    weights[:, 1] = valid & (nr > 1)
    weights[:, 2] = valid & (rn == nr)
    weights[:, 3] = np.where(valid, rn, 0)
    weights[:, 4] = np.where(valid, rn * rn, 0)
    return weights


def _shares(sums: np.ndarray) -> np.ndarray:
    """float64 (Q, 3) of int64 (Q, 5) sphere sums: the multi-return share, the last-return
    share and the return-number spread; NaN rows where no point has returns."""
    count, multi, last, s1, s2 = (sums[:, k] for k in range(_N_SUMS))
    out = np.full((len(sums), len(ECHO_NEIGHBOURHOOD_NAMES)), np.nan)
    some = count > 0
    n = count[some].astype(np.float64)
    out[some, 0] = multi[some] / n
    out[some, 1] = last[some] / n
    # n * S2 - S1^2 >= 0 exactly in integers (rn <= 15, so far from int64's limit)
    spread = count[some] * s2[some] - s1[some] * s1[some]
    out[some, 2] = np.sqrt(spread.astype(np.float64)) / n
    return out


def echo_neighbourhood_features(xyz, ids, query, return_number, number_of_returns,
                                radii) -> np.ndarray:  # fmt: skip
    """Echo columns of the sphere of each radius around each query point (module docstring).

    Parameters
    ----------
    xyz : float64 (N, 3)
        Coordinates, finite; any magnitude.
    ids : int64 (N,) or None
        Unique global ids (None: rows); they pick the points of a piled-up voxel that count.
    query : int64 (Q,) or None
        Rows to describe (None: every row).
    return_number, number_of_returns : integer (N,) or both None
        LAS fields; None: a cloud without returns.
    radii : sequence of float
        Distinct sphere radii (metres).

    Returns
    -------
    float32 (Q, 3 * len(radii))
        Columns named by :func:`echo_names`; NaN where no point within r has returns.
        Chunk-invariant with a halo of :func:`echo_halo`.
    """
    xyz = _check_cloud(xyz)
    ids = _check_ids(ids, len(xyz))
    query = _check_query(query, len(xyz))
    values = _check_radii(radii)
    rn, nr = _check_returns(return_number, number_of_returns, len(xyz))
    width = len(ECHO_NEIGHBOURHOOD_NAMES)
    out = np.full((len(query), width * len(values)), np.nan, dtype=np.float32)
    if rn is None or len(query) == 0 or not _valid(rn, nr).any():
        return out
    weights = _echo_weights(rn, nr)
    for i, r in enumerate(values):
        index = RadiusIndex(xyz, r, ids, neighbourhood_members(xyz, ids, r))
        sums = index.sphere_sums(query, r, weights=weights)[:, :_N_SUMS]
        out[:, i * width:(i + 1) * width] = _shares(sums)
    return out
