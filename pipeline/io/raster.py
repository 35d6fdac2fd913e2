"""Rasters of a tile's points as GeoTIFF: digital terrain, surface and canopy height models.

A raster here is a window of the one grid (:mod:`pipeline.grid`), cells of side ``cell``
anchored at multiples of ``cell`` (so the rasters of neighbouring tiles line up), held south
row first as in :class:`pipeline.grid.Raster`; the GeoTIFF is written north-up, as GIS software expects,
float32, with the tile's CRS and a nodata value, through rasterio (GDAL). Files are written
atomically.
"""

import math

import numpy as np

from pipeline.atomic import atomic_path
from pipeline.errors import InputError
from pipeline.grid import Raster

NODATA = -9999.0


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
