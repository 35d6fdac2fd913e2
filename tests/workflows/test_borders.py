"""Chunks in one pass share the features of their borders through the store: a chunk reads
the rows its neighbours kept and computes only the others, keeps its own band only for the
neighbours still to come, and ignores a band that is not whole."""

from types import SimpleNamespace

import numpy as np

from pipeline.store import open_store
from pipeline.tiling import Grid
from workflows.steps.borders import Borders, borders_path, remove_borders
from workflows.store.layout import chunk_path
from workflows.store.marks import mark_done

WIDTH = 0.5


def _cloud():
    """Points on two chunks of 4 m side by side (x 0-8 m), global ids in random order."""
    rng = np.random.default_rng(0)
    xyz = rng.uniform((0, 0, 0), (8, 4, 1), size=(4000, 3))
    ids = rng.permutation(10 * len(xyz))[:len(xyz)].astype(np.int64)
    return xyz, ids


def _features(xyz, ids, rows):
    """Stand-in features: a function of each point alone, as the real ones are of its
    surroundings."""
    return np.stack([ids[rows] * 0.5, xyz[rows, 0], xyz[rows, 2]], axis=1).astype(np.float32)


def _window(xyz, box, halo):
    x0, y0, x1, y1 = box
    inside = ((xyz[:, 0] >= x0 - halo) & (xyz[:, 0] < x1 + halo)
              & (xyz[:, 1] >= y0 - halo) & (xyz[:, 1] < y1 + halo))
    return np.flatnonzero(inside)


def _run_chunk(root, borders, chunk, xyz, ids):
    """The features of one chunk's rows (its core and ring), as the one pass asks for them:
    the rows computed, and how many were read."""
    window = _window(xyz, borders.boxes[chunk], WIDTH)
    view = SimpleNamespace(root=root, scene="predict", chunk=chunk)
    computed = []

    def compute(rows):
        computed.append(rows)
        return _features(xyz[window], ids[window], rows)

    rows = np.arange(len(window))
    out, shared = borders.features(view, rows, ids[window], xyz[window], compute)
    assert np.array_equal(out, _features(xyz[window], ids[window], rows))
    root.require_group(chunk_path("predict", chunk))
    mark_done(root[chunk_path("predict", chunk)], "apply", borders.fingerprint)
    return np.concatenate(computed), shared


def _setup(tmp_path):
    root = open_store(tmp_path / "store.zarr")
    grid = Grid(0.0, 0.0, 4.0, 2, 1)
    boxes = {grid.chunk_name(i): tuple(box) for i, box in enumerate(grid.boxes())}
    return root, Borders(boxes, WIDTH, "apply", "f" * 16)


def test_the_second_chunk_reads_its_border_and_the_band_is_removed(tmp_path):
    root, borders = _setup(tmp_path)
    xyz, ids = _cloud()
    assert list(borders.neighbours("0_0")) == ["1_0"]
    first, shared = _run_chunk(root, borders, "0_0", xyz, ids)
    assert shared == 0
    second, shared = _run_chunk(root, borders, "1_0", xyz, ids)
    # the second chunk's rows within the ring of the first's box came from its band
    window = _window(xyz, borders.boxes["1_0"], WIDTH)
    near = np.count_nonzero(xyz[window, 0] <= 4.0 + WIDTH)
    assert shared == near > 0 and len(second) == len(window) - near
    # the second kept nothing: its only neighbour was done
    assert f"{borders_path('predict')}/{'f' * 16}/1_0" not in root
    remove_borders(root, ["predict"])
    assert borders_path("predict") not in root


def test_bands_of_another_fingerprint_or_damaged_are_not_read(tmp_path):
    root, borders = _setup(tmp_path)
    xyz, ids = _cloud()
    _run_chunk(root, borders, "0_0", xyz, ids)
    other = Borders(borders.boxes, WIDTH, "apply", "e" * 16)
    _, shared = _run_chunk(root, other, "1_0", xyz, ids)
    assert shared == 0

    root, borders = _setup(tmp_path / "damaged")
    _run_chunk(root, borders, "0_0", xyz, ids)
    band = tmp_path / "damaged" / "store.zarr" / borders_path("predict") / ("f" * 16) / "0_0"
    shard = next(p for p in (band / "band").iterdir() if p.name != "zarr.json")
    shard.write_bytes(shard.read_bytes()[:-7] + b"1234567")
    computed, shared = _run_chunk(root, borders, "1_0", xyz, ids)
    assert shared == 0 and len(computed)
