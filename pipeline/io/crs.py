"""Coordinate reference systems of LAS tiles: GeoTIFF keys to WKT, one CRS per scene.

LAS 1.4 point formats 6-10 (everything Silva writes) store the CRS as one OGC WKT record with
the header's WKT bit set; GeoTIFF keys, the CRS records of LAS 1.0-1.3, are not allowed there.
Keys that name EPSG codes are converted with pyproj (a dependency of Silva for this reason).
"""

from collections.abc import Iterable

import laspy
import pyproj
from laspy.vlrs.known import (
    GeoAsciiParamsVlr,
    GeoDoubleParamsVlr,
    GeoKeyDirectoryVlr,
    WktCoordinateSystemVlr,
)

from pipeline.errors import InputError

_GEOTIFF_VLRS = (GeoKeyDirectoryVlr, GeoDoubleParamsVlr, GeoAsciiParamsVlr)
#: GeoTIFF keys of EPSG codes (OGC 19-008r4): projected, geographic and vertical CRS.
_PROJECTED_KEY, _GEOGRAPHIC_KEY, _VERTICAL_KEY = 3072, 2048, 4096


def crs_wkt(header: laspy.LasHeader, path=None) -> str | None:
    """The CRS of a LAS header as WKT, or None when it has no CRS record.

    The OGC WKT (E)VLR is returned as stored. Failing that, GeoTIFF keys are converted with
    pyproj (EPSG codes of the projected or geographic CRS, plus the vertical CRS when given);
    keys that name no EPSG CRS (user-defined projections, malformed keys) raise InputError
    naming ``path``.
    """
    records = list(header.vlrs) + list(header.evlrs or [])
    for record in records:
        if isinstance(record, WktCoordinateSystemVlr) and record.string.strip("\0 \n"):
            return record.string.rstrip("\0")
    keys = [r for r in records if isinstance(r, GeoKeyDirectoryVlr)]
    if not keys:
        return None
    try:
        crs = geokeys_crs(keys[0].geo_keys)
    except Exception as exc:  # noqa: BLE001 - pyproj refuses an unknown code
        crs, reason = None, " ".join(str(exc).split())
    else:
        reason = "they name no EPSG projected or geographic CRS"
    if crs is None:
        raise InputError(
            f"cannot convert the GeoTIFF CRS keys of {path} to the WKT that LAS 1.4 needs: "
            f"{reason}; assign the file an EPSG CRS (e.g. pdal translate IN OUT "
            "--writers.las.a_srs=EPSG:<code>) and use that file"
        )
    return crs.to_wkt("WKT1_GDAL") or crs.to_wkt()


def geokeys_crs(geo_keys):
    """The pyproj CRS that GeoTIFF keys name by EPSG code, or None when they name none."""
    codes = {k.id: k.value_offset for k in geo_keys if 1024 <= k.value_offset <= 32766}
    code = codes.get(_PROJECTED_KEY, codes.get(_GEOGRAPHIC_KEY))
    if code is None:
        return None
    horizontal = pyproj.CRS.from_epsg(code)
    if _VERTICAL_KEY not in codes:
        return horizontal
    vertical = pyproj.CRS.from_epsg(codes[_VERTICAL_KEY])
    return pyproj.crs.CompoundCRS(f"{horizontal.name} + {vertical.name}", [horizontal, vertical])


def add_wkt(header: laspy.LasHeader, wkt: str) -> None:
    """Store wkt as the header's only CRS record (OGC WKT VLR, global-encoding WKT bit)."""
    header.vlrs[:] = [
        v for v in header.vlrs if not isinstance(v, (WktCoordinateSystemVlr, *_GEOTIFF_VLRS))
    ]
    header.vlrs.append(WktCoordinateSystemVlr(wkt))
    header.global_encoding.wkt = True


def las14_crs(header: laspy.LasHeader, src) -> None:
    """Store the CRS as point formats 6-10 require: one OGC WKT record and the WKT bit.

    GeoTIFF keys are converted (see :func:`crs_wkt`) and removed; a WKT already stored as an
    EVLR stays there.
    """
    if any(isinstance(v, WktCoordinateSystemVlr) for v in header.evlrs or []):
        header.vlrs[:] = [v for v in header.vlrs if not isinstance(v, _GEOTIFF_VLRS)]
        header.global_encoding.wkt = True
        return
    wkt = crs_wkt(header, src)
    if wkt:
        add_wkt(header, wkt)


def check_same_crs(tiles: Iterable[tuple], where: str) -> str | None:
    """The one CRS (WKT) of ``(path, crs_wkt)`` pairs; InputError naming two tiles that differ.

    Tiles without a CRS (None) are compatible with any. Two WKT strings are the same CRS when
    pyproj finds them equal (the same CRS written as WKT1 and WKT2 is the same). ``where``
    names the tiles' config key in the message (e.g. ``data.train``).
    """
    first = None
    for path, wkt in tiles:
        if not wkt:
            continue
        if first is None:
            first = (path, wkt)
        elif wkt != first[1] and not _same_crs(wkt, first[1]):
            raise InputError(
                f"tiles {first[0]} ({crs_name(first[1])}) and {path} ({crs_name(wkt)}) of "
                f"{where} have different CRSs; reproject them to one CRS (e.g. with PDAL's "
                "filters.reprojection) or process them in separate runs"
            )
    return first[1] if first else None


def check_metres(wkt: str | None, path, centre=None) -> None:
    """Refuse (InputError, one line naming ``path``) a CRS whose coordinates are not metres.

    Radii, cells, rasters and heights above ground are in the CRS's units, all taken as
    metres: a tile in degrees would get one cell of terrain, one in feet wrong radii and
    heights in feet under a metres label. Refused: a geographic CRS (degrees; the message
    suggests the UTM zone of ``centre``, the tile's (x, y) centre, when it is a longitude
    and latitude), a geocentric one, and any axis, the vertical one of a compound CRS
    included, in another linear unit (US survey feet, feet). A tile without a CRS, or with
    a WKT pyproj cannot read, is taken as it is.
    """
    if not wkt:
        return
    try:
        crs = pyproj.CRS.from_wkt(wkt)
    except pyproj.exceptions.CRSError:
        return
    for part in crs.sub_crs_list or [crs]:
        if part.is_geographic or part.is_geocentric:
            kind = "geographic (degrees)" if part.is_geographic else "geocentric (earth-centred)"
            raise InputError(
                f"tile {path} is in a {kind} CRS, {crs_name(part.to_wkt())}, and Silva's radii, "
                "cells and heights are metres; reproject it to a projected CRS in metres "
                f"first, {_reprojection(path, _utm_hint(centre))}"
            )
        for axis in part.axis_info:
            if axis.unit_conversion_factor != 1.0:
                raise InputError(
                    f"tile {path} has coordinates in {axis.unit_name} ({axis.name}, CRS "
                    f"{crs_name(crs.to_wkt())}), and Silva's radii, cells and heights are "
                    "metres; reproject it to a CRS in metres first, "
                    f"{_reprojection(path, 'EPSG:<code of a CRS in metres>')}"
                )


def _reprojection(path, target: str) -> str:
    """The PDAL command that reprojects ``path`` to ``target``, as advice."""
    return (f"e.g. pdal translate {path} metres.laz reprojection "
            f"--filters.reprojection.out_srs={target}")


def _utm_hint(centre) -> str:
    """'EPSG:326NN' (or 327NN south) of the UTM zone of a (longitude, latitude) centre, or
    'EPSG:<code of a projected CRS in metres>' when it is not one."""
    if centre is None or not (-180.0 <= centre[0] <= 180.0 and -90.0 <= centre[1] <= 90.0):
        return "EPSG:<code of a projected CRS in metres>"
    zone = min(int((centre[0] + 180.0) // 6.0) + 1, 60)
    return f"EPSG:{(32600 if centre[1] >= 0 else 32700) + zone}"


def _same_crs(a: str, b: str) -> bool:
    try:
        return pyproj.CRS.from_wkt(a).equals(pyproj.CRS.from_wkt(b), ignore_axis_order=True)
    except pyproj.exceptions.CRSError:  # WKT that pyproj cannot read: the text decides
        return False


def crs_name(wkt: str) -> str:
    """'EPSG:32610', or the CRS's name, or the start of the WKT."""
    try:
        crs = pyproj.CRS.from_wkt(wkt)
    except pyproj.exceptions.CRSError:
        return wkt[:40]
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.name
