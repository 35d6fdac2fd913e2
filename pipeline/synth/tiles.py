"""A synthetic plot written as LAZ tiles of a regular grid, one tile at a time.

The plot is generated once (one random stream over the whole plot, so a seed gives the same
points whatever the tiling), then each tile's points are gathered and written in turn: no
shuffled copy of the plot is made. Peak memory is about 54 bytes per point of the plot
(about 1.3 GB at the largest size, 300 m: 24 million points). Beside the tiles, ``trees.csv``
holds the truth of the trees whose IDs the points carry (:mod:`~pipeline.synth.truth`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError
from pipeline.synth.params import BATCH, CRS_WKT, DEFAULT_ORIGIN, DEFAULT_SIZE, DEFAULT_TILE_SIZE
from pipeline.synth.scene import check_plot_args, check_positive, scanned_plot
from pipeline.synth.truth import tree_truth, write_truth_csv

#: The extra dimension of the tiles holding each point's tree, and the truth table's file.
TREE_ID = "TreeID"
TRUTH_CSV = "trees.csv"

log = logging.getLogger(__name__)


def write_synthetic_plot(
    out_dir, seed: int = 0, size: float = DEFAULT_SIZE, tile_size: float = DEFAULT_TILE_SIZE
) -> list[Path]:
    """Write :func:`synthetic_plot` as LAZ tiles of a regular ``tile_size`` grid in ``out_dir``.

    Tiles are LAS 1.4, point format 6, scale 1 mm, with the ETRS89 / UTM 32N WKT (:data:`CRS_WKT`)
    the class code in ``classification`` and the tree of each point in the extra dimension
    ``TreeID`` (uint32, 0 in no living tree). Tile (ix, iy) holds the points of the half-open
    cell [ox + ix t, ox + (ix+1) t) x [oy + iy t, oy + (iy+1) t), so every point is in exactly
    one tile; empty tiles are not written. The trees' truth goes to ``out_dir/trees.csv``.
    Returns the paths ``plot_s{seed}_{ix}_{iy}.laz`` sorted by (ix, iy).
    """
    from pipeline.io import ExtraDim, write_las

    seed, size, _ = check_plot_args(seed, size, DEFAULT_ORIGIN)
    tile_size = check_positive("tile_size", tile_size)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output directory {out_dir} is a file; choose a directory path")
    xyz, labels, ids, order, layout = scanned_plot(seed, size)
    origin = np.asarray(DEFAULT_ORIGIN)
    n_tiles = max(1, math.ceil(size / tile_size))
    # The tile of each point of the shuffled plot, then the points of each tile in shuffled
    # order, as indices into the unshuffled arrays: no shuffled copy of the plot is made.
    n_cells = n_tiles * n_tiles
    # small integer keys: a radix sort (16 bits) or a merge sort without an int64 copy
    key = np.empty(len(order), dtype=np.uint16 if n_cells <= 1 << 16 else np.int64)
    for start in range(0, len(order), BATCH):
        rows = order[start : start + BATCH]
        # from the written (shifted) coordinates, so a point on a tile edge rounds as written
        cell = np.floor(((xyz[rows, :2] + origin[:2]) - origin[:2]) / tile_size).astype(np.int64)
        cell = np.clip(cell, 0, n_tiles - 1)
        key[start : start + len(rows)] = cell[:, 0] * n_tiles + cell[:, 1]
    counts = np.bincount(key, minlength=n_cells)
    by_tile = np.argsort(key, kind="stable")  # keeps each tile's points in plot order
    del key
    np.take(order, by_tile, out=by_tile, mode="clip")  # shuffled position -> unshuffled row
    # (mode clip: unbuffered, in place; every index is valid)
    del order
    keys = np.flatnonzero(counts)
    bounds = np.append(np.cumsum(counts)[keys] - counts[keys], len(by_tile))
    names = [f"plot_s{seed}_{k // n_tiles}_{k % n_tiles}.laz" for k in keys]

    stale = sorted(
        p.name for p in out_dir.glob(f"plot_s{seed}_*.laz") if p.name not in set(names)
    )
    if stale:
        raise ConfigError(
            f"{out_dir} already holds tiles of seed {seed} from another tiling ({stale[0]}, ...); "
            "delete them or choose an empty directory"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (k, name) in enumerate(zip(keys, names)):
        sel = by_tile[bounds[i] : bounds[i + 1]]
        paths.append(
            write_las(
                out_dir / name,
                xyz[sel] + origin,
                fields={"classification": labels[sel], TREE_ID: ids[sel]},
                extra_dims=[ExtraDim(TREE_ID, "uint32", "Tree of the point, 0: none")],
                crs_wkt=CRS_WKT,
                scale=(0.001, 0.001, 0.001),
                point_format=6,
            )
        )
    write_truth_csv(out_dir / TRUTH_CSV, tree_truth(layout, origin, np.unique(ids[ids > 0])))
    log.info("wrote %d synthetic tiles (%d points) to %s", len(paths), len(xyz), out_dir)
    return [Path(p) for p in paths]
