"""A synthetic plot written as LAZ tiles of a regular grid, streamed through files.

The plot is generated as one random stream over the whole plot (so a seed gives the same
points whatever the tiling, and the same as :func:`~pipeline.synth.scene.synthetic_scene`),
but never held in memory: the recorded samples go to a file batch by batch (and to a file
per scanner), each scanner's samples are read back for its scan shadows, then all of them
batch by batch for the range noise, and each point inside the plot is appended to its
tile's file; once the plot's shuffle is drawn, each tile is read back, put in the shuffled
order and written as LAZ. Memory holds one batch, one scanner's samples, one tile, and 1
byte per recorded sample and 8 per point of the plot (the shadows' verdicts, the shuffle);
the temporary files (about 110 bytes per point) live in a hidden folder of the output
directory, removed at the end. Beside the tiles, ``trees.csv`` holds the truth
of the trees whose IDs the points carry (:mod:`~pipeline.synth.truth`).
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np

from pipeline.checks import finite_number
from pipeline.errors import ConfigError
from pipeline.synth.layout import random_layout
from pipeline.synth.params import (
    BATCH,
    CRS_WKT,
    DEFAULT_ORIGIN,
    DEFAULT_SIZE,
    DEFAULT_TILE_SIZE,
    Stand,
)
from pipeline.synth.scanner import Shadows, beam_noise, captured, in_plot
from pipeline.synth.scene import check_plot_args, check_stand
from pipeline.synth.surfaces import sample_surfaces
from pipeline.synth.truth import tree_truth, write_truth_csv

#: The extra dimension of the tiles holding each point's tree, and the truth table's file.
TREE_ID = "TreeID"
TRUTH_CSV = "trees.csv"
#: A recorded sample in the first temporary file, and a point of the plot in a tile's.
SAMPLE = np.dtype([("xyz", "<f8", 3), ("label", "u1"), ("tree", "<u4"), ("owner", "<i4")])
POINT = np.dtype([("row", "<i8"), ("xyz", "<f8", 3), ("label", "u1"), ("tree", "<u4")])

log = logging.getLogger(__name__)


def write_synthetic_plot(
    out_dir, seed: int = 0, size: float = DEFAULT_SIZE, tile_size: float = DEFAULT_TILE_SIZE,
    stand: Stand = Stand(),
) -> list[Path]:
    """Write :func:`synthetic_plot` as LAZ tiles of a regular ``tile_size`` grid in ``out_dir``.

    Tiles are LAS 1.4, point format 6, scale 1 mm, with the ETRS89 / UTM 32N WKT (:data:`CRS_WKT`)
    the class code in ``classification`` and the tree of each point in the extra dimension
    ``TreeID`` (uint32, 0 in no living tree). Tile (ix, iy) holds the points of the half-open
    cell [ox + ix t, ox + (ix+1) t) x [oy + iy t, oy + (iy+1) t), so every point is in exactly
    one tile; empty tiles are not written. The trees' truth goes to ``out_dir/trees.csv``.
    ``stand`` adds realism as in :func:`~pipeline.synth.scene.synthetic_scene`.
    Returns the paths ``plot_s{seed}_{ix}_{iy}.laz`` sorted by (ix, iy). Memory grows with the
    plot by 1 byte per recorded sample and 8 per point only (module docstring).
    """
    seed, size, _ = check_plot_args(seed, size, DEFAULT_ORIGIN)
    tile_size = finite_number(tile_size, "tile_size", hint="the tiles' side in metres")
    stand = check_stand(stand)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output directory {out_dir} is a file; choose a directory path")
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".synth-s{seed}-", dir=out_dir))
    try:
        return _write_tiles(out_dir, work, seed, size, tile_size, stand)
    except BaseException:
        if created:
            shutil.rmtree(out_dir, ignore_errors=True)
        raise
    finally:
        shutil.rmtree(work, ignore_errors=True)


class _ScannerFiles:
    """The recorded samples of each scanner, with their rows among all samples, in one file
    per scanner, buffered up to BATCH samples in memory."""

    RECORD = np.dtype([("row", "<i8"), ("xyz", "<f8", 3)])

    def __init__(self, folder: Path):
        self.folder = folder
        self.pending: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.size = 0

    def path(self, k: int) -> Path:
        return self.folder / f"scanner{k}.bin"

    def add(self, first_row: int, xyz: np.ndarray, owner: np.ndarray) -> None:
        """Samples ``xyz`` (n, 3) of rows first_row.. recorded by scanners ``owner`` (n,)."""
        self.pending.append((first_row, xyz, owner))
        self.size += len(xyz)
        if self.size >= BATCH:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        records = np.empty(self.size, dtype=self.RECORD)
        owner = np.empty(self.size, dtype=np.int64)
        at = 0
        for first_row, xyz, who in self.pending:
            records["row"][at : at + len(xyz)] = first_row + np.arange(len(xyz))
            records["xyz"][at : at + len(xyz)] = xyz
            owner[at : at + len(xyz)] = who
            at += len(xyz)
        self.pending, self.size = [], 0
        order = np.argsort(owner, kind="stable")
        scanners, starts = np.unique(owner[order], return_index=True)
        for k, part in zip(scanners, np.split(records[order], starts[1:])):
            with open(self.path(k), "ab") as f:
                part.tofile(f)

    def read(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The rows (n,) int64 and coordinates (n, 3) of scanner ``k``'s samples."""
        path = self.path(k)
        records = (np.fromfile(path, dtype=self.RECORD) if path.exists()
                   else np.empty(0, dtype=self.RECORD))
        path.unlink(missing_ok=True)
        return records["row"], np.ascontiguousarray(records["xyz"])


def _write_tiles(out_dir: Path, work: Path, seed: int, size: float, tile_size: float,
                 stand: Stand):
    """:func:`write_synthetic_plot` with its temporary files in ``work``."""
    rng = np.random.default_rng(seed)
    layout = random_layout(rng, size, stand)
    origin = np.asarray(DEFAULT_ORIGIN)
    n_tiles = max(1, math.ceil(size / tile_size))

    # 1. the recorded samples, in the order of the random stream, and each scanner's (with
    # their rows) for its shadows
    samples = work / "samples.bin"
    shadows = Shadows(layout)
    by_scanner = _ScannerFiles(work)
    n_samples = 0
    shares = {}
    with open(samples, "wb") as f:
        for xyz, labels, trees, owner in captured(rng, sample_surfaces(rng, layout, shares),
                                                  layout):
            batch = np.empty(len(xyz), dtype=SAMPLE)
            batch["xyz"], batch["label"], batch["tree"], batch["owner"] = xyz, labels, trees, owner
            batch.tofile(f)
            by_scanner.add(n_samples, xyz, owner)
            n_samples += len(batch)
    by_scanner.flush()

    # 2. the shadows, one scanner at a time (each sample's verdict is its own)
    visible = np.ones(n_samples, dtype=bool)
    for k in range(len(layout.scanners)):
        rows, xyz = by_scanner.read(k)
        visible[rows] = shadows.visible(xyz, np.full(len(rows), k))

    # 3. noise and the plot's edges, batch by batch; each point to its tile's file, with its
    # row in the plot
    counts = np.zeros(n_tiles * n_tiles, dtype=np.int64)
    present = np.zeros(0, dtype=np.uint32)
    n_points = 0
    start = 0
    with open(samples, "rb") as f:
        while len(batch := np.fromfile(f, dtype=SAMPLE, count=BATCH)):
            batch, start = batch[visible[start : start + len(batch)]], start + len(batch)
            xyz = beam_noise(rng, batch["xyz"], batch["owner"], layout.scanners)
            inside = in_plot(xyz, layout.size)
            points = np.empty(int(inside.sum()), dtype=POINT)
            points["row"] = n_points + np.arange(len(points))
            points["xyz"], points["label"] = xyz[inside], batch["label"][inside]
            points["tree"] = batch["tree"][inside]
            n_points += len(points)
            present = np.union1d(present, points["tree"][points["tree"] > 0])
            # the tile from the written (shifted) coordinates, so a point on a tile edge
            # rounds as written
            cell = np.floor(((points["xyz"][:, :2] + origin[:2]) - origin[:2]) / tile_size)
            cell = np.clip(cell.astype(np.int64), 0, n_tiles - 1)
            key = cell[:, 0] * n_tiles + cell[:, 1]
            by_tile = np.argsort(key, kind="stable")
            keys, starts = np.unique(key[by_tile], return_index=True)
            for k, part in zip(keys, np.split(points[by_tile], starts[1:])):
                with open(work / f"tile{k}.bin", "ab") as tile:
                    part.tofile(tile)
                counts[k] += len(part)
    samples.unlink()
    del visible

    keys = np.flatnonzero(counts)
    names = [f"plot_s{seed}_{k // n_tiles}_{k % n_tiles}.laz" for k in keys]
    stale = sorted(
        p.name for p in out_dir.glob(f"plot_s{seed}_*.laz") if p.name not in set(names)
    )
    if stale:
        raise ConfigError(
            f"{out_dir} already holds tiles of seed {seed} from another tiling ({stale[0]}, ...); "
            "delete them or choose an empty directory"
        )

    # 4. the shuffle of the whole plot (no spatial or per-class order in the files)
    paths = _write_shuffled(out_dir, work, rng, n_points, keys, names, origin)
    write_truth_csv(out_dir / TRUTH_CSV, tree_truth(layout, origin, present, shares))
    log.info("wrote %d synthetic tiles (%d points) to %s", len(paths), n_points, out_dir)
    return [Path(p) for p in paths]


def _write_shuffled(out_dir: Path, work: Path, rng, n_points: int, keys, names, origin):
    """Each tile's file ``work/tile{k}.bin`` (of ``keys``) written as LAZ ``names`` in the
    order of the whole plot's shuffle (the draws of rng.permutation(n_points)): the position
    of each row, then each tile's points in that order. Returns the paths written."""
    from pipeline.io import ExtraDim, write_las

    shuffled = np.arange(n_points, dtype=np.int32 if n_points < 2**31 else np.int64)
    rng.shuffle(shuffled)  # the draws of rng.permutation(n_points), in half the memory
    position = np.empty_like(shuffled)
    for start in range(0, n_points, BATCH):
        rows = shuffled[start : start + BATCH]
        position[rows] = np.arange(start, start + len(rows), dtype=shuffled.dtype)
    del shuffled
    paths = []
    for k, name in zip(keys, names):
        points = np.fromfile(work / f"tile{k}.bin", dtype=POINT)
        points = points[np.argsort(position[points["row"]])]
        paths.append(
            write_las(
                out_dir / name,
                points["xyz"] + origin,
                fields={"classification": points["label"], TREE_ID: points["tree"]},
                extra_dims=[ExtraDim(TREE_ID, "uint32", "Tree of the point, 0: none")],
                crs_wkt=CRS_WKT,
                scale=(0.001, 0.001, 0.001),
                point_format=6,
            )
        )
        (work / f"tile{k}.bin").unlink()
    return paths
