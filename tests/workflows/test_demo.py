"""``silva demo``: synthetic plots, the whole workflow, a report, on a real LocalCluster (the
session's 2 workers)."""

import json

import pytest
from click.testing import CliRunner

from pipeline.io import read_info
from pipeline.synth import synthetic_plot
from workflows.cli.main import main

pytestmark = pytest.mark.slow


def test_demo_runs_end_to_end(tmp_path, dask_cluster):
    out = tmp_path / "demo"
    args = ["demo", "--out", str(out), "--plot-size", "12", "--quiet",
            "--set", "cascade.n_estimators=8",
            *(f"--set=cluster.{key}={value}" for key, value in dask_cluster.items())]
    result = CliRunner().invoke(main, args, catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert f"report: {out / 'report.html'}" in result.output
    report = (out / "report.html").read_text()
    assert "chunk size (m)" in report and "train 15" in report  # configs/demo.yaml
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["macro"]["f1"] > 0.5
    # --plot-size 12: each plot is 2 x 2 tiles of 6 m, the training plot seed 1, the test plot 2
    tiles = {role: [f"plot_s{seed}_{ix}_{iy}.laz" for ix in (0, 1) for iy in (0, 1)]
             for role, seed in (("train", 1), ("test", 2))}
    for role, names in tiles.items():
        assert sorted(p.name for p in (out / "data" / role).glob("*.laz")) == names
    assert sum(read_info(out / "data" / "train" / name).n_points for name in tiles["train"]) \
        == len(synthetic_plot(1, 12.0)[0])
    assert sorted(p.name for p in (out / "predictions").glob("*.laz")) == sorted(
        tiles["train"] + tiles["test"])
    # a second demo resumes: nothing to redo, the same metrics
    again = CliRunner().invoke(main, args)
    assert again.exit_code == 0, again.output
    assert json.loads((out / "metrics.json").read_text()) == metrics
