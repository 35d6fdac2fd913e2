"""A synthetic plot written as LAZ tiles of a regular grid, streamed through files.

The plot is generated as one random stream over the whole plot (so a seed gives the same
points whatever the tiling, and the same as :func:`~pipeline.synth.scene.synthetic_scene`),
but never held in memory: the recorded samples go to a file batch by batch (and to a file
per scanner), each scanner's samples are read back for its scan shadows (the rows of the
hidden ones go to a file per batch), then all of them batch by batch for the range noise,
and each point inside the plot is appended to its tile's file; once the plot's shuffle is
drawn, each point's position in it goes to its tile through files too, and each tile is
read back, put in the shuffled order and written as LAZ. Memory holds one batch, one
scanner's samples, one tile, and the shuffle: 4 bytes per point of the plot, which drawing
the same permutation as ``rng.permutation`` needs (the only memory that grows with the
plot: about 100 MB at the largest size, MAX_SIZE). The temporary files (about 90 bytes per point)
live in a hidden folder of the output directory, removed at the end. Beside the tiles,
``trees.csv`` holds the truth of the trees whose IDs the points carry
(:mod:`~pipeline.synth.truth`).
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
POINT = np.dtype([("xyz", "<f8", 3), ("label", "u1"), ("tree", "<u4")])

log = logging.getLogger(__name__)


def write_synthetic_plot(
    out_dir, seed: int = 0, size: float = DEFAULT_SIZE, tile_size: float = DEFAULT_TILE_SIZE,
    stand: Stand = Stand(), origin=DEFAULT_ORIGIN,
) -> list[Path]:
    """Write :func:`synthetic_plot` as LAZ tiles of a regular ``tile_size`` grid in ``out_dir``.

    Tiles are LAS 1.4, point format 6, scale 1 mm, with the ETRS89 / UTM 32N WKT (:data:`CRS_WKT`)
    the class code in ``classification`` and the tree of each point in the extra dimension
    ``TreeID`` (uint32, 0 in no living tree). Tile (ix, iy) holds the points of the half-open
    cell [ox + ix t, ox + (ix+1) t) x [oy + iy t, oy + (iy+1) t), so every point is in exactly
    one tile; empty tiles are not written. The trees' truth goes to ``out_dir/trees.csv``.
    ``stand`` adds realism as in :func:`~pipeline.synth.scene.synthetic_scene`; ``origin``
    is the plot's lower-left corner at ground level (x, y, z in the CRS), so that plots
    written apart can be one scene side by side.
    Returns the paths ``plot_s{seed}_{ix}_{iy}.laz`` sorted by (ix, iy). Memory grows with the
    plot by 4 bytes per point only, the shuffle (module docstring); a tile is held whole.
    """
    seed, size, origin = check_plot_args(seed, size, origin)
    tile_size = finite_number(tile_size, "tile_size", hint="the tiles' side in metres")
    stand = check_stand(stand)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"output directory {out_dir} is a file; choose a directory path")
    created = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".synth-s{seed}-", dir=out_dir))
    try:
        return _write_tiles(out_dir, work, seed, size, tile_size, stand, origin)
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
        for k, part in _by_key(owner, records):
            _append(self.path(k), part)

    def read(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The rows (n,) int64 and coordinates (n, 3) of scanner ``k``'s samples."""
        path = self.path(k)
        records = (np.fromfile(path, dtype=self.RECORD) if path.exists()
                   else np.empty(0, dtype=self.RECORD))
        path.unlink(missing_ok=True)
        return records["row"], np.ascontiguousarray(records["xyz"])


def _append(path: Path, array: np.ndarray) -> None:
    with open(path, "ab") as f:
        array.tofile(f)


def _by_key(keys: np.ndarray, values: np.ndarray):
    """(key, the values of that key in their order) for each distinct key of ``keys`` (n,),
    ascending; ``values`` (n, ...) is split along its first axis."""
    order = np.argsort(keys, kind="stable")
    found, starts = np.unique(keys[order], return_index=True)
    return zip(found, np.split(values[order], starts[1:]))


def _write_tiles(out_dir: Path, work: Path, seed: int, size: float, tile_size: float,
                 stand: Stand, origin: tuple[float, float, float]):
    """:func:`write_synthetic_plot` with its temporary files in ``work``."""
    rng = np.random.default_rng(seed)
    layout = random_layout(rng, size, stand)
    origin = np.asarray(origin)
    n_tiles = max(1, math.ceil(size / tile_size))
    shares = {}
    _hide_shadowed(work, layout, _record_samples(work, rng, layout, shares))
    counts, present = _points_to_tiles(work, rng, layout, tile_size, n_tiles, origin)
    n_points = int(counts.sum())

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

    _shuffle_positions(work, rng, n_points)
    paths = _write_shuffled(out_dir, work, keys, names, origin)
    write_truth_csv(out_dir / TRUTH_CSV, tree_truth(layout, origin, present, shares))
    log.info("wrote %d synthetic tiles (%d points) to %s", len(paths), n_points, out_dir)
    return [Path(p) for p in paths]


def _record_samples(work: Path, rng, layout, shares: dict) -> _ScannerFiles:
    """1. The recorded samples, in the order of the random stream, to ``work/samples.bin``,
    and each scanner's (with their rows) to its own file, for its shadows."""
    by_scanner = _ScannerFiles(work)
    n_samples = 0
    with open(work / "samples.bin", "wb") as f:
        for xyz, labels, trees, owner in captured(rng, sample_surfaces(rng, layout, shares),
                                                  layout):
            batch = np.empty(len(xyz), dtype=SAMPLE)
            batch["xyz"], batch["label"], batch["tree"], batch["owner"] = xyz, labels, trees, owner
            batch.tofile(f)
            by_scanner.add(n_samples, xyz, owner)
            n_samples += len(batch)
    by_scanner.flush()
    return by_scanner


def _hide_shadowed(work: Path, layout, by_scanner: _ScannerFiles) -> None:
    """2. The shadows, one scanner at a time (each sample's verdict is its own): the rows of
    the samples a stem hides, by the BATCH of samples they belong to, to
    ``work/hidden{b}.bin`` (int64)."""
    shadows = Shadows(layout)
    for k in range(len(layout.scanners)):
        rows, xyz = by_scanner.read(k)
        hidden = rows[~shadows.visible(xyz, np.full(len(rows), k))]
        for b, part in _by_key(hidden // BATCH, hidden):
            _append(work / f"hidden{b}.bin", part)


def _visible(work: Path, b: int, n: int) -> np.ndarray:
    """Whether each of the ``n`` samples of batch ``b`` escaped every shadow: (n,) bool."""
    visible = np.ones(n, dtype=bool)
    path = work / f"hidden{b}.bin"
    if path.exists():
        visible[np.fromfile(path, dtype=np.int64) - b * BATCH] = False
        path.unlink()
    return visible


def _points_to_tiles(work: Path, rng, layout, tile_size: float, n_tiles: int, origin):
    """3. Noise and the plot's edges, batch by batch: each point of the plot appended to its
    tile's file ``work/tile{k}.bin`` (so in the plot's order), and its tile to
    ``work/keys.bin`` (int64, one per point of the plot, in its order). Returns the points of
    each tile (n_tiles², ) int64 and the tree IDs the points carry."""
    counts = np.zeros(n_tiles * n_tiles, dtype=np.int64)
    present = np.zeros(0, dtype=np.uint32)
    with open(work / "samples.bin", "rb") as f, open(work / "keys.bin", "wb") as tile_keys:
        b = 0
        while len(batch := np.fromfile(f, dtype=SAMPLE, count=BATCH)):
            batch, b = batch[_visible(work, b, len(batch))], b + 1
            xyz = beam_noise(rng, batch["xyz"], batch["owner"], layout.scanners)
            inside = in_plot(xyz, layout.size)
            points = np.empty(int(inside.sum()), dtype=POINT)
            points["xyz"], points["label"] = xyz[inside], batch["label"][inside]
            points["tree"] = batch["tree"][inside]
            present = np.union1d(present, points["tree"][points["tree"] > 0])
            # the tile from the written (shifted) coordinates, so a point on a tile edge
            # rounds as written
            cell = np.floor(((points["xyz"][:, :2] + origin[:2]) - origin[:2]) / tile_size)
            cell = np.clip(cell.astype(np.int64), 0, n_tiles - 1)
            key = cell[:, 0] * n_tiles + cell[:, 1]
            key.tofile(tile_keys)
            for k, part in _by_key(key, points):
                _append(work / f"tile{k}.bin", part)
                counts[k] += len(part)
    (work / "samples.bin").unlink()
    return counts, present


def _shuffle_positions(work: Path, rng, n_points: int) -> None:
    """4. The shuffle of the whole plot (no spatial or per-class order in the files; the
    draws of rng.permutation(n_points)): each point's position in it appended to its tile's
    ``work/tile{k}.pos`` (int64), in the order of ``work/tile{k}.bin``.

    Memory holds the shuffle (4 bytes a point, what drawing it bit for bit needs) and a
    batch: the positions go by blocks of BATCH rows to ``work/block{b}.bin``, then each
    block is put in row order and dealt to the tiles by ``work/keys.bin``.
    """
    dtype = np.int32 if n_points < 2**31 else np.int64
    shuffled = np.arange(n_points, dtype=dtype)
    rng.shuffle(shuffled)  # the draws of rng.permutation(n_points), in half the memory
    pair = np.dtype([("row", dtype), ("position", dtype)])
    for start in range(0, n_points, BATCH):
        pairs = np.empty(min(BATCH, n_points - start), dtype=pair)
        pairs["row"] = shuffled[start : start + len(pairs)]
        pairs["position"] = np.arange(start, start + len(pairs), dtype=dtype)
        for b, part in _by_key(pairs["row"] // BATCH, pairs):
            _append(work / f"block{b}.bin", part)
    del shuffled
    with open(work / "keys.bin", "rb") as tile_keys:
        for b in range(math.ceil(n_points / BATCH)):
            keys = np.fromfile(tile_keys, dtype=np.int64, count=BATCH)
            pairs = np.fromfile(work / f"block{b}.bin", dtype=pair)
            (work / f"block{b}.bin").unlink()
            position = np.empty(len(keys), dtype=np.int64)
            position[pairs["row"] - b * BATCH] = pairs["position"]
            for k, part in _by_key(keys, position):
                _append(work / f"tile{k}.pos", part)
    (work / "keys.bin").unlink()


def _write_shuffled(out_dir: Path, work: Path, keys, names, origin) -> list:
    """Each tile's file ``work/tile{k}.bin`` (of ``keys``) written as LAZ ``names``, its
    points in the order of their positions in the plot's shuffle (``work/tile{k}.pos``).
    Returns the paths written."""
    from pipeline.io import ExtraDim, write_las

    paths = []
    for k, name in zip(keys, names):
        points = np.fromfile(work / f"tile{k}.bin", dtype=POINT)
        order = np.argsort(np.fromfile(work / f"tile{k}.pos", dtype=np.int64))
        # the columns in the shuffle's order, without the tile's records while it is written
        xyz, labels, trees = (points[name][order] for name in ("xyz", "label", "tree"))
        xyz += origin
        del points, order
        paths.append(
            write_las(
                out_dir / name,
                xyz,
                fields={"classification": labels, TREE_ID: trees},
                extra_dims=[ExtraDim(TREE_ID, "uint32", "Tree of the point, 0: none")],
                crs_wkt=CRS_WKT,
                scale=(0.001, 0.001, 0.001),
                point_format=6,
            )
        )
        (work / f"tile{k}.bin").unlink()
        (work / f"tile{k}.pos").unlink()
    return paths
