"""The class seen from above: counted per chunk in the cells within its core, merged only at
the chunks' borders, the same counts as the highest point of every cell of the whole scene."""

import numpy as np
import pytest

from pipeline.grid import cell_keys, first_per_cell
from pipeline.tiling import Grid
from workflows.steps.survey import class_tops, merge_tops


@pytest.mark.parametrize("size", [3.0, 7.5, 40.0])
def test_the_class_seen_from_above_does_not_depend_on_the_chunking(size):
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(0, 30, (20_000, 2)), rng.uniform(0, 20, 20_000)])
    xyz[:50, :2] = np.round(xyz[:50, :2])  # points on cell and chunk borders
    label = rng.integers(0, 4, len(xyz))
    cell = 1.0
    keys = cell_keys(xyz[:, 0], xyz[:, 1], cell)
    expected = np.bincount(label[first_per_cell(keys, -xyz[:, 2])], minlength=4)
    grid = Grid.covering(xyz.min(axis=0), xyz.max(axis=0), size)
    chunk, boxes = grid.chunk_of(xyz[:, :2]), grid.boxes()
    parts = [class_tops(xyz[chunk == c], label[chunk == c], boxes[c], cell, 4)
             for c in np.unique(chunk)]
    assert np.array_equal(merge_tops(parts, 4), expected)
    if size > cell * 2:  # most cells are counted within their chunk, not merged
        assert sum(len(p[1]) for p in parts) < len(np.unique(keys))
