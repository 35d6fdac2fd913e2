"""Points kept from the balanced layout's counting pass for ingest to store.

The balanced layout counts every point of a scene before any chunk exists, then ingest
reads the points again to store them by chunk: each LAZ tile was decoded twice. The
counting pass now also writes what ingest reads of a tile or point range (its coordinates
and the fields ingest needs, as read) to an uncompressed ``.npy`` file of the run's work
folder, and ingest reads that file, in the same batches, instead of decoding the tile
again; it removes the file once the points are in the store.

A file is renamed into place only when it holds all its points, and ingest takes it only
when it holds the fields and the number of points it expects: anything else (a run killed
while counting, a file removed) is read from the tile, the same points. Both sides stream:
memory follows the read batch. Disk use is bounded by :data:`MAX_STAGED_POINTS` per scene;
the points beyond are decoded twice as before.
"""

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.io import PointBatch

#: Points of a scene kept between the two reads at most.
MAX_STAGED_POINTS = 50_000_000

#: Bytes a kept point takes on disk, about: its coordinates (24) and the fields ingest reads.
STAGED_BYTES_PER_POINT = 28


def staged_bytes(n_points: int) -> int:
    """Disk that the points kept of a scene of ``n_points`` take at most, about."""
    return min(n_points, MAX_STAGED_POINTS) * STAGED_BYTES_PER_POINT


def staged_file(folder: str | Path, tile: int, span: tuple[int, int] | None) -> Path:
    """Where the points of tile ``tile`` (index), or of its point range ``span``, are kept."""
    start, stop = span or (0, None)
    return Path(folder) / f"{tile}-{start}-{'end' if stop is None else stop}.npy"


class Stager:
    """Writes the read batches of one tile or range (``n_points`` in all) to ``path``,
    which appears only once :meth:`close` finds every point written."""

    def __init__(self, path: str | Path, n_points: int):
        self.path, self.n_points = Path(path), int(n_points)
        self._part = self.path.with_name(self.path.name + ".part")
        self._file, self._dtype, self._written = None, None, 0

    def write(self, batch: PointBatch) -> None:
        if self._file is None:
            self._open(batch)
        records = np.empty(len(batch.xyz), dtype=self._dtype)
        records["xyz"] = batch.xyz
        for name, values in batch.fields.items():
            records[name] = values
        records.tofile(self._file)
        self._written += len(records)

    def _open(self, batch: PointBatch) -> None:
        self._dtype = np.dtype([("xyz", "<f8", (3,)),
                                *((name, values.dtype) for name, values in batch.fields.items())])
        self._part.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self._part, "wb")
        np.lib.format.write_array_header_2_0(self._file, {
            "descr": np.lib.format.dtype_to_descr(self._dtype), "fortran_order": False,
            "shape": (self.n_points,)})

    def close(self) -> None:
        if self._file is None:
            return
        self._file.close()
        if self._written == self.n_points:
            os.replace(self._part, self.path)
        else:
            self._part.unlink(missing_ok=True)

    def __enter__(self) -> "Stager":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is not None:  # a failed read keeps nothing
            self._written = -1
        self.close()


def staged_batches(path: str | Path, fields: tuple[str, ...], n_points: int, start: int,
                   batch_size: int) -> Iterator[PointBatch] | None:
    """The kept points of ``path`` as the read batches of ``batch_size`` points of the tile
    would be (the first is point ``start`` of the tile), or None when the file is missing or
    does not hold ``n_points`` points with ``fields``."""
    try:
        handle = open(path, "rb")
    except FileNotFoundError:
        return None
    try:
        if np.lib.format.read_magic(handle) != (2, 0):
            raise ValueError("not written by a Stager")
        shape, _, dtype = np.lib.format.read_array_header_2_0(handle)
        whole = handle.tell() + n_points * dtype.itemsize == os.fstat(handle.fileno()).st_size
    except (ValueError, OSError):
        whole = False
    if not whole or shape != (n_points,) or not set(fields) <= set(dtype.names or ()):
        handle.close()
        return None
    return _batches(handle, dtype, fields, n_points, start, batch_size)


def _batches(handle, dtype, fields, n_points, start, batch_size) -> Iterator[PointBatch]:
    with handle:
        for first in range(0, n_points, batch_size):
            records = np.empty(min(batch_size, n_points - first), dtype=dtype)
            handle.readinto(records.view(np.uint8))
            yield PointBatch(start=start + first, xyz=np.ascontiguousarray(records["xyz"]),
                             fields={name: np.ascontiguousarray(records[name])
                                     for name in fields})


def remove_staged(path: str | Path) -> None:
    """Forget a kept file (nothing when there is none)."""
    Path(path).unlink(missing_ok=True)
