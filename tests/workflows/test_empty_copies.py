"""A thinned copy that would hold no point (data.densities far below the training scene's) is
skipped, saying so by name, instead of failing later in its terrain model."""

from types import SimpleNamespace

from pipeline.store import open_store
from tests.workflows.conftest import silva, write_config
from workflows.store.scenes import Thinning


def test_a_density_whose_copy_would_be_empty_makes_none_and_says_why(tiny_survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", tiny_survey, data={"densities": [0.001]},
                          features={"set": "covariance", "r1": 0.5})
    plan = silva("plan", config)
    assert plan.exit_code == 0, plan.output
    line = next(line for line in plan.output.splitlines()
                if line.startswith("data.densities 0.001"))
    assert line.startswith("data.densities 0.001: no copy of scene train: thinned from ")
    assert "would leave about none" in line and "remove 0.001 from data.densities" in line
    out = tmp_path / "out"
    result = silva("features", config, "--out", out, "--in-process")
    assert result.exit_code == 0, result.output
    assert line in result.output
    scenes = open_store(out / "store.zarr", mode="r").attrs["layout"]["scenes"]
    assert sorted(scenes) == ["test", "train"]


def test_a_copy_that_kept_no_point_is_skipped_by_name(capsys):
    from workflows.steps.copies import without_empty_copies

    thinning = Thinning("train", 0.5, 0.6, 1)
    scenes = {"train": SimpleNamespace(thinning=None, chunks=("0_0",)),
              "train@0.5ppm": SimpleNamespace(thinning=thinning, chunks=()),
              "test": SimpleNamespace(thinning=None, chunks=("0_0",))}
    assert list(without_empty_copies(scenes)) == ["train", "test"]
    said = capsys.readouterr().err
    assert said.startswith("ingest: copy train@0.5ppm: the thinning kept none of the points "
                           "of scene train (fraction 0.6, about 1 expected): skipped")
    assert "remove 0.5 from data.densities" in said
    kept = {**scenes, "train@0.5ppm": SimpleNamespace(thinning=thinning, chunks=("0_0",))}
    assert list(without_empty_copies(kept)) == list(kept)
