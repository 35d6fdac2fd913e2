"""A store removed after its run (``output.keep_store: false``): the record of what the run
completed, kept in the store's attributes once its chunks are gone."""

import zarr


def remove_chunks(root: zarr.Group, record: dict) -> None:
    """Remove every scene (chunks, parts and tile marks: the bulk of the store), keeping the
    root's attributes and the export marks; ``record`` describes the finished run and is kept
    as the root's ``removed`` attribute (see :func:`removed_record`)."""
    root.update_attributes({"removed": record})  # first: a kill in between leaves it marked
    if "scenes" in root:
        del root["scenes"]


def removed_record(root: zarr.Group) -> dict | None:
    """What :func:`remove_chunks` recorded, or None when the store holds its chunks."""
    return root.attrs.get("removed") or None


def forget_removed(root: zarr.Group) -> None:
    """Clear a removed store completely (layout, export marks, record): a run starts afresh."""
    for key in ("scenes", "exports"):
        if key in root:
            del root[key]
    root.update_attributes({"layout": None, "removed": None})
