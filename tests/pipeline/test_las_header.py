"""A LAS header whose scale, offset or bounds give no real coordinates is refused when the
header is read, with the file and the header field named: never points on one value or NaN
coordinates classified further on."""

import struct
import warnings

import laspy
import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.io import export_with_extra_dims, iter_points, read_info, write_las

#: Byte offsets of float64 header fields (LAS 1.0-1.4 public header block).
FIELDS = {("x", "scale"): 131, ("y", "scale"): 139, ("z", "scale"): 147,
          ("x", "offset"): 155, ("y", "offset"): 163, ("z", "offset"): 171,
          ("x", "max"): 179, ("x", "min"): 187, ("y", "max"): 195, ("y", "min"): 203,
          ("z", "max"): 211, ("z", "min"): 219}


@pytest.fixture(params=[".las", ".laz"])
def good(request, tmp_path):
    xyz = np.random.default_rng(0).random((200, 3)) * 10 + [500_000, 5_500_000, 100]
    return write_las(tmp_path / f"good{request.param}", xyz,
                     fields={"classification": np.full(200, 2)})


def patched(path, axis, field, value):
    """A copy of ``path`` with one float64 header field set to ``value``."""
    data = bytearray(path.read_bytes())
    data[FIELDS[axis, field]:FIELDS[axis, field] + 8] = struct.pack("<d", value)
    out = path.with_name(f"{axis}_{field}_{value}{path.suffix}")
    out.write_bytes(bytes(data))
    return out


def test_the_offsets_are_those_laspy_reads(good):
    header = laspy.open(good).header
    for (axis, field), offset in FIELDS.items():
        values = {"scale": header.scales, "offset": header.offsets, "min": header.mins,
                  "max": header.maxs}[field]
        stored, = struct.unpack("<d", good.read_bytes()[offset:offset + 8])
        assert stored == values["xyz".index(axis)]


CASES = [("y", "scale", 0.0, "0"), ("x", "scale", float("nan"), "nan"),
         ("z", "scale", float("inf"), "inf"), ("x", "offset", float("nan"), "nan"),
         ("z", "offset", float("-inf"), "-inf"), ("y", "max", float("nan"), "nan"),
         ("x", "min", float("inf"), "inf")]


@pytest.mark.parametrize("axis, field, value, shown", CASES)
def test_a_header_without_real_coordinates_is_refused_when_read(good, axis, field, value,
                                                                 shown):
    bad = patched(good, axis, field, value)
    for read in (read_info, lambda p: next(iter_points(p)),
                 lambda p: export_with_extra_dims(p, p.with_name("o.las"), [], dict)):
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no numpy warning before the refusal
            with pytest.raises(InputError) as caught:
                read(bad)
        message = str(caught.value)
        assert message.startswith(f"{bad}: header {axis} {field} is {shown}; ")
        assert "re-export the tile" in message and "\n" not in message
    assert not bad.with_name("o.las").exists()


def test_a_scale_too_large_for_finite_coordinates(good):
    bad = patched(good, "x", "scale", 1e308)
    with pytest.raises(InputError, match=r"header x scale is 1e\+308, too large"):
        read_info(bad)


@pytest.mark.parametrize("axis, field, value", [("x", "scale", 1e-7), ("y", "scale", -0.001),
                                                ("z", "offset", 1e7)])
def test_unusual_but_valid_transforms_are_read(good, axis, field, value):
    ok = patched(good, axis, field, value)
    batch = next(iter_points(ok))
    assert np.isfinite(batch.xyz).all() and len(np.unique(batch.xyz[:, 0])) > 1


def test_the_check_names_the_path_it_is_given():
    from pipeline.io.las import check_header_transform

    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.01, 0.0, 0.01])
    with pytest.raises(InputError, match=r"^a\.laz: header y scale is 0; "):
        check_header_transform("a.laz", header)
    header.scales = np.array([0.01, 0.01, 0.01])
    check_header_transform("a.laz", header)
