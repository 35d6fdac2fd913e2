"""output.keep_store: false removes a completed run's chunks; status and reruns stay sensible."""

from pipeline.synth import DEFAULT_ORIGIN
from tests.workflows.conftest import SMALL_PLOT, error_line, silva, write_config


def _files(path):
    return sorted(p for p in path.rglob("*") if p.is_file())


def test_a_completed_run_removes_its_chunks_and_reruns_as_complete(survey, tmp_path):
    # one plot split in two, one stage: the cheapest complete run
    config = write_config(
        tmp_path / "c.yaml", survey,
        data={"test": [], "split": {"axis": "y", "at": DEFAULT_ORIGIN[1] + SMALL_PLOT / 2}},
        features={"set": "paper"}, cascade={"stages": 1}, output={"keep_store": False})
    out = tmp_path / "out"
    first = silva("run", config, "--out", out, "--in-process", "-q")
    assert first.exit_code == 0, first.output
    assert "store: chunks removed" in (out / "silva.log").read_text()
    n_tiles = len(list(survey["train"].glob("*.laz")))
    # what is left: the root's metadata (layout, record) and one export mark per tile
    assert len(_files(out / "store.zarr")) == 2 + n_tiles
    metrics = (out / "metrics.json").read_text()

    status = silva("status", out)
    assert status.exit_code == 0, status.output
    assert "store: its chunks were removed after the run completed" in status.output
    assert f"predictions: {n_tiles} of {n_tiles} tiles exported" in status.output
    assert f"metrics: {out / 'metrics.json'}" in status.output
    assert "scene " not in status.output

    again = silva("run", config, "--out", out, "--in-process", "-q")
    assert again.exit_code == 0, again.output
    assert "the results of this configuration are complete" in again.output
    assert f"metrics: {out / 'metrics.json'}" in again.output
    assert (out / "metrics.json").read_text() == metrics

    # a step command of the same configuration: its work is part of the complete run
    export = silva("export", config, "--out", out, "--in-process", "-q")
    assert export.exit_code == 0, export.output
    assert "the results of this configuration are complete" in export.output
    assert not (out / "store.zarr" / "scenes").exists()
    # one that would redo everything for a part of it says so, and how to ask for it
    other = ("--set", "output.probabilities=false")
    line = error_line(silva("export", config, "--out", out, "--in-process", "-q", *other))
    assert line == (
        f"silva: error: {out / 'store.zarr'}: its chunks were removed after the run completed "
        "(output.keep_store: false) and it completed with another configuration, other inputs "
        "or another model; 'silva export' would compute every step up to it again from the "
        "input tiles: to do so, rerun it with --overwrite (set output.keep_store: true to "
        "keep the chunks of the next run)")
    assert (out / "metrics.json").read_text() == metrics  # refused: nothing removed
    line = error_line(silva("features", config, "--out", out, "--in-process", "-q",
                            "--chunk", "train/0_0"))
    assert "and --chunk needs the chunks; 'silva features' would compute" in line
    # the whole run of another configuration computes the chunks again from the inputs
    rerun = silva("run", config, "--out", out, "--in-process", "-q", *other,
                  "--set", "output.keep_store=true")
    assert rerun.exit_code == 0, rerun.output
    assert "computing again from the input tiles" in rerun.output
    assert (out / "store.zarr" / "scenes" / "train").is_dir()
    status = silva("status", out).output
    assert "removed" not in status and "scene train: 1 chunk" in status
