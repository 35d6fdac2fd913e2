"""Scene models in the store: what a model that has ``to_arrays``/``from_arrays`` (a terrain
model, trees, the block models to come) shares with every other.

A scene's model lives in the group ``scenes/<scene>/<kind>``; a model computed in blocks
keeps each occupied block of its grid in ``<group>/blocks/<bx>_<by>``, written and marked done
on its own (a run killed at any moment redoes only the unfinished blocks), and read lazily
by the workers (:data:`CACHED_BLOCKS` kept). The report draws a scene's model thinned to
about :data:`OVERVIEW_CELLS` cells (:func:`thinned`).
"""

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import zarr

from pipeline.errors import StoreError
from pipeline.grid import Raster
from pipeline.store import write_arrays
from workflows.store.marks import is_done, mark_done, read_array

#: Block models a worker keeps read (a chunk's points lie under a few blocks).
CACHED_BLOCKS = 9
#: Cells of a scene's model drawn in the report at most (a large survey is drawn coarser).
OVERVIEW_CELLS = 4_000_000


@dataclass(frozen=True)
class SceneModels:
    """Where the models of one kind live in the store and how they are marked done.

    ``kind``: the group's name under the scene and the step that marks it done
    ("terrain", "trees"); ``noun``: what a message calls a scene's model ("terrain model").
    """

    kind: str
    noun: str

    def path(self, scene: str) -> str:
        return f"scenes/{scene}/{self.kind}"

    def block_path(self, scene: str, block) -> str:
        return f"{self.path(scene)}/blocks/{int(block[0])}_{int(block[1])}"

    def write_block(self, root: zarr.Group, scene: str, block, arrays: dict,
                    fingerprint: str, **attrs) -> None:
        """Store the arrays of one block's model and mark the block done, with ``attrs``."""
        group = root.require_group(self.block_path(scene, block))
        write_arrays(group, arrays)
        mark_done(group, self.kind, fingerprint, **attrs)

    def block_done(self, root: zarr.Group, scene: str, block,
                   fingerprint: str) -> zarr.Group | None:
        """The group of a block stored done with ``fingerprint`` (None: not done)."""
        path = self.block_path(scene, block)
        if path not in root or not is_done(root[path], self.kind, fingerprint):
            return None
        return root[path]

    def block_arrays(self, root: zarr.Group, scene: str, block, names) -> dict:
        """The arrays ``names`` of a block's model, for its ``from_arrays``."""
        group = root[self.block_path(scene, block)]
        return {name: read_array(group, name) for name in names}

    def done(self, root: zarr.Group, scene: str, mark: str | None = None) -> str | None:
        """The fingerprint the scene's model was marked done with (None: not done); with
        ``mark``, that of another mark kept in its group (a table kept with it)."""
        path = self.path(scene)
        if path not in root:
            return None
        return root[path].attrs.get("done", {}).get(mark or self.kind)

    def scene_group(self, root: zarr.Group, scene: str) -> zarr.Group:
        """The group of the scene's model marked done, or a StoreError that says so."""
        if self.done(root, scene) is None:
            raise StoreError(f"scene '{scene}' has no {self.noun} in the store; run the same "
                             "command again (or start afresh with --overwrite)")
        return root[self.path(scene)]


def lazy_blocks(load: Callable[[int], object]) -> Callable[[int], object]:
    """``load`` (a block's row -> its model), each model kept once read, up to
    :data:`CACHED_BLOCKS`."""
    return lru_cache(maxsize=CACHED_BLOCKS)(load)


def thinned(rasters: Iterable[Raster], cells: float,
            max_cells: int = OVERVIEW_CELLS) -> list[Raster]:
    """The ``rasters`` (an iterator that reads each when its turn comes keeps memory
    bounded) of about ``cells`` cells in all, every k-th cell of each along both axes, k
    such that about ``max_cells`` are drawn."""
    step = max(1, int(np.ceil(np.sqrt(cells / max_cells))))
    # a copy: a view would keep every block's whole raster alive
    return [Raster(r.values[::step, ::step].copy(), r.x0, r.y0, r.cell * step)
            for r in rasters]
