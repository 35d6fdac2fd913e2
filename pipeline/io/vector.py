"""The tree table as CSV and as a GeoPackage of tree tops and crown polygons.

The CSV has one row per tree, the columns of :data:`~pipeline.trees.TABLE_DTYPE` at fixed
decimals (millimetres for positions and heights), an empty field where a value is unknown (NaN:
no DBH fitted, no crown, no points). The GeoPackage, in the tiles' CRS, holds two layers with
the table's attributes: ``tops`` (a point per tree with a position) and ``crowns`` (a polygon
per tree with a crown, the union of its cells on the CHM grid). GDAL comes with pyogrio's
wheel; polygons are traced by rasterio and unioned by shapely. Files are written atomically.
"""

import warnings

import numpy as np

from pipeline.atomic import atomic_path, atomic_write_text
from pipeline.trees import TABLE_DTYPE

#: Decimals of each float column in the CSV.
CSV_DECIMALS = {"x": 3, "y": 3, "z": 3, "height": 3, "crown_area": 2, "crown_diameter": 3,
                "dbh": 3}
TOPS_LAYER = "tops"
CROWNS_LAYER = "crowns"


def _csv_column(values: np.ndarray, decimals: int | None) -> list[str]:
    if decimals is None:
        return [str(v) for v in values.tolist()]
    return ["" if not np.isfinite(v) else f"{v:.{decimals}f}" for v in values.tolist()]


def write_tree_csv(path, table: np.ndarray) -> None:
    """Write the tree table (structured array of dtype TABLE_DTYPE) as CSV, atomically."""
    names = TABLE_DTYPE.names
    columns = [_csv_column(table[name], CSV_DECIMALS.get(name)) for name in names]
    lines = [",".join(names)] + [",".join(row) for row in zip(*columns)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def crown_polygons(labels: np.ndarray, x0: float, y0: float, cell: float,
                   trees: np.ndarray | None = None) -> dict:
    """{tree ID: shapely (Multi)Polygon} of the cells of each tree in ``labels`` (uint (ny, nx),
    row 0 south, 0 = none) on the grid ``x0, y0, cell``; only the trees whose IDs are in
    ``trees`` when given (e.g. one tile's)."""
    import shapely
    from rasterio.features import shapes
    from rasterio.transform import Affine

    labels = np.asarray(labels)
    wanted = labels > 0 if trees is None else np.isin(labels, trees) & (labels > 0)
    if not wanted.any():
        return {}
    (r0, r1), (c0, c1) = ((k[0], k[-1] + 1) for k in (np.flatnonzero(wanted.any(axis=1)),
                                                      np.flatnonzero(wanted.any(axis=0))))
    crop = np.where(wanted[r0:r1, c0:c1], labels[r0:r1, c0:c1], 0)
    # small consecutive values for rasterio (int32 at most), mapped back to the tree IDs
    ids, local = np.unique(crop, return_inverse=True)
    north_first = np.ascontiguousarray(local.reshape(crop.shape)[::-1], dtype=np.int32)
    transform = Affine(cell, 0.0, x0 + c0 * cell, 0.0, -cell, y0 + r1 * cell)
    pieces = {}
    for geometry, value in shapes(north_first, mask=crop[::-1] > 0, connectivity=4,
                                  transform=transform):
        pieces.setdefault(int(ids[int(value)]), []).append(shapely.geometry.shape(geometry))
    return {tree: shapely.union_all(parts) for tree, parts in sorted(pieces.items())}


def _layer(path, layer, table, geometries, crs_wkt) -> None:
    import pyogrio.raw
    import shapely

    names = list(TABLE_DTYPE.names)
    points = layer == TOPS_LAYER
    with warnings.catch_warnings():
        # the temporary file's name ends in .part; it is renamed to the .gpkg once complete
        warnings.filterwarnings("ignore", message=".*(extension|file extension)",
                                category=RuntimeWarning)
        # a tile without a CRS (a local TLS frame) gives layers without one, as its LAZ
        warnings.filterwarnings("ignore", message="'crs' was not provided", category=UserWarning)
        pyogrio.raw.write(path, shapely.to_wkb(np.asarray(geometries, dtype=object)),
                          [np.ascontiguousarray(table[name]) for name in names], names,
                          layer=layer, driver="GPKG", crs=crs_wkt, promote_to_multi=not points,
                          geometry_type="Point" if points else "MultiPolygon")


def write_tree_gpkg(path, table: np.ndarray, labels: np.ndarray, x0: float, y0: float,
                    cell: float, crs_wkt: str | None) -> None:
    """Write the tree tops and crowns as a GeoPackage, atomically.

    ``table`` holds the rows of the tree table (TABLE_DTYPE, IDs ascending) to write, e.g. one
    tile's; ``labels`` (uint (ny, nx), row 0 south) the tree ID of each CHM cell on the grid
    ``x0, y0, cell`` (a TreeModel's ``labels``, the whole scene's), of which only the table's
    trees are traced; shape (0, 0) gives an empty crowns layer. Trees without a position (no
    points, no stem) have no top; trees without crown cells no crown. NaN attributes are
    written as null.
    """
    import shapely

    located = table[np.isfinite(table["x"]) & np.isfinite(table["y"])]
    tops = shapely.points(located["x"], located["y"])
    polygons = crown_polygons(labels, x0, y0, cell, trees=table["tree_id"])
    rows = np.searchsorted(table["tree_id"], np.asarray(list(polygons), dtype=np.uint32))
    with atomic_path(path) as tmp:
        _layer(tmp, TOPS_LAYER, located, tops, crs_wkt)
        _layer(tmp, CROWNS_LAYER, table[rows], list(polygons.values()), crs_wkt)
