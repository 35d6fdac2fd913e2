"""Rasters of a tile's points as GeoTIFF: digital terrain, surface and canopy height models.

A raster here is a grid of square cells of side ``cell`` anchored at multiples of ``cell``
(so the rasters of neighbouring tiles line up), held south row first as in
:class:`pipeline.terrain.Raster`; the GeoTIFF is written north-up, as GIS software expects,
float32, with the tile's CRS and a nodata value, through rasterio (GDAL). Files are written
atomically.
"""

import math

import numpy as np

from pipeline.atomic import atomic_path
from pipeline.errors import InputError
from pipeline.terrain import Raster

NODATA = -9999.0
#: A coordinate within SNAP cells of a cell boundary is on it (see :func:`cell_coordinate`).
SNAP = 1e-6


def cell_coordinate(values, cell: float) -> np.ndarray:
    """float64: ``values`` / ``cell``, taken as the nearest integer within :data:`SNAP`: a
    coordinate on a cell boundary in decimal (LAS stores steps of 0.01 m) divides to within
    rounding of an integer (500000.3 / 0.1 = 5000002.9999999995) and must count as on it."""
    u = np.asarray(values, dtype=np.float64) / cell
    nearest = np.round(u)
    return np.where(np.abs(u - nearest) <= SNAP, nearest, u)


def tile_grid(mins, maxs, cell: float) -> tuple[float, float, int, int]:
    """(x0, y0, nx, ny) of the cells of side ``cell`` covering the half-open XY box
    [``mins``, ``maxs``), anchored at multiples of ``cell``; at least one cell each way.

    Half-open, as the chunk grid: a tile that ends on a cell boundary does not take the next
    cell, which is its neighbour's first (two tiles' rasters never share a cell, so a mosaic
    does not depend on their order). Its points on that boundary belong to its last cell
    (:func:`cell_index`).
    """
    k0 = np.floor(cell_coordinate(mins[:2], cell))
    k1 = np.ceil(cell_coordinate(maxs[:2], cell))
    nx, ny = (max(int(n), 1) for n in k1 - k0)
    return float(k0[0]) * cell, float(k0[1]) * cell, nx, ny


def cell_index(xy: np.ndarray, x0: float, y0: float, cell: float, shape) -> np.ndarray:
    """int64 (N,) flat index (row * nx + column) of the cell of each point of a grid
    anchored at multiples of ``cell`` (as :func:`tile_grid`'s), -1 outside.

    Cells hold their lower edges; a point on the grid's upper edge belongs to the last
    cell, so a grid of :func:`tile_grid` holds every point of its box, the highest too.
    """
    ny, nx = shape
    u = cell_coordinate(xy[:, 0], cell) - round(x0 / cell)
    w = cell_coordinate(xy[:, 1], cell) - round(y0 / cell)
    col = np.where(u == nx, nx - 1, np.floor(u)).astype(np.int64)
    row = np.where(w == ny, ny - 1, np.floor(w)).astype(np.int64)
    inside = (col >= 0) & (col < nx) & (row >= 0) & (row < ny)
    return np.where(inside, row * nx + col, -1)


def write_geotiff(path, raster: Raster, crs_wkt: str | None, nodata: float = NODATA) -> None:
    """Write ``raster`` (south row first, NaN = no data) as a float32 north-up GeoTIFF."""
    import rasterio
    from rasterio.transform import Affine

    values = np.asarray(raster.values, dtype=np.float64)[::-1]  # north row first
    data = np.where(np.isfinite(values), values, nodata).astype(np.float32)
    ny, nx = data.shape
    top = raster.y0 + ny * raster.cell
    profile = dict(driver="GTiff", width=nx, height=ny, count=1, dtype="float32",
                   nodata=nodata, compress="deflate", predictor=3,
                   transform=Affine(raster.cell, 0.0, raster.x0, 0.0, -raster.cell, top),
                   crs=rasterio.crs.CRS.from_wkt(crs_wkt) if crs_wkt else None)
    with atomic_path(path) as tmp:
        with rasterio.open(tmp, "w", **profile) as dst:
            dst.write(data, 1)
            dst.update_tags(AREA_OR_POINT="Area")


def read_geotiff(path) -> tuple[Raster, str | None]:
    """A GeoTIFF written by :func:`write_geotiff` as (raster, CRS WKT); nodata becomes NaN."""
    import rasterio

    try:
        with rasterio.open(path) as src:
            data = src.read(1).astype(np.float64)
            nodata, transform = src.nodata, src.transform
            wkt = src.crs.to_wkt() if src.crs else None
    except rasterio.errors.RasterioIOError as err:
        raise InputError(f"{path}: not a readable GeoTIFF ({err})") from None
    if nodata is not None:
        data[data == nodata] = np.nan
    cell = transform.a
    y0 = transform.f - data.shape[0] * cell
    return Raster(data[::-1].copy(), float(transform.c), float(y0), float(cell)), wkt


def hillshade(dem: np.ndarray, cell: float, azimuth: float = 315.0,
              altitude: float = 45.0) -> np.ndarray:
    """float64 shading in [0, 1] of a DEM held south row first (Horn's gradients via
    numpy.gradient; light from ``azimuth`` degrees clockwise from north, ``altitude``
    above the horizon); NaN where the DEM is NaN."""
    z = np.asarray(dem, dtype=np.float64)
    if min(z.shape) < 2:
        return np.where(np.isnan(z), np.nan, math.sin(math.radians(altitude)))
    filled = np.where(np.isnan(z), np.nanmean(z) if np.isfinite(z).any() else 0.0, z)
    dz_dy, dz_dx = np.gradient(filled, cell)  # rows go north
    slope = np.arctan(np.hypot(dz_dx, dz_dy))
    aspect = np.arctan2(-dz_dx, -dz_dy)  # direction the slope faces, clockwise from north
    az, alt = math.radians(azimuth), math.radians(altitude)
    shade = (math.sin(alt) * np.cos(slope)
             + math.cos(alt) * np.sin(slope) * np.cos(az - aspect))
    return np.where(np.isnan(z), np.nan, np.clip(shade, 0.0, 1.0))
