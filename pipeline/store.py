"""The zarr v3 store of a run: one group per spatial chunk, written step by step.

Layout::

    store.zarr/                      attrs: schema_version, tiles, scenes, classes, ingest
      scenes/<scene>/parts/<tile>/<chunk>/   points of one tile in one chunk (written by ingest)
          core_xyz (n, 3) f8, core_gid (n,) i8, core_label (n,) i2, core_role (n,) i1
          halo_xyz (m, 3) f8, halo_gid (m,) i8
      scenes/<scene>/chunks/<chunk>/         one chunk, assembled from its parts
          xyz, gid, label, role              core points sorted by global id
          halo_xyz, halo_gid                 halo copies sorted by global id
          features (n, d) f4                the feature set's columns
          stage<t>_context (n, 2C) f4, stage<t>_proba (n, C) f4   (t = 1, 2, ...)
        attrs: done = {step: fingerprint}, counts

A step marks a group done only after all its arrays are written (zarr's local store writes
each file atomically), so a run killed at any moment redoes exactly the unfinished groups.

Every array records the CRC-32 of its values in its attributes (``crc32``) when it is
written, and :func:`read_array` checks it: a chunk file that disappeared (which zarr would
read as fill values) or changed is a :class:`StoreError`, never silently wrong data. The
error also clears the done-marks that claimed the damaged group complete, so running the same
command again recomputes it. Chunks are compressed with zstd's own frame checksum too.
"""

import zlib
from pathlib import Path

import numpy as np
import zarr
from zarr.codecs import ZstdCodec

from pipeline.errors import StoreError

SCHEMA_VERSION = 2  # 2: every array records the checksum of its values
CHECKSUM = "crc32"
_COMPRESSOR = ZstdCodec(level=0, checksum=True)

#: Point roles: what a point is used for.
ROLE_TRAIN, ROLE_TEST, ROLE_PREDICT = 0, 1, 2


def open_store(path: str | Path, mode: str = "a") -> zarr.Group:
    """Open (or create, with mode "a"/"w") the run's store."""
    path = Path(path)
    if mode == "r" and not path.exists():
        raise StoreError(f"no store at {path}; run 'silva ingest' (or 'silva run') first")
    try:
        root = zarr.open_group(str(path), mode=mode)
        version = root.attrs.get("schema_version")
    except (ValueError, TypeError, KeyError, UnicodeDecodeError) as err:  # unreadable zarr.json
        raise StoreError(f"store {path} is damaged (its metadata cannot be read: "
                         f"{type(err).__name__}); rerun with --overwrite") from None
    except FileNotFoundError:
        raise StoreError(f"no store at {path}; run 'silva ingest' (or 'silva run') "
                         "first") from None
    if version is None and mode != "r":
        root.attrs["schema_version"] = SCHEMA_VERSION
    elif version is not None and version != SCHEMA_VERSION:
        raise StoreError(
            f"store {path} has schema version {version}, this Silva writes {SCHEMA_VERSION}; "
            "rerun with --overwrite"
        )
    return root


def checksum(data: np.ndarray, previous: int = 0) -> int:
    """CRC-32 of an array's values (continuing ``previous``: rows appended in order)."""
    return zlib.crc32(np.ascontiguousarray(data).view(np.uint8).reshape(-1), previous)


def write_arrays(group: zarr.Group, arrays: dict[str, np.ndarray]) -> None:
    """Write (replacing) whole arrays into a group, chunked along the first axis."""
    for name, data in arrays.items():
        data = np.ascontiguousarray(data)
        rows = max(1, min(len(data), 1 << 20))
        chunks = (rows,) + data.shape[1:]
        group.create_array(name, data=data, chunks=chunks, overwrite=True,
                           compressors=_COMPRESSOR, attributes={CHECKSUM: checksum(data)})


class Appender:
    """Appends rows to arrays of groups, creating them on first use; :meth:`seal` then
    records each array's checksum and returns the rows each holds, as read back from the
    store, by ``(group path, array name)``. An array not sealed reads as damaged."""

    def __init__(self):
        self._arrays: dict[tuple[str, str], list] = {}  # -> [array, crc, rows appended]

    def append(self, group: zarr.Group, arrays: dict[str, np.ndarray]) -> None:
        for name, data in arrays.items():
            data = np.ascontiguousarray(data)
            entry = self._arrays.get((group.path, name))
            if entry is None:
                chunks = (1 << 18,) + data.shape[1:]
                array = group.create_array(name, shape=(0,) + data.shape[1:], dtype=data.dtype,
                                           chunks=chunks, compressors=_COMPRESSOR,
                                           overwrite=True)
                entry = self._arrays[(group.path, name)] = [array, 0, 0]
            entry[0].append(data)
            entry[1] = checksum(data, entry[1])
            entry[2] += len(data)

    def seal(self) -> dict[tuple[str, str], tuple[int, int]]:
        """Record the checksums; return {(group, name): (rows appended, rows stored)}."""
        rows = {}
        for key, (array, crc, appended) in self._arrays.items():
            array.update_attributes({CHECKSUM: crc})
            stored = zarr.open_array(store=array.store, path=array.path, mode="r").shape[0]
            rows[key] = (appended, stored)
        return rows


def read_array(group: zarr.Group, name: str) -> np.ndarray:
    """A whole array of a group as NumPy, checked against the checksum written with it.

    A missing, unsealed or damaged array is a :class:`StoreError` that names it; the
    done-marks of its group (and of the groups above it) are cleared, so that running the
    command again recomputes the group.
    """
    try:
        array = group[name]
    except KeyError:
        _forget(group)
        raise StoreError(
            f"array '{name}' missing in store group '{group.path}'; the step that writes it did "
            "not finish: run the same command again to redo it"
        ) from None
    try:
        data = array[...]
        expected = array.attrs.get(CHECKSUM)
    except Exception as err:  # noqa: BLE001 - any decoding failure means damaged bytes
        problem = f"its bytes cannot be decoded ({type(err).__name__})"
    else:
        if expected is not None and checksum(data) == expected:
            return data
        problem = ("it was never completely written" if expected is None else
                   "its values differ from what was written: a chunk file is missing or "
                   "corrupt")
    _forget(group)
    raise StoreError(
        f"store array '{group.path}/{name}' is damaged ({problem}); its chunk is marked for "
        "recomputation: run the same command again (or start afresh with --overwrite)"
    )


def _forget(group: zarr.Group) -> None:
    """Clear the done-marks of ``group`` and of every group above it (below the root)."""
    parts = group.path.split("/")
    for depth in range(len(parts), 0, -1):
        try:
            node = zarr.open_group(store=group.store, path="/".join(parts[:depth]), mode="r+")
            if node.attrs.get("done"):
                node.attrs["done"] = {}
        except Exception:  # noqa: BLE001 - a read-only or half-deleted store: nothing to clear
            continue


def forget_done(group: zarr.Group) -> None:
    """Clear every done-mark of ``group``: its steps run again."""
    if group.attrs.get("done"):
        group.attrs["done"] = {}


def rows_of(sorted_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``ids`` in a chunk's ``sorted_ids`` (its gid array) and whether each is there.

    Returns int64 positions (valid only where found) and a bool mask ``found``.
    """
    if len(sorted_ids) == 0:
        return np.zeros(len(ids), np.int64), np.zeros(len(ids), bool)
    pos = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return pos, sorted_ids[pos] == ids


def is_done(group: zarr.Group, step: str, fingerprint: str) -> bool:
    """True when ``step`` completed for this group with the same configuration fingerprint."""
    return group.attrs.get("done", {}).get(step) == fingerprint


def mark_done(group: zarr.Group, step: str, fingerprint: str, **attrs) -> None:
    """Record that ``step`` completed; call only after every output is written."""
    done = dict(group.attrs.get("done", {}))
    done[step] = fingerprint
    group.attrs.update({"done": done, **attrs})


def tile_part(root: zarr.Group, scene: str, tile: int, chunk: str, prefix: str):
    """The part group of ``tile`` in ``chunk`` holding its ``prefix`` ("core" or "halo")
    points, or None when the tile has no such points there.

    Ingest records in the tile's marker which parts it wrote (``parts``); a part it wrote
    that is gone is a :class:`StoreError`, and the tile is marked to be ingested again.
    """
    marker = root[f"scenes/{scene}/parts/{tile}"]
    if prefix not in marker.attrs.get("parts", {}).get(chunk, []):
        return None
    path = part_path(scene, tile, chunk)
    if path not in root:
        _forget(root[path.rsplit("/", 1)[0]])
        raise StoreError(f"store group '{path}' is missing; its tile is marked to be ingested "
                         "again: run the same command again (or start afresh with --overwrite)")
    return root[path]


def proba_array(stage: int) -> str:
    """Name of the probabilities array of cascade stage ``stage`` (0-based; named from 1)."""
    return f"stage{stage + 1}_proba"


def context_array(stage: int) -> str:
    """Name of the context array that feeds cascade stage ``stage`` (0-based; named from 1)."""
    return f"stage{stage + 1}_context"


def chunk_path(scene: str, chunk_name: str) -> str:
    return f"scenes/{scene}/chunks/{chunk_name}"


def part_path(scene: str, tile_index: int, chunk_name: str) -> str:
    return f"scenes/{scene}/parts/{tile_index}/{chunk_name}"
