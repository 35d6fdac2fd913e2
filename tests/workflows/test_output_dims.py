"""Output options: feature columns as extra dimensions (output.feature_dims) and the input's
point format kept (output.point_format: keep), round-tripped through laspy."""

import laspy
import numpy as np
import pytest

from pipeline.store import open_store, read_array, rows_of
from pipeline.tiling import global_ids
from workflows.cli.commands import RunOptions, start_run
from workflows.config.schema import feature_dim_name
from tests.workflows.conftest import error_line, silva, write_config


def _legacy_copy(src, dst, point_format, drop_code):
    """src without its points of class ``drop_code``, as LAS 1.2 in a legacy point format."""
    las = laspy.read(src)
    keep = las.classification != drop_code
    header = laspy.LasHeader(version="1.2", point_format=point_format)
    header.scales, header.offsets = las.header.scales, las.header.offsets
    out = laspy.LasData(header)
    out.X, out.Y, out.Z = las.X[keep], las.Y[keep], las.Z[keep]
    out.classification = np.asarray(las.classification)[keep]
    out.intensity = np.arange(int(keep.sum()), dtype=np.uint16)
    out.write(dst)
    return dst


@pytest.fixture(scope="module")
def legacy(survey, tmp_path_factory):
    """The survey's smallest test tile as LAS 1.2 point format 3, without its dead wood
    (code 64 does not fit the 0..31 of formats 0-5): codes 1, 2 and 5."""
    src = min(survey["test"].glob("*.laz"), key=lambda p: p.stat().st_size)
    root = tmp_path_factory.mktemp("legacy")
    return _legacy_copy(src, root / "fit.las", point_format=3, drop_code=64)


def _config(path, survey, tile, classes=None, **output):
    las = laspy.read(tile)
    data = {"train": [str(tile)], "test": [],
            "split": {"axis": "y", "at": float(np.median(las.y))}}
    if classes:
        data.update(classes=classes, background=[])
    return write_config(path, survey, data=data, tiling={"chunk_size": 3.0},
                        cascade={"stages": 1}, output=output)


INVARIANTS = ["I2_22", "I2_222", "I3_33", "I3_11", "I23_3_2", "I23_31_2", "I23_1_2",
              "I3_3333", "I3_3131", "I3_3331", "I3_3111"]  # the paper set's columns


def test_feature_dims_and_kept_point_format_round_trip(legacy, survey, tmp_path):
    tile = legacy
    config = _config(tmp_path / "c.yaml", survey, tile,
                     classes={"terrain": [2], "tree": [5], "misc": [1]},
                     point_format="keep", write_classification=True,
                     feature_dims=["I2_22", "I3_3*"], format="las")
    out = tmp_path / "out"
    start_run(config, RunOptions(out, quiet=True, in_process=True), "export")
    src = laspy.read(tile)
    dst = laspy.read(out / "predictions" / "fit.las")
    assert str(dst.header.version) == "1.2" and dst.point_format.id == 3
    for name in src.point_format.dimension_names:  # every input value, untouched
        if name != "classification":
            assert np.array_equal(np.asarray(dst[name]), np.asarray(src[name])), name
    assert np.array_equal(dst.classification, dst["PredictedClassification"])
    assert set(np.unique(dst.classification)) <= {1, 2, 5}
    columns = ["I2_22", "I3_33", "I3_3333", "I3_3131", "I3_3331", "I3_3111"]
    extra = list(dst.point_format.extra_dimension_names)
    assert [c for c in extra if c.startswith("I")] == columns
    # each written column equals the feature stored for its point
    root = open_store(out / "store.zarr", mode="r")
    gid = global_ids(root.attrs["layout"]["tiles"][0]["index"], 0, len(src))
    checked = 0
    for chunk in root["scenes/train/chunks"].group_keys():
        group = root[f"scenes/train/chunks/{chunk}"]
        ids, features = read_array(group, "gid"), read_array(group, "features")
        pos, hit = rows_of(gid, ids)
        assert hit.all()
        for column in columns:
            stored = features[:, INVARIANTS.index(column)]
            assert np.array_equal(np.asarray(dst[column])[pos], stored, equal_nan=True)
        checked += len(ids)
    assert checked == len(src)


def test_kept_legacy_format_refuses_class_codes_above_31_before_any_work(legacy, survey,
                                                                          tmp_path):
    # the default classes of write_config include dead_wood, output code 64
    config = _config(tmp_path / "c.yaml", survey, legacy, point_format="keep",
                     write_classification=True)
    out = tmp_path / "out"
    line = error_line(silva("run", config, "--out", out, "--quiet", "--in-process"))
    assert "output.point_format keep cannot write class code 64" in line
    assert "point format 3 holds codes 0..31" in line and "output.point_format: auto" in line
    # refused after reading the headers, before the store holds anything
    assert not (out / "store.zarr").exists() or "scenes/train/chunks" not in open_store(
        out / "store.zarr", mode="r")


def test_every_feature_set_gives_valid_dimension_names():
    from workflows.config import validate_config

    for name in ("paper", "covariance", "default"):
        for r1 in (0.05, 0.5, 3.7183, 40.0):
            cfg = validate_config({"features": {"set": name, "r1": r1},
                                   "output": {"feature_dims": "all"}})
            dims = [feature_dim_name(c) for c in cfg.feature_dim_columns]
            assert len(set(dims)) == len(dims)
            assert all(len(d.encode()) <= 32 and d.replace("_", "").isalnum() for d in dims)
