"""Chunks assembled from ingest's parts.

The features step assembles a chunk from the parts of every tile (:func:`chunk_points`),
writes its ``points`` pack, records the ingest fingerprint it was built from
(``assembled``) and removes those parts: a later features step with another configuration
reads the chunk's own points, and no intermediate part outlives the step.
"""

import numpy as np
import zarr

from pipeline.errors import StoreError
from pipeline.store import write_arrays
from workflows.store.layout import CORE, HALO, POINTS, RETURNS
from workflows.store.layout import chunk_path, part_path, unit_path
from workflows.store.marks import forget, forget_done, read_array, read_records

_EMPTY = {"xyz": np.empty((0, 3)), "gid": np.empty(0, np.int64),
          "label": np.empty(0, np.int16), "role": np.empty(0, np.int8),
          **{name: np.empty(0, np.uint8) for name in RETURNS}}


def tile_part(root: zarr.Group, scene: str, tile: int, chunk: str, prefix: str):
    """The part group of ``tile`` in ``chunk`` holding its ``prefix`` ("core" or "halo")
    points, or None when the tile has no such points there.

    Ingest records in the tile's marker which parts it wrote (``parts``); a part it wrote
    that is gone is a :class:`StoreError`, and the tile is marked to be ingested again.
    """
    marker = root[unit_path(scene, tile)]
    if prefix not in marker.attrs.get("parts", {}).get(chunk, []):
        return None
    path = part_path(scene, tile, chunk)
    if path not in root:
        forget(root[path.rsplit("/", 1)[0]])
        raise StoreError(f"store group '{path}' is missing; its tile is marked to be ingested "
                         "again: run the same command again (or start afresh with --overwrite)")
    return root[path]


def chunk_points(root: zarr.Group, scene: str, chunk: str, tiles, group: zarr.Group | None = None,
                 returns: bool = False) -> tuple[dict, dict]:
    """The core and halo points of a chunk, each a dict of arrays sorted by global id:
    core ``xyz`` (n, 3) f8, ``gid`` (n,) i8, ``label`` (n,) i2, ``role`` (n,) i1; halo
    ``xyz`` (m, 3) f8, ``gid`` (m,) i8.

    With ``returns``, both also hold ``return_number`` and ``number_of_returns`` (n,) u1
    (m,) u1, which ingest stored with ``features.echoes`` (a StoreError when it did not).

    The first call after an ingest gathers them from the parts of ``tiles`` (tile indices),
    writes the chunk's ``points`` pack, marks the chunk assembled from that ingest and
    removes the parts; later calls read the pack. Parts that ingest wrote and that are gone
    are one :class:`StoreError` naming them, and all their tiles are marked to be ingested
    again. ``group`` is the chunk's group when the caller holds it open (its attributes are
    then updated through it, so that the caller's later marks keep them).
    """
    group = root.require_group(chunk_path(scene, chunk)) if group is None else group
    built_from = (root.attrs.get("layout") or {}).get("fingerprint")
    if built_from is not None and group.attrs.get("assembled") == built_from:
        extra = RETURNS if returns else ()
        if extra and not set(extra) <= set(group.attrs.get("arrays", {})):
            raise _without_returns(group)
        core = {name: read_array(group, name) for name in CORE + extra}
        halo = {name: read_array(group, f"halo_{name}") for name in HALO + extra}
        return core, halo
    found, missing = {}, []
    for tile in tiles:
        for prefix in ("core", "halo"):
            try:
                found[tile, prefix] = tile_part(root, scene, tile, chunk, prefix)
            except StoreError as err:
                missing.append(err)
    if missing:
        more = f" (and {len(missing) - 1} more tiles)" if len(missing) > 1 else ""
        raise StoreError(f"{missing[0]}{more}")
    records = {key: read_records(part, key[1]) for key, part in found.items()
               if part is not None}
    # one ingest stores the return numbers in every part or in none (its fingerprint says)
    extra = (RETURNS if records and all(set(RETURNS) <= set(r) for r in records.values())
             else ())
    core = _gather(records, tiles, "core", CORE + extra)
    halo = _gather(records, tiles, "halo", HALO + extra)
    write_arrays(group, {**core, **{f"halo_{name}": halo[name] for name in HALO + extra}},
                 pack=POINTS)
    if returns and not extra:
        raise _without_returns(group)
    if built_from is not None:
        group.update_attributes({"assembled": built_from})
        for tile in tiles:
            drop_part(root, scene, tile, chunk)
    return core, halo


def _gather(records: dict, tiles, prefix: str, names) -> dict:
    """The ``prefix`` (core or halo) points of a chunk from every tile's part (``records``:
    (tile, prefix) -> its record array's members), by global id."""
    arrays = {name: [] for name in names}
    for tile in tiles:
        part = records.get((tile, prefix))
        if part is not None:
            for name in names:
                arrays[name].append(part[name])
    arrays = {k: np.concatenate(v) if v else _EMPTY[k] for k, v in arrays.items()}
    order = np.argsort(arrays["gid"], kind="stable")
    return {k: v[order] for k, v in arrays.items()}


def _without_returns(group: zarr.Group) -> StoreError:
    return StoreError(f"store group '{group.path}' holds no return numbers, which "
                      "features.echoes needs: the store was ingested without them; rerun with "
                      "--overwrite")


def restart_unit(root: zarr.Group, scene: str, marker: zarr.Group) -> None:
    """Make the read unit of ``marker`` (in ``scene``) ready to be ingested again: not
    done, without the parts of an earlier (half-written or damaged) attempt, and the chunks
    built from those parts to be built again."""
    forget_done(marker)
    for name in list(marker.group_keys()):
        if chunk_path(scene, name) in root:
            forget_done(root[chunk_path(scene, name)])
        del marker[name]


def drop_part(root: zarr.Group, scene: str, tile: int, chunk: str) -> None:
    """Remove the part of ``tile`` in ``chunk`` (nothing when there is none)."""
    if part_path(scene, tile, chunk) in root:
        del root[unit_path(scene, tile)][chunk]


def drop_assembled_parts(root: zarr.Group) -> int:
    """Remove every part whose chunk is assembled from the current ingest (parts a tile
    ingested again left behind); return how many were removed."""
    built_from = (root.attrs.get("layout") or {}).get("fingerprint")
    if built_from is None or "scenes" not in root:
        return 0
    removed = 0
    for scene in list(root["scenes"].group_keys()):
        if f"scenes/{scene}/parts" not in root:
            continue
        for tile in list(root[f"scenes/{scene}/parts"].group_keys()):
            marker = root[unit_path(scene, tile)]
            for chunk in list(marker.group_keys()):
                path = chunk_path(scene, chunk)
                if path in root and root[path].attrs.get("assembled") == built_from:
                    del marker[chunk]
                    removed += 1
    return removed
