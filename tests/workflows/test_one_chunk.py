"""``--chunk SCENE/CHUNK``: one chunk recomputed alone, with what the whole run trained."""

import shutil

import numpy as np
import pytest

from tests.workflows.conftest import assert_same_predictions, error_line, silva, write_config


@pytest.fixture(scope="module")
def plots(tmp_path_factory):
    """Two 8 m plots cut into 4 m chunks: their borders hold most points, so with
    ``keep_features: auto`` the test scene goes stage by stage."""
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("one_chunk")
    for role, seed in (("train", 1), ("test", 2)):
        write_synthetic_plot(root / role, seed=seed, size=8.0, tile_size=8.0)
    config = write_config(root / "c.yaml", {"train": root / "train", "test": root / "test"},
                          tiling={"chunk_size": 4.0},
                          cascade={"n_estimators": 4, "max_train_points": 3000})
    return config, root


@pytest.fixture(scope="module")
def finished(plots):
    """A complete run of ``plots`` (copy it before changing it)."""
    config, root = plots
    out = root / "finished"
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return out


def _copy(finished, out):
    shutil.copytree(finished, out)
    return out


def _chunk_arrays(out, scene, chunk):
    from pipeline.store import open_store, read_array
    from workflows.store.layout import chunk_path

    group = open_store(out / "store.zarr", mode="r")[chunk_path(scene, chunk)]
    return {name: read_array(group, name) for name in sorted(group.attrs["arrays"])}


def _forget_chunk(out, scene, chunk):
    """Remove the done-marks of one chunk, as if its tasks had never finished."""
    from pipeline.store import open_store
    from workflows.store.layout import chunk_path

    group = open_store(out / "store.zarr")[chunk_path(scene, chunk)]
    group.attrs["done"] = {}


def _chunks(out, scene):
    from pipeline.store import open_store

    return open_store(out / "store.zarr", mode="r").attrs["layout"]["scenes"][scene]["chunks"]


@pytest.mark.parametrize("scene", ["train", "test"])
def test_one_chunk_recomputes_every_stage_to_the_same_bits(plots, finished, scene, tmp_path):
    config, _ = plots
    out = _copy(finished, tmp_path / "out")
    chunk = _chunks(out, scene)[1]
    before = _chunk_arrays(out, scene, chunk)
    assert {"features", "stage1_proba", "stage2_proba"} <= before.keys()
    _forget_chunk(out, scene, chunk)
    result = silva("run", config, "--out", out, "--in-process", "-q", "--chunk",
                   f"{scene}/{chunk}")
    assert result.exit_code == 0, result.output
    after = _chunk_arrays(out, scene, chunk)
    assert after.keys() == before.keys()
    for name in before:  # a training chunk's out-of-fold answers follow the model's sample
        assert np.array_equal(after[name], before[name], equal_nan=True), name


def test_one_chunk_never_trains_a_stage(plots, tmp_path):
    config, _ = plots
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q", "--chunk",
                   "train/0_0")
    line = error_line(result)
    assert "--chunk train/0_0: stage 1 of the model is not trained yet" in line
    assert f"silva train CONFIG --out {out}" in line
    assert not list((out / "model").glob("*.skops"))  # no forest fitted on one chunk


def test_keep_features_changed_on_a_finished_run_takes_effect(plots, finished, tmp_path):
    config, _ = plots
    out = _copy(finished, tmp_path / "out")
    shutil.copytree(out / "predictions", tmp_path / "auto" / "predictions")
    assert "features" in _chunk_arrays(out, "test", _chunks(out, "test")[0])
    result = silva("run", config, "--out", out, "--in-process", "-q",
                   "--set", "output.keep_features=false")
    assert result.exit_code == 0, result.output
    assert "features" not in _chunk_arrays(out, "test", _chunks(out, "test")[0])  # one pass
    assert_same_predictions(tmp_path / "auto", out)
