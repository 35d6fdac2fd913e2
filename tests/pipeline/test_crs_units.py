"""Coordinates must be metres: CRSs in degrees or feet are refused in one line."""

import pyproj
import pytest

from pipeline.errors import InputError
from pipeline.io.crs import check_metres


def _wkt(*codes):
    parts = [pyproj.CRS.from_epsg(c) for c in codes]
    crs = parts[0] if len(parts) == 1 else pyproj.crs.CompoundCRS("compound", parts)
    return crs.to_wkt()


@pytest.mark.parametrize("wkt", [
    None, "", _wkt(32633), _wkt(25832, 5783), _wkt(2056), "not a WKT pyproj reads",
])
def test_metres_and_unknown_crss_pass(wkt):
    check_metres(wkt, "t.laz", (500_000.0, 5_500_000.0))


def test_a_geographic_crs_is_refused_with_the_reprojection_to_its_utm_zone():
    with pytest.raises(InputError) as err:
        check_metres(_wkt(4326), "plot.laz", (10.4, 50.1))
    line = str(err.value)
    assert "\n" not in line and "plot.laz" in line and "EPSG:4326" in line
    assert "geographic (degrees)" in line
    assert ("pdal translate plot.laz metres.laz reprojection "
            "--filters.reprojection.out_srs=EPSG:32632") in line
    with pytest.raises(InputError, match="out_srs=EPSG:32719"):  # UTM 19S
        check_metres(_wkt(4979), "andes.laz", (-70.0, -33.4))
    with pytest.raises(InputError, match="geographic.*out_srs=EPSG:<code"):  # not lon, lat
        check_metres(_wkt(4326), "x.laz", (500e3, 5e6))


@pytest.mark.parametrize("codes, unit", [
    ((2227,), "US survey foot"),  # NAD83 / California zone 3 (ftUS)
    ((2272,), "US survey foot"),  # NAD83 / Pennsylvania South (ftUS)
    ((25832, 6360), "US survey foot"),  # metres across, heights in feet (NAVD88 ftUS)
])
def test_other_linear_units_are_refused_naming_the_unit(codes, unit):
    with pytest.raises(InputError) as err:
        check_metres(_wkt(*codes), "feet.laz")
    line = str(err.value)
    assert "\n" not in line and "feet.laz" in line and f"in {unit}" in line
    assert "--filters.reprojection.out_srs=" in line


def test_a_geocentric_crs_is_refused():
    with pytest.raises(InputError, match="geocentric"):
        check_metres(_wkt(4978), "ecef.laz")
