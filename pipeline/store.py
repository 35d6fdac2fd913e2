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
"""

from pathlib import Path

import numpy as np
import zarr

from pipeline.errors import StoreError

SCHEMA_VERSION = 1

#: Point roles: what a point is used for.
ROLE_TRAIN, ROLE_TEST, ROLE_PREDICT = 0, 1, 2


def open_store(path: str | Path, mode: str = "a") -> zarr.Group:
    """Open (or create, with mode "a"/"w") the run's store."""
    path = Path(path)
    if mode == "r" and not path.exists():
        raise StoreError(f"no store at {path}; run 'silva ingest' (or 'silva run') first")
    root = zarr.open_group(str(path), mode=mode)
    version = root.attrs.get("schema_version")
    if version is None and mode != "r":
        root.attrs["schema_version"] = SCHEMA_VERSION
    elif version is not None and version != SCHEMA_VERSION:
        raise StoreError(
            f"store {path} has schema version {version}, this Silva writes {SCHEMA_VERSION}; "
            "rerun with --overwrite"
        )
    return root


def write_arrays(group: zarr.Group, arrays: dict[str, np.ndarray]) -> None:
    """Write (replacing) whole arrays into a group, chunked along the first axis."""
    for name, data in arrays.items():
        data = np.ascontiguousarray(data)
        rows = max(1, min(len(data), 1 << 20))
        chunks = (rows,) + data.shape[1:]
        group.create_array(name, data=data, chunks=chunks, overwrite=True)


def append_arrays(group: zarr.Group, arrays: dict[str, np.ndarray]) -> None:
    """Append rows to arrays of a group, creating them on first use."""
    for name, data in arrays.items():
        data = np.ascontiguousarray(data)
        if name in group:
            group[name].append(data)
        else:
            chunks = (1 << 18,) + data.shape[1:]
            array = group.create_array(
                name, shape=(0,) + data.shape[1:], dtype=data.dtype, chunks=chunks
            )
            array.append(data)


def read_array(group: zarr.Group, name: str) -> np.ndarray:
    """A whole array of a group as NumPy, with a clear error when it was never written."""
    try:
        return group[name][...]
    except KeyError as err:
        raise StoreError(
            f"array '{name}' missing in store group '{group.path}'; the step that writes it did "
            "not finish: rerun 'silva run'"
        ) from err


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
