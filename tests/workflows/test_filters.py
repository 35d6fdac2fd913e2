"""Ingest filters: excluded points (noise codes, withheld flag) are in no chunk and no
neighbourhood, are not scored, and are exported unchanged with the Excluded marking."""

import json

import laspy
import numpy as np
import pytest

from pipeline.errors import ConfigError
from pipeline.io import write_las
from pipeline.store import open_store, read_array
from pipeline.tiling import global_ids
from workflows.cli.commands import RunOptions, start_run
from workflows.config import validate_config
from tests.workflows.conftest import read_predictions, write_config

NOISE = (7, 18)


def _run(config, out, target):
    return start_run(config, RunOptions(out, quiet=True, in_process=True), target)


def _with_noise(src, dst, seed, withheld=False):
    """dst = src plus noise points (codes 7 and 18) inside its bounding box, scattered
    through the file's point order; with ``withheld``, a few more points carry the withheld
    flag. Returns the bool mask of the added points in dst."""
    las = laspy.read(src)
    xyz = np.c_[las.x, las.y, las.z]
    rng = np.random.default_rng(seed)
    n_noise = 60
    low, high = xyz.min(axis=0), xyz.max(axis=0)
    noise = rng.uniform(low + 0.5, high - 0.5, size=(n_noise, 3))
    noise[:, 2] = rng.uniform(low[2], low[2] + 3.0, n_noise)  # among the points, not above
    n = len(xyz) + n_noise
    added = np.zeros(n, dtype=bool)
    added[rng.choice(n, n_noise, replace=False)] = True
    out_xyz = np.empty((n, 3))
    out_xyz[~added], out_xyz[added] = xyz, noise
    classes = np.empty(n, dtype=np.uint8)
    classes[~added] = las.classification
    classes[added] = rng.choice(NOISE, n_noise)
    flags = np.zeros(n, dtype=np.uint8)
    if withheld:  # withheld points keep an ordinary class code: only the flag excludes them
        picked = np.flatnonzero(added)[:10]
        flags[picked] = 1
        classes[picked] = 2
    write_las(dst, out_xyz, fields={"classification": classes, "withheld": flags},
              crs_wkt=las.header.parse_crs().to_wkt() if las.header.parse_crs() else None,
              scale=las.header.scales, offset=las.header.offsets)
    return added


@pytest.fixture(scope="module")
def noisy(survey, tmp_path_factory):
    """The survey's first test tile, clean and with noise; and the noise mask."""
    root = tmp_path_factory.mktemp("noisy")
    src = min(survey["test"].glob("*.laz"), key=lambda p: p.stat().st_size)  # quick runs
    (root / "clean").mkdir()
    (root / "noisy").mkdir()
    clean = root / "clean" / "plot.laz"
    clean.write_bytes(src.read_bytes())
    added = _with_noise(src, root / "noisy" / "plot.laz", seed=5, withheld=True)
    return {"clean": clean, "noisy": root / "noisy" / "plot.laz", "added": added,
            "root": root}


def _config(path, survey, tile, scene="predict", ranges=1, **data):
    """One tile in ``scene``, read in ``ranges`` point ranges; a train tile is split in two
    at its middle (y)."""
    if scene == "train":
        las = laspy.read(tile)
        data["split"] = {"axis": "y", "at": float(np.median(las.y))}
    target = -(-laspy.open(tile).header.point_count // ranges)
    return write_config(path, survey, data={"train": [], "test": [], scene: [str(tile)], **data},
                        tiling={"chunk_size": 3.0, "target_points": target},
                        cascade={"stages": 1})


def test_excluded_points_are_in_no_chunk_and_change_no_feature(noisy, survey, tmp_path):
    runs = {}
    # the noisy tile read in three point ranges: the same chunks, the excluded points summed
    for name, ranges, data in (
            ("clean", 1, {}),
            ("noisy", 3, {"exclude_codes": list(NOISE), "exclude_withheld": True})):
        config = _config(tmp_path / f"{name}.yaml", survey, noisy[name], ranges=ranges, **data)
        summary = _run(config, tmp_path / name, "features")
        runs[name] = (open_store(tmp_path / name / "store.zarr", mode="r"), summary)
    (clean, clean_summary), (noisy_store, noisy_summary) = runs["clean"], runs["noisy"]
    assert noisy_summary["excluded points"] == int(noisy["added"].sum())
    assert clean_summary["excluded points"] == 0
    layout = noisy_store.attrs["layout"]
    assert len(layout["scenes"]["predict"]["tiles"]) == 3
    index = next(t["index"] for t in layout["tiles"] if t["path"] == str(noisy["noisy"]))
    noise_gid = global_ids(index, 0, len(noisy["added"]))[noisy["added"]]
    chunks = layout["scenes"]["predict"]["chunks"]
    assert chunks == clean.attrs["layout"]["scenes"]["predict"]["chunks"] and len(chunks) > 1
    for chunk in chunks:
        a = clean[f"scenes/predict/chunks/{chunk}"]
        b = noisy_store[f"scenes/predict/chunks/{chunk}"]
        for name in ("gid", "halo_gid"):
            assert not np.isin(read_array(b, name), noise_gid).any(), (chunk, name)
        for name in ("xyz", "halo_xyz"):
            assert np.array_equal(read_array(a, name), read_array(b, name)), (chunk, name)
        fa, fb = read_array(a, "features"), read_array(b, "features")
        assert np.array_equal(fa, fb, equal_nan=True), chunk


def test_excluded_points_are_exported_unchanged_and_not_scored(noisy, survey, tmp_path):
    config = _config(tmp_path / "c.yaml", survey, noisy["noisy"], scene="train",
                     exclude_codes=list(NOISE), exclude_withheld=True)
    config.write_text(config.read_text() + "output: {write_classification: true}\n")
    summary = _run(config, tmp_path / "out", "evaluate")
    added = noisy["added"]
    assert summary["excluded points"] == int(added.sum())
    src = laspy.read(noisy["noisy"])
    dims = read_predictions(tmp_path / "out")["plot"]
    assert np.array_equal(dims["X"], np.asarray(src.X))  # every point, in its order
    assert np.array_equal(dims["classification"][added], np.asarray(src.classification)[added])
    assert np.all(dims["Excluded"][added] == 1) and np.all(dims["Excluded"][~added] == 0)
    assert np.all(dims["PredictedClassification"][added] == 0)
    assert np.all(dims["Confidence"][added] == 0) and np.all(dims["Entropy"][added] == 0)
    assert np.all(dims["Probability_tree"][added] == 0)
    kept = ~added
    assert np.all(dims["PredictedClassification"][kept] > 0)
    assert np.array_equal(dims["classification"][kept], dims["PredictedClassification"][kept])
    # the metrics count exactly the labelled test points that were not excluded
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    tested = (np.asarray(src.y) >= float(np.median(src.y))) & kept
    labelled = np.isin(np.asarray(src.classification), [2, 5, 64, 1])
    assert int(np.sum(metrics["confusion"])) == int((tested & labelled).sum())
    assert metrics["excluded_points"] == int(added.sum())
    # the model records the filters, so a run applying it leaves the same points out
    described = json.loads((tmp_path / "out" / "model" / "model.json").read_text())
    assert described["data.exclude_codes"] == sorted(NOISE)
    assert described["data.exclude_withheld"] is True


def test_exclude_codes_config():
    cfg = validate_config({"data": {"exclude_codes": [7, 18]}})
    assert cfg.data.exclude_codes == [7, 18] and cfg.data.excludes
    assert not validate_config({}).data.excludes
    with pytest.raises(ConfigError, match=r"data.exclude_codes\[0\] must be a LAS"):
        validate_config({"data": {"exclude_codes": [300]}})
    with pytest.raises(ConfigError, match="code 2, which is a code of class 'terrain'"):
        validate_config({"data": {"classes": {"terrain": [2]}, "exclude_codes": [2]}})


def test_forest_template_excludes_noise():
    from workflows.cli.templates import template_path
    from workflows.config import load_config

    with template_path("forest") as path:
        cfg = load_config(path)
    assert cfg.data.exclude_codes == [7, 18] and cfg.data.exclude_withheld is False


def test_a_filter_that_leaves_a_scene_no_point_names_its_tiles_and_the_filter(survey, tmp_path):
    from pipeline.errors import InputError

    src = laspy.read(min(survey["test"].glob("*.laz"), key=lambda p: p.stat().st_size))
    tile = tmp_path / "all-noise.laz"
    write_las(tile, np.c_[src.x, src.y, src.z],
              fields={"classification": np.full(len(src.x), 7, np.uint8)})
    config = _config(tmp_path / "c.yaml", survey, tile, exclude_codes=[7])
    with pytest.raises(InputError) as refused:
        _run(config, tmp_path / "out", "ingest")
    message = str(refused.value)
    assert str(tile) in message and "data.exclude_codes" in message and "[7]" in message
    assert "\n" not in message
