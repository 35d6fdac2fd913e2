"""The features of the points by a chunk's borders, kept for the chunks beside it.

In one pass (:mod:`workflows.steps.one_pass`) a chunk computes the first stage's features of
its core and of the halo points within a ring of it (:func:`pipeline.cascade.one_pass.
ring_width`), whose probabilities its context counts. The chunk beside computes the ring's
points again, as its own core, and its own ring holds this chunk's border points: on the
terrestrial plot cut once through the scanner the two bands hold 7 % of the points, and their
features were 5 % of the run's CPU time.

A point's features follow from the points around it alone (the halo contract), so a chunk
reads the features its neighbours kept of its rows instead of computing them again, then
keeps, by global id, those of its rows within a ring of every neighbour not yet classified.
Chunks that run one after the other (one worker, or more chunks than workers) so compute
each point's features once; two neighbours that run at once both compute their borders, as
before. The same bits either way. A kept band is scratch: read only when whole (its
checksums) and written under the same step fingerprint, and removed when the step ends.
"""

from dataclasses import dataclass

import numpy as np
import zarr

from pipeline.store import DamagedArrayError, has_array, read_array, rows_of, write_arrays
from pipeline.tiling import box_distance
from workflows.store.layout import chunk_path
from workflows.store.marks import is_done

#: The folder of a scene's kept bands, one group per fingerprint and chunk.
FOLDER = "borders"


def borders_path(scene: str) -> str:
    return f"scenes/{scene}/{FOLDER}"


def box_gap(a, b) -> float:
    """How far apart two boxes (xmin, ymin, xmax, ymax) lie along the farther axis, the
    measure of :func:`pipeline.tiling.box_distance` (zero when they touch)."""
    dx = max(a[0] - b[2], b[0] - a[2], 0.0)
    dy = max(a[1] - b[3], b[1] - a[3], 0.0)
    return max(dx, dy)


@dataclass(frozen=True)
class Borders:
    """The bands a scene's chunks share: ``boxes``, the core box of each of its chunks
    (:attr:`workflows.store.scenes.SceneLayout.chunk_boxes`); ``width``, the one pass's
    ring beyond a core; ``step`` and ``fingerprint``, the step whose done-mark says a chunk
    needs no band any more, and the fingerprint its bands are kept under."""

    boxes: dict[str, tuple[float, float, float, float]]
    width: float
    step: str
    fingerprint: str

    def neighbours(self, chunk: str) -> dict[str, tuple]:
        """The other chunks whose boxes lie within ``width`` of ``chunk``'s: name -> box."""
        own = self.boxes[chunk]
        return {name: box for name, box in self.boxes.items()
                if name != chunk and box_gap(own, box) <= self.width}

    def features(self, view, rows: np.ndarray, ids: np.ndarray, xyz: np.ndarray, compute
                 ) -> tuple[np.ndarray, int]:
        """The features of the window rows ``rows`` (``ids`` and ``xyz``: the window's
        global ids and coordinates; ``compute(rows)`` computes them), and how many were
        read from the neighbours' bands."""
        neighbours = self.neighbours(view.chunk)
        gids = ids[rows]
        out, known = None, np.zeros(len(rows), dtype=bool)
        for name in neighbours:
            band = self._read(view, name)
            if band is None:
                continue
            pos, found = rows_of(band[0], gids)
            found &= ~known
            if out is None:
                out = np.empty((len(rows), band[1].shape[1]), dtype=band[1].dtype)
            out[found] = band[1][pos[found]]
            known |= found
        todo = np.flatnonzero(~known)
        if out is None:
            out = compute(rows)
        elif len(todo):
            out[todo] = compute(rows[todo])
        self._keep(view, neighbours, gids, xyz[rows], out)
        return out, int(np.count_nonzero(known))

    def _path(self, scene: str, chunk: str) -> str:
        return f"{borders_path(scene)}/{self.fingerprint}/{chunk}"

    def _read(self, view, chunk: str) -> tuple[np.ndarray, np.ndarray] | None:
        """A neighbour's kept band (sorted global ids, their features), or None."""
        group = view.root.get(self._path(view.scene, chunk))
        if group is None or not has_array(group, "features"):
            return None
        try:
            return read_array(group, "gid"), read_array(group, "features")
        except DamagedArrayError:  # being written again by a resumed run: computed instead
            return None

    def _pending(self, view, chunk: str) -> bool:
        """Whether ``chunk`` is still to be classified by this step."""
        group = view.root.get(chunk_path(view.scene, chunk))
        return group is None or not is_done(group, self.step, self.fingerprint)

    def _keep(self, view, neighbours: dict, gids: np.ndarray, xyz: np.ndarray,
              features: np.ndarray) -> None:
        """Keep the features of the rows within ``width`` of a neighbour still to come."""
        near = np.zeros(len(gids), dtype=bool)
        for chunk, box in neighbours.items():
            if self._pending(view, chunk):
                near |= box_distance(xyz, box) <= self.width
        if not near.any():
            return
        group = view.root.require_group(self._path(view.scene, view.chunk))
        if has_array(group, "features"):  # kept by an earlier run of this chunk: the same
            return
        rows = np.flatnonzero(near)
        rows = rows[np.argsort(gids[rows], kind="stable")]
        write_arrays(group, {"gid": gids[rows], "features": features[rows]}, pack="band")


def remove_borders(root: zarr.Group, scenes) -> None:
    """Remove the kept bands of ``scenes`` (the step that reads them is done)."""
    for scene in scenes:
        if borders_path(scene) in root:
            del root[borders_path(scene)]
