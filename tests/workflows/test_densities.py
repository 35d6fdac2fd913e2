"""Thinned copies of the training scene (data.densities): the rows thinned_mask keeps, the
scene's density over all its tiles, the same copies, features and model whatever the
chunking, the order of the tasks and the number of workers; never exported nor scored; in
the model, the plan and the fingerprints; none when a model is applied."""

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.cascade.thinning import point_density, thinned_mask
from pipeline.io import read_info
from pipeline.store import open_store
from workflows.config import validate_config
from workflows.exec.engine import Engine
from workflows.models import installed_models, model_summary
from workflows.steps.table import STEPS as TABLE
from pipeline.model import trained_densities
from workflows.store.layout import ROLE_TEST
from workflows.store.marks import forget_done
from tests.workflows.conftest import assert_same_predictions, scene_arrays, silva, write_config

STEPS, fingerprint = TABLE.fingerprinted, TABLE.fingerprint

pytestmark = pytest.mark.slow

DENSITIES = [400, 50, 10]  # the synthetic training plot holds about 320 points/m²
COPIES = ("train@50ppm", "train@10ppm")
SEED = 3  # cascade.seed of write_config


def dense_config(path: Path, survey: dict, **sections) -> Path:
    """write_config with data.densities and the training plot split in two by y (so that
    the copies hold test points too, which must never be scored)."""
    ys = [(read_info(p).mins[1] + read_info(p).maxs[1]) / 2
          for p in sorted(survey["train"].glob("*.laz"))]
    data = {"densities": DENSITIES, "split": {"axis": "y", "at": float(np.median(ys))},
            **sections.pop("data", {})}
    return write_config(path, survey, data=data, **sections)


def run_ok(*args) -> str:
    result = silva(*args)
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def reference(survey, tmp_path_factory) -> Path:
    """One chunk per scene, in this process."""
    root = tmp_path_factory.mktemp("dense_reference")
    config = dense_config(root / "c.yaml", survey)
    run_ok("run", config, "--out", root / "out", "--in-process", "-q")
    return root / "out"


@pytest.fixture(scope="module")
def chunked(survey, tmp_path_factory, dask_cluster) -> Path:
    """Chunks balanced by point count, a few per scene, on 2 workers (the session's): the
    tasks finish in any order."""
    root = tmp_path_factory.mktemp("dense_chunked")
    config = dense_config(
        root / "c.yaml", survey, tiling={"chunk_size": "auto", "target_points": 20_000},
        cluster=dask_cluster)
    run_ok("run", config, "--out", root / "out", "-q")
    return root / "out"


def layout_of(out: Path) -> dict:
    return open_store(out / "store.zarr", mode="r").attrs["layout"]


def test_a_copy_holds_the_rows_thinned_mask_keeps(reference):
    layout = layout_of(reference)
    assert [s for s in layout["scenes"] if "@" in s] == list(COPIES)  # 400: above the scene
    source = scene_arrays(reference, "train", ("xyz", "gid", "label", "role"))
    density = layout["scenes"]["train"]["density"]
    # the scene's density over all its tiles, as point_density defines it (the oracle)
    assert density["points"] == len(source["gid"])
    assert density["value"] == point_density(source["xyz"])
    for scene, target in zip(COPIES, (50, 10)):
        info = layout["scenes"][scene]
        assert info["copy_of"] == "train" and info["target"] == target
        assert info["fraction"] == target / density["value"]
        copy = scene_arrays(reference, scene, ("xyz", "gid", "label", "role"))
        kept = thinned_mask(source["gid"], info["fraction"], SEED)
        for name in ("xyz", "gid", "label", "role"):
            assert np.array_equal(copy[name], source[name][kept]), (scene, name)
        assert abs(len(copy["gid"]) - info["expected"]) < 4 * np.sqrt(info["expected"])
    sparse, dense = (set(scene_arrays(reference, s, ("gid",))["gid"].tolist()) for s in
                     reversed(COPIES))
    assert sparse < dense  # nested


def test_copies_features_and_model_do_not_depend_on_chunks_or_workers(reference, chunked):
    for scene in ("train", *COPIES):
        a, b = scene_arrays(reference, scene), scene_arrays(chunked, scene)
        for name in ("xyz", "gid", "label", "role"):
            assert np.array_equal(a[name], b[name]), (scene, name)
        assert np.array_equal(a["features"], b["features"], equal_nan=True), scene
    # the copies' features are their own: a sparse neighbourhood, not the scene's
    train, sparse = scene_arrays(reference, "train"), scene_arrays(reference, COPIES[1])
    rows = np.searchsorted(train["gid"], sparse["gid"])
    assert not np.array_equal(train["features"][rows], sparse["features"], equal_nan=True)
    assert len(layout_of(chunked)["scenes"][COPIES[0]]["chunks"]) >= 3
    models = [json.loads((out / "model" / "model.json").read_text())
              for out in (reference, chunked)]
    for key in ("data.densities", "training_copies", "training_fractions"):
        assert models[0][key] == models[1][key]
    assert [s["training_rows"] for s in models[0]["stages"]] == [
        s["training_rows"] for s in models[1]["stages"]]
    assert_same_predictions(reference, chunked)


def test_the_forests_do_not_follow_the_order_tasks_finish_in(reference, survey, tmp_path,
                                                            monkeypatch):
    """A point and its copies share a global id: their training rows keep one order (the
    scenes'), whatever order the engine hands the tasks' results back in."""
    mapped = Engine.map
    monkeypatch.setattr(Engine, "map", lambda self, step, tasks: dict(
        reversed(list(mapped(self, step, tasks).items()))))
    config = dense_config(tmp_path / "c.yaml", survey)
    run_ok("run", config, "--out", tmp_path / "out", "--in-process", "-q")
    assert_same_predictions(reference, tmp_path / "out")


def test_copies_are_never_exported_or_scored(reference, survey):
    tiles = sorted(p.name for key in ("train", "test") for p in survey[key].glob("*.laz"))
    assert sorted(p.name for p in (reference / "predictions").iterdir()) == tiles
    metrics = json.loads((reference / "metrics.json").read_text())
    scored = 0
    for scene in ("train", "test"):
        points = scene_arrays(reference, scene, ("gid", "label", "role"))
        scored += int(np.count_nonzero((points["role"] == ROLE_TEST) & (points["label"] >= 0)))
    assert np.sum(metrics["confusion"]) == scored  # the background class too
    copy = scene_arrays(reference, COPIES[0], ("gid", "label", "role"))
    assert np.count_nonzero((copy["role"] == ROLE_TEST) & (copy["label"] >= 0)) > 100


def test_the_model_records_its_densities_and_predict_makes_no_copies(reference, survey,
                                                                     tmp_path):
    model = json.loads((reference / "model" / "model.json").read_text())
    assert trained_densities(model) == [400.0, 50.0, 10.0]
    assert [c["scene"] for c in model["training_copies"]] == list(COPIES)
    for name, directory in installed_models().items():  # saved before densities: []
        described = json.loads((directory / "model.json").read_text())
        assert "data.densities" not in described and trained_densities(described) == []
        assert model_summary(name, directory)["densities"] == []
    config = dense_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "predicted"
    output = run_ok("predict", config, "--model", reference / "model", "--out", out,
                    "--in-process")
    assert "data.densities: no thinned copies: the run applies a saved model" in output
    assert sorted(layout_of(out)["scenes"]) == ["test", "train"]
    assert json.loads((out / "metrics.json").read_text())["n_test_points"] == json.loads(
        (reference / "metrics.json").read_text())["n_test_points"]


def test_plan_shows_each_copy_and_each_density_that_makes_none(reference, survey, tmp_path):
    config = dense_config(tmp_path / "c.yaml", survey)
    lines = run_ok("plan", config).splitlines()
    layout = layout_of(reference)
    density = layout["scenes"]["train"]["density"]["value"]
    copies = [line for line in lines if line.startswith("copy ")]
    assert len(copies) == 2
    for line, scene in zip(copies, COPIES):
        info = layout["scenes"][scene]
        assert line == (
            f"copy {scene}: scene train ({density:,.1f} points/m² in its occupied 2 m cells) "
            f"thinned to {info['target']:g} points/m², fraction {info['fraction']:.4f} "
            f"(seed {SEED}): about {info['expected']:,} points, trained on, not exported "
            "or scored")
    assert (f"data.densities 400: no copy of scene train, whose density is {density:,.1f} "
            "points/m² (a copy is never denser than its scene)") in lines


def test_a_copy_not_done_is_written_again_and_other_densities_start_afresh(survey, tmp_path):
    config = dense_config(tmp_path / "c.yaml", survey, data={"densities": [50]})
    out = tmp_path / "out"
    run_ok("ingest", config, "--out", out, "--in-process", "-q")
    root = open_store(out / "store.zarr")
    marker = root["scenes/train@50ppm/parts/0"]
    counts = dict(marker.attrs["core_counts"])
    forget_done(marker)
    del marker[next(iter(marker.group_keys()))]  # and a part of it is lost
    run_ok("ingest", config, "--out", out, "--in-process", "-q")
    assert dict(root["scenes/train@50ppm/parts/0"].attrs["core_counts"]) == counts
    config = dense_config(tmp_path / "c.yaml", survey, data={"densities": [10]})
    run_ok("ingest", config, "--out", out, "--in-process", "-q")
    assert sorted(open_store(out / "store.zarr", mode="r")["scenes"].group_keys()) == [
        "test", "train", "train@10ppm"]


def test_fingerprints_follow_the_densities_and_their_seed():
    base = {"data": {"train": ["/d/t/*.laz"], "classes": {"ground": [2]}}, "tiling": {"halo": 1}}

    def prints(densities=(), seed=0):
        cfg = validate_config({**base, "data": {**base["data"], "densities": list(densities)},
                               "cascade": {"seed": seed}})
        return {step: fingerprint(cfg, step) for step in STEPS}

    plain, copies = prints(), prints([5, 2])
    assert all(plain[step] != copies[step] for step in STEPS)
    assert copies == prints([2, 5])
    assert prints([5, 2], seed=1)["ingest"] != copies["ingest"]  # the seed picks the points
    assert prints(seed=1)["ingest"] == plain["ingest"]  # without copies it does not


@pytest.mark.parametrize("densities, message", [
    ([0], "data.densities[0] must be a number of points per m² > 0, got 0.0"),
    ([5, 5.0], "data.densities lists 5 points/m² twice; list each density once"),
    (["many"], "data.densities[0] must be a number, got 'many'"),
])
def test_bad_densities_are_refused_in_one_line(densities, message):
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        validate_config({"data": {"densities": densities}})
    assert message in str(err.value)
