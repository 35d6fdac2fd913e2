"""The truth of a synthetic plot's trees: where each stands, how tall, its DBH.

A tree's ID is the one its points carry (:func:`~pipeline.synth.surfaces.tree_ids`); the table
lists the trees with at least one point in the plot, so the IDs of the points and of the table
are the same set. Stem bases are sunk a little below the ground (the flare meets a slope), so
heights are measured from the ground under the stem base, as a forester measures them. ``z``
is the elevation of the tree's top, as in the trees tables Silva writes: ``z - height`` is
the ground under the stem.

Trees grow a few metres beyond the plot (``TREE_MARGIN``), so some crowns reach in from a stem
that stands outside: ``inside`` says whether the stem base stands in the plot, ``share`` what
share of the tree's surface lies in it. A scorer can then leave the trees standing outside
out of its counts, as a forest inventory's buffer rule does
(:func:`pipeline.trees.instances.match_pairs`'s ``left_out``).
"""

from __future__ import annotations

import numpy as np

from pipeline.atomic import atomic_write_text
from pipeline.synth.layout import Layout
from pipeline.synth.surfaces import tree_ids

#: Where the DBH is measured, metres above the ground under the stem.
BREAST_HEIGHT = 1.3
#: The columns of the truth table (metres): stem base x, y, the elevation z of the tree's top,
#: the tree's height above the ground under its stem (z - height is that ground), its DBH
#: at BREAST_HEIGHT above it, whether its stem base stands inside the plot (1) or outside (0)
#: and the share (0-1) of its surface above the ground that lies inside the plot.
TRUTH_DTYPE = np.dtype([("tree_id", np.uint32), ("x", np.float64), ("y", np.float64),
                        ("z", np.float64), ("height", np.float64), ("dbh", np.float64),
                        ("inside", np.uint8), ("share", np.float64)])
#: Decimals written to CSV (a tenth of a millimetre).
CSV_DECIMALS = 4


def tree_truth(layout: Layout, origin, present: np.ndarray, shares: dict) -> np.ndarray:
    """The truth table (TRUTH_DTYPE, sorted by tree_id) of the trees whose ID is in ``present``.

    ``origin`` (3,) shifts the local frame to the plot's CRS; ``present`` holds the tree IDs
    found among the plot's points (any integer array); ``shares`` maps a tree ID to the share
    of its surface inside the plot (:func:`~pipeline.synth.surfaces.sample_surfaces`).
    """
    ids = tree_ids(layout)
    keep = np.isin(ids, np.asarray(present))
    table = np.zeros(int(keep.sum()), dtype=TRUTH_DTYPE)
    trees = [tree for tree, kept in zip(layout.trees, keep) if kept]
    table["tree_id"] = ids[keep]
    for row, tree in zip(table, trees):
        stem = tree.stem
        ground = float(layout.terrain.height(stem.base[0], stem.base[1]))
        sunk = ground - float(stem.base[2])  # the axis's length below the ground
        row["x"], row["y"] = stem.base[:2] + np.asarray(origin[:2], dtype=np.float64)
        row["height"] = stem.height - sunk
        row["z"] = ground + float(origin[2]) + row["height"]
        row["dbh"] = 2.0 * float(stem.radius(BREAST_HEIGHT + sunk))
        row["inside"] = bool(np.all((stem.base[:2] >= 0.0) & (stem.base[:2] < layout.size)))
        row["share"] = shares[int(row["tree_id"])]
    return table


def write_truth_csv(path, table: np.ndarray) -> None:
    """Write the truth table (TRUTH_DTYPE) as CSV with a header line, atomically."""
    lines = [",".join(TRUTH_DTYPE.names)]
    for row in table:
        lines.append(",".join(
            str(int(row[name])) if TRUTH_DTYPE[name].kind in "ui"
            else f"{float(row[name]):.{CSV_DECIMALS}f}" for name in TRUTH_DTYPE.names))
    atomic_write_text(path, "\n".join(lines) + "\n")
