"""Ingest streams: its memory follows the read batch, not the size of the tile. The
synthetic generator holds a plot about once while writing it tile by tile."""

import tracemalloc

import numpy as np

from pipeline.io import read_info, write_las
from pipeline.store import open_store
from pipeline.tiling import Grid
from workflows.steps.ingest import IngestTask, ingest_tile


def _peak_ingest(tmp_path, tile_path, n_points, read_batch):
    store = tmp_path / f"store-{read_batch}.zarr"
    open_store(store)
    tile = {"index": 0, "path": str(tile_path), "name": "big", "scene": "train",
            "n_points": n_points}
    grid = Grid(0.0, 0.0, 100.0, 1, 1)
    tracemalloc.start()
    ingest_tile(IngestTask(str(store), "train", tile, grid, 0.5, "classification",
                           {2: 0}, None, read_batch, "fp"))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def test_ingest_memory_does_not_grow_with_the_tile(tmp_path):
    """Three times the points, the same read batch: the peak barely moves.

    What remains is the read batch plus zarr's chunk buffers (fixed in size).
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


def test_synth_holds_the_plot_about_once(tmp_path, monkeypatch):
    """With small batches (so that the fixed batch buffers do not hide it) writing a plot
    allocates at most ~110 bytes per point at the peak: the recorded samples and the tile
    order (traced allocations; resident memory is lower: the copy of the samples is filled
    as their pieces are freed). Before: 168 (a shuffled copy and noise temporaries of
    every point at once)."""
    import pipeline.synth.scanner
    import pipeline.synth.terrain
    import pipeline.synth.tiles
    from pipeline.synth import write_synthetic_plot

    for module in (pipeline.synth.scanner, pipeline.synth.terrain, pipeline.synth.tiles):
        monkeypatch.setattr(module, "BATCH", 1 << 14)
    tracemalloc.start()
    paths = write_synthetic_plot(tmp_path, seed=0, size=30.0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    n = sum(read_info(p).n_points for p in paths)
    assert n > 150_000
    assert peak < 110 * n, (peak, n, peak / n)
