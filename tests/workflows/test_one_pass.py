"""Scenes no forest trains on are classified in one pass per chunk: the same bits as the
stage-by-stage cascade over stored features, a store without features, and a run killed
in the middle of it resumes to the same result without redoing finished chunks."""

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.features.density import capped_halo
from pipeline.store import open_store
from pipeline.tiling import BalancedLayout, Grid
from workflows.config import load_config
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.steps.ingest import plan_scenes, plan_tiles
from workflows.steps.one_pass import MAX_BORDER_SHARE, border_share
from workflows.store.scenes import SceneLayout
from workflows.steps.table import STEPS
from tests.workflows.conftest import (
    assert_same_predictions,
    read_predictions,
    sigkill_when,
    silva,
    write_config,
)

pytestmark = pytest.mark.slow

SMALL_CHUNKS = {"chunk_size": "auto", "target_points": 12_000}


def _members(out: Path, scene: str) -> set[str]:
    """The array names stored in the chunks of a scene."""
    root = open_store(out / "store.zarr", mode="r")
    chunks = root[f"scenes/{scene}/chunks"]
    return {name for chunk in chunks.group_keys()
            for name in chunks[chunk].attrs.get("arrays", {})}


def _apply_marks(out: Path) -> dict[str, int]:
    """mtime of the results of every chunk whose one-pass step is marked done."""
    marks = {}
    for meta in (out / "store.zarr").glob("scenes/*/chunks/*/zarr.json"):
        try:
            done = json.loads(meta.read_text())["attributes"].get("done", {})
        except (OSError, ValueError, KeyError):
            continue
        pack = meta.parent / "predictions" / "zarr.json"
        if "apply" in done and pack.exists():
            marks[str(meta.parent)] = pack.stat().st_mtime_ns
    return marks


def _attributes(chunk: str) -> dict:
    """The done-marks and assembly mark of a chunk, from its metadata."""
    attrs = json.loads((Path(chunk) / "zarr.json").read_text())["attributes"]
    return {"done": attrs.get("done"), "results": sorted(attrs.get("results", {})),
            "assembled": attrs.get("assembled")}


def _same_test_tiles(a: Path, b: Path) -> None:
    """The tiles of ``b`` were exported by ``a`` too, with the same predictions."""
    pa, pb = read_predictions(a), read_predictions(b)
    assert pb and set(pb) <= set(pa)
    for tile in pb:
        for dim in ("PredictedClassification", "Confidence", "Probability_tree"):
            assert np.array_equal(pa[tile][dim], pb[tile][dim]), (tile, dim)


def test_the_same_bits_as_stored_features_and_a_store_without_them(survey_run, survey_run_kept):
    _, out = survey_run  # its test scene classified in one pass
    kept = survey_run_kept  # the same config with output.keep_features true
    assert_same_predictions(out, kept)
    assert json.loads((out / "metrics.json").read_text()) == json.loads(
        (kept / "metrics.json").read_text())
    # the test scene keeps its points, its cells' lowest points (the terrain model's input),
    # the last stage's probabilities, the first's labels and the flags; the train scene its
    # features
    assert _members(out, "test") == {"xyz", "gid", "label", "role", "halo_xyz", "halo_gid",
                                     "minima_keys", "minima_z", "minima_xy", "undefined",
                                     "stage1_labels", "stage2_proba"}
    assert "features" in _members(out, "train") and "features" in _members(kept, "test")
    size = {d: sum(f.stat().st_size for f in (d / "store.zarr/scenes/test").rglob("*")
                   if f.is_file()) for d in (out, kept)}
    assert size[out] * 2 < size[kept]


def test_predict_in_one_pass_over_many_chunks(survey_run, survey, tmp_path, dask_cluster):
    """A saved model applied to balanced chunks in one pass, on two workers (the session's
    cluster), gives what the stage-by-stage cascade gives with the features kept (in this
    process); one chunk recomputed alone (--chunk) gives its bits again."""
    _, out = survey_run
    config = write_config(tmp_path / "p.yaml", survey, tiling=SMALL_CHUNKS,
                          data={"train": [], "test": [], "predict": [
                              str(survey["test"] / "*.laz")]},
                          cluster=dask_cluster)
    runs = {}
    for keep in ("false", "true"):
        runs[keep] = tmp_path / f"keep_{keep}"
        here = ["--in-process"] if keep == "true" else []
        result = silva("predict", config, "--model", out / "model", "--out", runs[keep],
                       "--quiet", *here, "--set", f"output.keep_features={keep}")
        assert result.exit_code == 0, result.output
        folded = "[2/6] features: computed with the stages, in one pass per chunk"
        assert (folded in result.output) == (keep == "false")
    assert_same_predictions(runs["false"], runs["true"])
    _same_test_tiles(out, runs["false"])  # the run's own test scene, in one chunk
    assert "features" not in _members(runs["false"], "predict")
    layout = open_store(runs["false"] / "store.zarr", mode="r").attrs["layout"]
    chunks = layout["scenes"]["predict"]["chunks"]
    assert len(chunks) >= 4
    again = ("predict", config, "--model", out / "model", "--out", runs["false"], "--quiet",
             "--in-process", "--set", "output.keep_features=false")
    result = silva(*again, "--chunk", f"predict/{chunks[1]}")
    assert result.exit_code == 0, result.output
    result = silva(*again)
    assert result.exit_code == 0, result.output
    assert_same_predictions(runs["true"], runs["false"])


def test_resume_after_sigkill_in_the_one_pass(survey_run, survey, tmp_path, dask_cluster):
    _, out = survey_run
    # killed in its own process, resumed on the session's cluster
    config = write_config(tmp_path / "k.yaml", survey, tiling={"chunk_size": 5.0},
                          data={"train": []}, output={"keep_features": False},
                          cluster=dask_cluster)
    killed = tmp_path / "killed"
    sigkill_when(["predict", config, "--model", out / "model", "--out", killed, "--quiet",
                  "--in-process"], lambda: len(_apply_marks(killed)) >= 3)
    done_before = _apply_marks(killed)
    layout = open_store(killed / "store.zarr", mode="r").attrs["layout"]
    assert 3 <= len(done_before) < len(layout["scenes"]["test"]["chunks"]), \
        "the kill did not land inside the one pass"
    marks = {chunk: _attributes(chunk) for chunk in done_before}  # to tell why, should one rerun
    result = silva("predict", config, "--model", out / "model", "--out", killed, "--quiet")
    assert result.exit_code == 0, result.output
    after = _apply_marks(killed)
    redone = [chunk for chunk, mtime in done_before.items() if after.get(chunk) != mtime]
    assert not redone, "; ".join(f"{chunk} was recomputed; its marks when killed: "
                                 f"{marks[chunk]}, after: {_attributes(chunk)}"
                                 for chunk in redone)
    _same_test_tiles(out, killed)
    assert np.isfinite(json.loads((killed / "metrics.json").read_text())["macro"]["f1"])


def test_the_default_set_in_one_pass_over_many_chunks_equals_one_stored_chunk(survey,
                                                                              tmp_path):
    """The default set (several radii, height columns, voxels; the covariance set is a part
    of it) reaches further than the paper's: in one pass over many chunks it gives the bits
    of one chunk with stored features. On a strip of two tiles a plot (14 m x 7 m): 4 x 2
    chunks of 4 m, the test scene's halo wider than a chunk."""
    features = {"set": "default", "voxel": "auto"}
    strip = {"train": [str(survey["train"] / "*_0.laz")],
             "test": [str(survey["test"] / "*_0.laz")]}
    runs = {}
    for name, tiling, keep in (("one_pass", {"chunk_size": 4.0}, "false"),  # halos > 4 m
                               ("stored", {"chunk_size": 100.0}, "true")):
        config = write_config(tmp_path / f"{name}.yaml", survey, tiling=tiling,
                              features={"r1": 0.5, **features}, data=strip)
        runs[name] = tmp_path / name
        result = silva("run", config, "--out", runs[name], "--quiet", "--in-process",
                       "--set", f"output.keep_features={keep}")
        assert result.exit_code == 0, result.output
    root = open_store(runs["one_pass"] / "store.zarr", mode="r")
    test = root.attrs["layout"]["scenes"]["test"]
    assert len(test["chunks"]) >= 8 and test["grid"]["nx"] >= 3 and test["one_pass"]
    assert test["halo"] > test["grid"]["size"]  # a chunk's window reaches past its neighbours
    assert len(read_predictions(runs["stored"])) == 4  # two tiles of each plot
    # the chunks, one after the other, read their borders' features from the chunks before
    shared = [root[f"scenes/test/chunks/{chunk}"].attrs["results"]["apply"]["shared_features"]
              for chunk in test["chunks"]]
    assert shared[0] == 0 and sum(shared) > 0, shared
    assert "borders" not in root["scenes/test"]  # scratch, removed with the step
    assert_same_predictions(runs["one_pass"], runs["stored"])


def test_auto_leaves_scenes_of_small_chunks_to_the_stored_features(survey, tmp_path):
    """keep_features auto: a scene gets the halo of the one pass unless the borders of its
    chunks hold more than an eighth of its points; false and true decide alone; the train
    scene never gets it. The halo then decides which scenes go in one pass."""
    def planned(keep, size):
        cfg = load_config(write_config(tmp_path / "c.yaml", survey, tiling={"chunk_size": size},
                                       output={"keep_features": keep}))
        run = Run(resolve_run(cfg), tmp_path / "out", quiet=True, steps=STEPS)
        scenes = plan_scenes(run, plan_tiles(run))
        return ({scene: info.halo for scene, info in scenes.items()},
                {scene for scene, info in scenes.items() if info.one_pass})

    # write_config's paper set at r1 0.5, and with 2 stages
    reach = capped_halo(0.5)
    wide = round(2 * reach + 0.01, 6)
    assert planned("auto", 100.0) == planned(False, 3.0) == (
        {"train": reach, "test": wide}, {"test"})
    assert planned("auto", 3.0) == planned(True, 100.0) == (
        {"train": reach, "test": reach}, set())
    assert not (tmp_path / "out").exists()  # planning writes nothing

    # the halo 1.01 m, the ring 0.5 m: squares of 30 m have 0.14 of their points beside
    # them within the halo, half of that within the ring; squares of 15 m twice as many
    def grid(size):
        return SceneLayout(Grid(0.0, 0.0, size, 3, 3), 1.01, groups=())

    share = {size: border_share(grid(size), 0.5) for size in (15.0, 30.0)}
    assert share[30.0] == pytest.approx(((30 + 2.02) ** 2 - 30**2) / 30**2 * 0.5 / 1.01)
    assert share[30.0] < MAX_BORDER_SHARE < share[15.0]
    balanced = SceneLayout(BalancedLayout(((0, 10.0, -1, -2),), 0.25, (0.0, 0.0, 20.0, 20.0)),
                           1.52, groups=(),
                           estimate={"core": [700, 771, 800], "window": [900, 956, 990]})
    assert border_share(balanced, 1.0) == pytest.approx((956 / 771 - 1) / 1.52)
