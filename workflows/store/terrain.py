"""Each scene's terrain model in the store."""

import numpy as np
import zarr

from pipeline.errors import StoreError
from pipeline.store import write_arrays
from pipeline.terrain import Raster
from workflows.store.layout import terrain_path
from workflows.store.marks import mark_done, read_array


def write_terrain(root: zarr.Group, scene: str, dtm: Raster, interpolated: float,
                  fingerprint: str) -> None:
    """Store the terrain model of ``scene`` and mark it done with ``fingerprint``."""
    group = root.require_group(terrain_path(scene))
    write_arrays(group, {"dtm": np.asarray(dtm.values, dtype=np.float64)})
    mark_done(group, "terrain", fingerprint, x0=float(dtm.x0), y0=float(dtm.y0),
              cell=float(dtm.cell), interpolated=float(interpolated))


def terrain_done(root: zarr.Group, scene: str) -> str | None:
    """The fingerprint the stored terrain model of ``scene`` was made with (None: none)."""
    path = terrain_path(scene)
    return root[path].attrs.get("done", {}).get("terrain") if path in root else None


def read_terrain(root: zarr.Group, scene: str) -> Raster:
    """The stored terrain model of ``scene``."""
    if terrain_done(root, scene) is None:
        raise StoreError(f"the terrain model of scene '{scene}' is missing from the store; "
                         "run the same command again (or start afresh with --overwrite)")
    group = root[terrain_path(scene)]
    attrs = group.attrs
    return Raster(read_array(group, "dtm"), attrs["x0"], attrs["y0"], attrs["cell"])
