"""Ingest streams: its memory follows the read batch, not the size of the tile. So does the
synthetic generator: it writes a plot through files, tile by tile."""

import tracemalloc

import numpy as np
import pytest

from pipeline.io import read_info, write_las
from pipeline.store import open_store
from pipeline.tiling import Grid
from tests.workflows.conftest import a_tile
from workflows.steps.ingest import IngestTask, count_tile, ingest_tile
from workflows.store.staged import staged_file


def _peak_ingest(tmp_path, tile_path, n_points, read_batch, staged=None):
    store = tmp_path / f"store-{read_batch}-{n_points}.zarr"
    open_store(store)
    tile = a_tile(n_points, path=str(tile_path), name="big", scene="train")
    grid = Grid(0.0, 0.0, 100.0, 1, 1)
    return _peak(ingest_tile, IngestTask(str(store), "train", tile, grid, 0.5,
                                         "classification", {2: 0}, None, read_batch, "fp",
                                         staged=staged))


def _peak(fn, *args) -> int:
    """Bytes traced at most while ``fn(*args)`` runs."""
    tracemalloc.start()
    try:
        fn(*args)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.fixture
def held_rows(monkeypatch):
    """Parts written every 50,000 rows (a worker's default holds a million, more than
    these tiles: memory then follows the tile up to that bound)."""
    import workflows.steps.ingest as ingest_step
    from pipeline.store import Appender

    monkeypatch.setattr(ingest_step, "Appender", lambda: Appender(hold_rows=50_000))


def test_ingest_memory_does_not_grow_with_the_tile(tmp_path, held_rows):
    """Three times the points, the same read batch: the peak barely moves.

    What remains is the read batch and the rows held before a write, plus zarr's chunk
    buffers (fixed in size).
    """
    peaks = []
    for n in (300_000, 900_000):
        xyz = np.random.default_rng(0).uniform([0, 0, 0], [90, 90, 10], size=(n, 3))
        path = write_las(tmp_path / f"tile{n}.laz", xyz,
                         fields={"classification": np.full(n, 2, np.uint8)})
        peaks.append(_peak_ingest(tmp_path, path, n, 10_000))
    assert peaks[1] < 1.4 * peaks[0], peaks
    tile_bytes = 900_000 * (3 * 8 + 8 + 2 + 1)  # the larger tile as the store holds it
    assert peaks[1] < tile_bytes, (peaks, tile_bytes)


def test_points_kept_for_ingest_stream_both_ways(tmp_path, held_rows):
    """The counting pass keeps a tile's points and ingest reads them back in read batches
    (:mod:`workflows.store.staged`): neither peak grows with the tile."""
    counting, ingesting = [], []
    for n in (300_000, 900_000):
        xyz = np.random.default_rng(1).uniform([0, 0, 0], [90, 90, 10], size=(n, 3))
        path = write_las(tmp_path / f"tile{n}.laz", xyz,
                         fields={"classification": np.full(n, 2, np.uint8)})
        kept = (str(staged_file(tmp_path / "staged", 0, None)), n)
        counting.append(_peak(count_tile, path, 1.0, 10_000, None, kept, ("classification",)))
        ingesting.append(_peak_ingest(tmp_path, path, n, 10_000, str(tmp_path / "staged")))
        assert not list((tmp_path / "staged").glob("*.npy"))  # taken, then removed
    for peaks in (counting, ingesting):
        assert peaks[1] < 1.4 * peaks[0], (counting, ingesting)


def test_synth_streams_the_plot(tmp_path, monkeypatch):
    """The plot goes through files: beyond what generating costs at any size (one object's
    samples, one batch of them scanned), writing holds one tile and 4 bytes per point of the
    plot for the shuffle (traced allocations; holding the plot in memory took about 30
    more)."""
    from pipeline.synth import scanner, terrain, tiles, write_synthetic_plot
    from pipeline.synth.layout import random_layout
    from pipeline.synth.surfaces import sample_surfaces

    for module in (scanner, terrain, tiles):  # batches and ground strips of 32,768 samples
        monkeypatch.setattr(module, "BATCH", 1 << 15)
    seed, size = 3, 30.0
    tracemalloc.start()
    try:
        rng = np.random.default_rng(seed)
        layout = random_layout(rng, size)
        for _ in scanner.captured(rng, sample_surfaces(rng, layout), layout):
            pass
        generating = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        paths = write_synthetic_plot(tmp_path, seed=seed, size=size, tile_size=10.0)
        writing = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    n_points = sum(read_info(p).n_points for p in paths)
    assert n_points > 200_000
    assert writing < generating + 16 * n_points, (writing, generating, n_points)


def _synth_peak(tmp_path, size: float) -> tuple[int, int]:
    """Traced peak bytes of writing a plot of ``size`` metres, and its points."""
    from pipeline.synth import write_synthetic_plot

    tracemalloc.start()
    try:
        paths = write_synthetic_plot(tmp_path / f"plot{size:g}", seed=3, size=size,
                                     tile_size=5.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    return peak, sum(read_info(p).n_points for p in paths)


def test_synth_memory_grows_by_the_plots_shuffle_only(tmp_path, monkeypatch):
    """Four times the area, the same batches, tiles and ground per scanner: the peak grows by
    the plot's shuffle alone, 4 bytes a point, which drawing it bit for bit needs (holding
    the shadows' verdicts and every point's position took 9 bytes a point and more).

    Only the ground is generated (its strips follow the batch, as every object's samples
    do), so that the plot's points, not its largest tree, set what grows."""
    from pipeline.synth import SYNTH_CLASSES, layout, scanner, terrain, tiles
    from pipeline.synth.surfaces import sample_surfaces

    def ground_only(rng, plot, shares=None):
        for part in sample_surfaces(rng, plot, shares):
            if part[1] != SYNTH_CLASSES["terrain"]:
                return
            yield part

    for module in (scanner, terrain, tiles):  # batches and ground strips of 4,096 samples
        monkeypatch.setattr(module, "BATCH", 1 << 12)
    monkeypatch.setattr(layout, "SCANNER_SPACING", 7.5)  # 4 and 16 scanners: 56 m² each
    monkeypatch.setattr(tiles, "sample_surfaces", ground_only)
    _synth_peak(tmp_path / "warm", 15.0)  # what happens once (imports, compiles) is not the plot's
    (small, n_small), (large, n_large) = (_synth_peak(tmp_path, size) for size in (15.0, 30.0))
    assert n_large > 3.5 * n_small > 3.5 * 20_000, (n_small, n_large)
    assert large - small < 5 * (n_large - n_small), (small, large, n_small, n_large)
