"""Scores of found trees against true ones: point instances, tree tables, height and DBH errors.

Two ways to pair predicted trees with true trees, both one-to-one:

- :func:`match_instances` compares the tree IDs of the same points (0 = in no tree on either
  side): a predicted tree matches a true tree when their point sets overlap with an
  intersection over union above 0.5. Above 0.5 each tree can overlap so much with one other
  tree only, so the matching is unique without any assignment step.
- :func:`match_tables` compares two tables of trees (as against a field inventory): a pair is
  possible when the tops (or stem bases) lie within ``max_distance`` in XY and, where both
  heights are known, the heights differ by at most ``height_tolerance`` of the true height;
  the most pairs, then the smallest total distance, by ``scipy.optimize.linear_sum_assignment``.

A :class:`Matching` gives instance precision, recall and F1; :func:`matched_errors` gives the
RMSE and bias (predicted minus true) of the matched trees' heights and DBH.

Both take ``left_out``: the true trees left out of the counts, as a forest inventory's buffer
rule leaves out the trees whose stem stands outside the plot although their crown reaches in.
The matching is made with every tree first, so that a predicted tree that is a left-out tree
pairs with it; then the left-out true trees and the predicted trees paired with them are
neither matches, nor misses, nor false trees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

#: Overlap above which a predicted tree's points are a true tree's (a unique match).
MIN_IOU = 0.5


@dataclass(frozen=True)
class Matching:
    """Pairs of true and predicted trees.

    true_ids, pred_ids uint32 (k,) the matched trees' IDs, by ascending true ID; score
    float64 (k,) the pair's IoU (instances) or XY distance in metres (tables); n_true, n_pred
    the trees on each side; left_true, left_pred the trees left out of all of these (the
    true trees named ``left_out`` that are present, the predicted trees paired with them).
    """

    true_ids: np.ndarray
    pred_ids: np.ndarray
    score: np.ndarray
    n_true: int
    n_pred: int
    left_true: int = 0
    left_pred: int = 0

    @property
    def precision(self) -> float:
        """Share of the predicted trees matched (NaN without predicted trees)."""
        return len(self.true_ids) / self.n_pred if self.n_pred else float("nan")

    @property
    def recall(self) -> float:
        """Share of the true trees matched (NaN without true trees)."""
        return len(self.true_ids) / self.n_true if self.n_true else float("nan")

    @property
    def f1(self) -> float:
        total = self.n_true + self.n_pred
        return 2.0 * len(self.true_ids) / total if total else float("nan")


def match_instances(true_ids: np.ndarray, pred_ids: np.ndarray, left_out=None) -> Matching:
    """Match the trees of two labellings of the same points (integer (N,) each, 0 = none) on
    an intersection over union above MIN_IOU; ``left_out`` (integer (m,) or None) the true
    trees left out of the counts (module docstring)."""
    true_ids, pred_ids = _as_ids(true_ids, "true_ids"), _as_ids(pred_ids, "pred_ids")
    if true_ids.shape != pred_ids.shape:
        raise ValueError(f"true_ids and pred_ids must label the same points, got "
                         f"{true_ids.shape[0]} and {pred_ids.shape[0]} labels")
    return match_pairs(pair_counts(true_ids, pred_ids), left_out)


def pair_counts(true_ids: np.ndarray, pred_ids: np.ndarray) -> np.ndarray:
    """int64 (K, 3): each (true ID, predicted ID) pair of the points and its point count;
    what :func:`match_pairs` needs, summed over batches by :func:`merge_pairs`."""
    keys = ((np.asarray(true_ids).astype(np.uint64) << np.uint64(32))
            | np.asarray(pred_ids).astype(np.uint64))
    pairs, counts = np.unique(keys, return_counts=True)
    return np.column_stack([(pairs >> np.uint64(32)).astype(np.int64),
                            (pairs & np.uint64(0xFFFFFFFF)).astype(np.int64),
                            counts.astype(np.int64)])


def merge_pairs(parts) -> np.ndarray:
    """The pair counts of several batches of points (:func:`pair_counts`) as one, exact in
    any order."""
    pairs = np.concatenate([np.asarray(p, np.int64).reshape(-1, 3) for p in parts]
                           or [np.empty((0, 3), np.int64)])
    keys, inverse = np.unique(pairs[:, :2], axis=0, return_inverse=True)
    counts = np.zeros(keys.shape[0], dtype=np.int64)
    np.add.at(counts, inverse.reshape(-1), pairs[:, 2])
    return np.column_stack([keys.reshape(-1, 2), counts])


def match_pairs(pairs: np.ndarray, left_out=None) -> Matching:
    """:func:`match_instances` from the points counted per (true ID, predicted ID) pair."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 3)
    true_trees, true_at = np.unique(pairs[:, 0], return_inverse=True)
    pred_trees, pred_at = np.unique(pairs[:, 1], return_inverse=True)
    true_sizes = np.bincount(true_at.reshape(-1), weights=pairs[:, 2])
    pred_sizes = np.bincount(pred_at.reshape(-1), weights=pairs[:, 2])
    both = (pairs[:, 0] > 0) & (pairs[:, 1] > 0)
    shared = pairs[both, 2].astype(np.float64)
    iou = shared / (true_sizes[true_at.reshape(-1)[both]] + pred_sizes[pred_at.reshape(-1)[both]]
                    - shared)
    keep = iou > MIN_IOU
    matched = pairs[both][keep]
    order = np.argsort(matched[:, 0], kind="stable")
    matching = Matching(true_ids=matched[order, 0].astype(np.uint32),
                        pred_ids=matched[order, 1].astype(np.uint32), score=iou[keep][order],
                        n_true=int(np.count_nonzero(true_trees > 0)),
                        n_pred=int(np.count_nonzero(pred_trees > 0)))
    return _leave_out(matching, true_trees[true_trees > 0], left_out)


def _leave_out(matching: Matching, true_trees: np.ndarray, left_out) -> Matching:
    """``matching`` without the true trees ``left_out`` among ``true_trees`` (every true
    tree's ID) and the predicted trees paired with them."""
    if left_out is None:
        return matching
    left_out = _as_ids(left_out, "left_out")
    gone = np.isin(matching.true_ids, left_out)
    left_true = int(np.count_nonzero(np.isin(np.asarray(true_trees, np.int64),
                                             left_out.astype(np.int64))))
    left_pred = int(np.count_nonzero(gone))
    return Matching(true_ids=matching.true_ids[~gone], pred_ids=matching.pred_ids[~gone],
                    score=matching.score[~gone], n_true=matching.n_true - left_true,
                    n_pred=matching.n_pred - left_pred, left_true=left_true,
                    left_pred=left_pred)


def _as_ids(ids, name: str) -> np.ndarray:
    """uint64 (N,) of integer tree IDs in 0..2**32 - 1 (two of them pack into one key)."""
    ids = np.asarray(ids).reshape(-1)
    if ids.size and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0
                     or int(ids.max()) >= 2**32):
        raise ValueError(f"{name} must be integer tree IDs in 0..2**32-1 (0: no tree), got "
                         f"{ids.dtype} values from {ids.min()} to {ids.max()}")
    return ids.astype(np.uint64)


def match_tables(true_table: np.ndarray, pred_table: np.ndarray, max_distance: float,
                 height_tolerance: float | None = None, left_out=None) -> Matching:
    """Match two tree tables (structured arrays with ``tree_id``, ``x``, ``y`` and, for the
    height rule, ``height``) one-to-one: the most pairs within ``max_distance`` metres in XY
    (and with |predicted - true| height <= height_tolerance * true height where both are
    known, when ``height_tolerance`` is given), then the smallest total distance. ``left_out``
    (integer (m,) or None): the true trees left out of the counts (module docstring)."""
    distance = np.hypot(true_table["x"][:, None] - pred_table["x"][None, :],
                        true_table["y"][:, None] - pred_table["y"][None, :])
    allowed = distance <= max_distance
    if height_tolerance is not None:
        true_h, pred_h = true_table["height"][:, None], pred_table["height"][None, :]
        with np.errstate(invalid="ignore"):
            close = np.abs(pred_h - true_h) <= height_tolerance * true_h
        allowed &= close | np.isnan(true_h) | np.isnan(pred_h)
    # A refused pair costs more than any set of allowed pairs: the most pairs come first.
    refused = max_distance * (min(distance.shape) + 1) + 1.0
    rows, cols = linear_sum_assignment(np.where(allowed, distance, refused))
    ok = allowed[rows, cols]
    rows, cols = rows[ok], cols[ok]
    order = np.argsort(true_table["tree_id"][rows], kind="stable")
    rows, cols = rows[order], cols[order]
    matching = Matching(true_ids=true_table["tree_id"][rows].astype(np.uint32),
                        pred_ids=pred_table["tree_id"][cols].astype(np.uint32),
                        score=distance[rows, cols], n_true=len(true_table),
                        n_pred=len(pred_table))
    return _leave_out(matching, true_table["tree_id"], left_out)


def matched_errors(matching: Matching, true_table: np.ndarray, pred_table: np.ndarray,
                   columns=("height", "dbh")) -> dict[str, dict[str, float]]:
    """RMSE and bias (mean of predicted - true) of ``columns`` over the matched trees whose
    value is known on both sides: ``{column: {"rmse", "bias", "n"}}`` (NaN when n is 0)."""
    true_rows = _rows_of(true_table, matching.true_ids)
    pred_rows = _rows_of(pred_table, matching.pred_ids)
    errors = {}
    for name in columns:
        diff = (np.asarray(pred_table[name], np.float64)[pred_rows]
                - np.asarray(true_table[name], np.float64)[true_rows])
        diff = diff[np.isfinite(diff)]
        n = int(diff.shape[0])
        errors[name] = {"rmse": float(np.sqrt(np.mean(diff**2))) if n else float("nan"),
                        "bias": float(np.mean(diff)) if n else float("nan"), "n": n}
    return errors


def _rows_of(table: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """int64 rows of ``table`` holding the tree IDs ``ids`` (each present once)."""
    order = np.argsort(table["tree_id"], kind="stable")
    rows = order[np.searchsorted(table["tree_id"], ids, sorter=order)]
    if not np.array_equal(table["tree_id"][rows], ids):
        raise ValueError("a matched tree ID is missing from its table")
    return rows
