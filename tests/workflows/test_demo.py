"""``silva demo``: synthetic plots, the whole workflow, a report, on a real LocalCluster."""

import json

import pytest
from click.testing import CliRunner

from workflows.cli import main

pytestmark = pytest.mark.slow


def test_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    result = CliRunner().invoke(
        main, ["demo", "--out", str(out), "--plot-size", "12", "--quiet",
               "--set", "cascade.n_estimators=8", "--set", "cluster.n_workers=2"],
        catch_exceptions=False)
    assert result.exit_code == 0, result.output
    assert f"report: {out / 'report.html'}" in result.output
    report = (out / "report.html").read_text()
    assert "chunk size (m)" in report and "train 15" in report  # configs/demo.yaml
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["macro"]["f1"] > 0.5
    assert sorted(p.name for p in (out / "data" / "train").glob("*.laz"))
    assert len(list((out / "predictions").glob("*.laz"))) == len(
        list((out / "data").glob("*/*.laz")))
    # a second demo resumes: nothing to redo, the same metrics
    again = CliRunner().invoke(
        main, ["demo", "--out", str(out), "--plot-size", "12", "--quiet",
               "--set", "cascade.n_estimators=8", "--set", "cluster.n_workers=2"])
    assert again.exit_code == 0, again.output
    assert json.loads((out / "metrics.json").read_text()) == metrics
