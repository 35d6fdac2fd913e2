"""``silva sweep``: one run per value x seed, features shared when the key leaves them alone,
and the CSV, Markdown table and plots computed from the runs' own metrics."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from workflows.cli.sweep import parse_values, plan_sweep
from tests.workflows.conftest import error_line, silva, write_config

PNG = b"\x89PNG\r\n\x1a\n"


def mtimes(root: Path, folder: str) -> list[int]:
    """mtime_ns of every file of every array folder named ``folder`` below ``root``."""
    found = [p for d in root.rglob(folder) if d.is_dir() for p in d.rglob("*") if p.is_file()]
    assert found, f"no {folder} arrays below {root}"
    return [p.stat().st_mtime_ns for p in found]


@pytest.fixture(scope="module")
def swept(survey, tmp_path_factory):
    """cascade.n_estimators = 3, 6 with seeds 0 and 1, in this process."""
    root = tmp_path_factory.mktemp("sweep")
    config = write_config(root / "c.yaml", survey)
    out = root / "out"
    result = silva("sweep", config, "--param", "cascade.n_estimators", "--values", "3,6",
                   "--seeds", 2, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return out, result.output


def test_one_csv_row_per_value_seed_and_stage_from_each_runs_metrics(swept):
    out, _ = swept
    with open(out / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    keys = [(r["value"], int(r["seed"]), int(r["stage"])) for r in rows]
    assert sorted(keys) == [(v, s, t) for v in ("3", "6") for s in (0, 1) for t in (1, 2)]
    assert {"macro_precision", "macro_recall", "macro_f1", "f1_terrain", "f1_tree",
            "f1_dead_wood"} <= set(rows[0])
    for row in rows:
        kept = out / f"cascade.n_estimators={row['value']}" / f"seed{row['seed']}"
        metrics = json.loads((kept / "metrics.json").read_text())
        stage = metrics["stages"][int(row["stage"]) - 1]
        assert float(row["macro_f1"]) == stage["macro"]["f1"]
        assert float(row["macro_recall"]) == stage["macro"]["recall"]
        assert float(row["f1_tree"]) == stage["per_class"]["tree"]["f1"]
        cascade = yaml.safe_load((kept / "config.yaml").read_text())["cascade"]
        assert (cascade["n_estimators"], cascade["seed"]) == (int(row["value"]),
                                                              int(row["seed"]))
    finals = {r["macro_f1"] for r in rows if r["stage"] == "2"}
    assert len(finals) > 1  # four different models, not one result copied four times


def test_markdown_table_holds_mean_and_std_over_seeds(swept):
    out, _ = swept
    with open(out / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    lines = (out / "sweep.md").read_text().splitlines()
    header = next(line for line in lines if line.startswith("| cascade.n_estimators"))
    assert header == ("| cascade.n_estimators | runs | precision | recall | F1 | F1 stage 1 "
                      "| F1 stage 2 |")
    table = [line for line in lines if line.startswith("| 3 ") or line.startswith("| 6 ")]
    assert len(table) == 2
    for line in table:
        cells = [c.strip() for c in line.strip("|").split("|")]
        value = cells[0]
        assert cells[1] == "2"

        def cell(column, stage):
            x = [float(r[column]) for r in rows if r["value"] == value
                 and r["stage"] == str(stage)]
            return f"{np.mean(x):.3f} ± {np.std(x, ddof=1):.3f}"

        assert cells[2:5] == [cell(f"macro_{m}", 2) for m in ("precision", "recall", "f1")]
        assert cells[5:7] == [cell("macro_f1", 1), cell("macro_f1", 2)]


def test_plots_are_written(swept):
    out, output = swept
    for name in ("sweep_scores.png", "sweep_stages.png"):
        data = (out / name).read_bytes()
        assert data.startswith(PNG) and len(data) > 10_000
        assert f"{name}: {out / name}" in output


def test_features_are_computed_once_and_the_cascade_for_every_run(swept):
    out, output = swept
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == [
        "cascade.n_estimators=3", "cascade.n_estimators=6", "run"]
    first = (out / "cascade.n_estimators=3" / "seed0" / "metrics.json").stat().st_mtime_ns
    last = (out / "cascade.n_estimators=6" / "seed1" / "metrics.json").stat().st_mtime_ns
    store = out / "run" / "store.zarr"
    assert max(mtimes(store, "features")) < first  # written by the first run only
    assert min(mtimes(store, "stage*_proba")) > first  # the last run refitted every stage
    assert max(mtimes(store, "stage*_proba")) < last
    assert output.count("macro F1") == 4


def test_only_a_key_that_changes_the_features_gets_a_run_directory_per_value(survey,
                                                                             tmp_path):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    for key, values, overrides in (
            ("cascade.context", "hard,soft", ()), ("features.r2", "0.1,0.2", ()),
            ("features.context_max_neighbors", "null,16", ()),
            # the default halo reaches across the stages: only a set halo keeps the ingest
            ("cascade.stages", "1,3", ("tiling.halo=2.0",))):
        plan = plan_sweep(config, key, values, 2, out, overrides)
        assert {r.work for r in plan} == {out / "run"}
        assert [r.seed for r in plan] == [0, 1, 0, 1]
        assert all(r.cfg.output.keep_features for r in plan)  # shared by the runs
    plan = plan_sweep(config, "cascade.stages", "1,3", 1, out)
    assert [r.work for r in plan] == [out / "cascade.stages=1" / "run",
                                      out / "cascade.stages=3" / "run"]
    plan = plan_sweep(config, "features.r1", "0.4,0.5", 2, out)
    assert [r.work for r in plan] == [out / "features.r1=0.4" / "run"] * 2 + [
        out / "features.r1=0.5" / "run"] * 2
    assert [r.result.name for r in plan] == ["seed0", "seed1"] * 2
    # the forest template's 'auto' values are resolved from the tiles before the plan
    plan = plan_sweep(config, "cascade.n_estimators", "3,6", 1, out,
                      ("features.set=default", "features.r1=auto", "features.echoes=auto"))
    assert {r.work for r in plan} == {out / "run"}
    plan = plan_sweep(config, "cascade.seed", "5,7", 1, out)
    assert [(r.seed, r.result.name) for r in plan] == [(5, "seed5"), (7, "seed7")]
    assert not out.exists()  # planning does no work


def test_values_are_yaml_scalars():
    assert parse_values(" 0.5, true ,paper,3,null") == [
        ("0.5", 0.5), ("true", True), ("paper", "paper"), ("3", 3), ("null", None)]


@pytest.mark.parametrize("args, expected", [
    (["--param", "cascade.trees", "--values", "3,6"], "unknown key 'cascade.trees'"),
    (["--param", "cascade.n_estimators", "--values", "3,many"], "cascade.n_estimators"),
    (["--param", "cascade.n_estimators", "--values", "3,3"], "lists 3 twice"),
    (["--param", "cascade.n_estimators", "--values", "3,"], "empty value"),
    (["--param", "cascade.n_estimators", "--values", "3", "--set", "data.test=[]"],
     "no labelled test points"),
    (["--param", "cluster.n_workers", "--values", "1,2"], "cluster keys"),
    (["--param", "cascade.seed", "--values", "1,2", "--seeds", "3"], "drop --seeds"),
    (["--param", "cascade.n_estimators", "--values", "3", "--seeds", "0"], "--seeds"),
])
def test_bad_input_is_one_line_before_any_work(survey, tmp_path, args, expected):
    config = write_config(tmp_path / "c.yaml", survey)
    out = tmp_path / "out"
    result = silva("sweep", config, *args, "--out", out, "--in-process", "-q")
    assert expected in error_line(result)
    assert not out.exists()
