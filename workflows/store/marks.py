"""Which groups of the store are done: a step marks a group done (with the fingerprint of
what it computed) only after all its arrays are written (zarr's local store writes each file
atomically), so a run killed at any moment redoes exactly the unfinished groups.

An array found missing or damaged when read (:func:`read_array`, :func:`read_records`)
clears the done-marks that claimed its group complete, so running the same command again
recomputes it.
"""

import numpy as np
import zarr

from pipeline import store
from pipeline.store import DamagedArrayError
from workflows.store.layout import POINT_ARRAYS


def read_array(group: zarr.Group, name: str) -> np.ndarray:
    """:func:`pipeline.store.read_array`; a missing or damaged array also clears the marks
    of its group (:func:`forget`)."""
    return _forgetting(store.read_array, group, name)


def read_records(group: zarr.Group, name: str) -> dict[str, np.ndarray]:
    """:func:`pipeline.store.read_records`; a missing or damaged record array also clears
    the marks of its group (:func:`forget`)."""
    return _forgetting(store.read_records, group, name)


def _forgetting(read, group: zarr.Group, name: str):
    try:
        return read(group, name)
    except DamagedArrayError as err:
        forget(err.group, err.name)
        raise


def forget(group: zarr.Group, name: str | None = None) -> None:
    """Clear the done-marks of ``group`` and of every group above it (below the root), and
    the assembly mark when the array ``name`` that failed holds the chunk's points (None:
    any): the points of a chunk are kept when only what was computed from them is lost,
    since its parts are gone once it is assembled."""
    points = name is None or name in POINT_ARRAYS
    cleared = {"done": {}, **({"assembled": None} if points else {})}
    parts = group.path.split("/")
    for depth in range(len(parts), 0, -1):
        try:
            node = zarr.open_group(store=group.store, path="/".join(parts[:depth]), mode="r+")
            if node.attrs.get("done") or (points and node.attrs.get("assembled")):
                node.update_attributes(cleared)
        except Exception:  # noqa: BLE001 - a read-only or half-deleted store: nothing to clear
            continue


def forget_done(group: zarr.Group) -> None:
    """Clear every done-mark of ``group`` (and its assembly mark): its steps run again."""
    if group.attrs.get("done") or group.attrs.get("assembled"):
        group.update_attributes({"done": {}, "assembled": None})


def is_done(group: zarr.Group, step: str, fingerprint: str) -> bool:
    """True when ``step`` completed for this group with the same configuration fingerprint."""
    return group.attrs.get("done", {}).get(step) == fingerprint


def mark_done(group: zarr.Group, step: str, fingerprint: str, **attrs) -> None:
    """Record that ``step`` completed, with ``attrs`` (its summary, ...), in one write of the
    group's metadata: a run killed at any moment leaves the mark with its attributes or
    neither (``group.attrs.update`` would write the metadata once per key). Call only after
    every output is written."""
    done = dict(group.attrs.get("done", {}))
    done[step] = fingerprint
    group.update_attributes({"done": done, **attrs})
