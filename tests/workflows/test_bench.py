"""``silva bench``: both commands on tiny inputs give every figure, positive and finite; bad
input is one line and exit code 1. No test looks at how fast anything was."""

import importlib.util
import json
import math

import numpy as np
import pytest

from workflows.cli import bench as bench_module
from tests.workflows.conftest import error_line, silva, write_config

FEATURE_KEYS = ("points", "silva_points_per_s", "baseline_name", "baseline_points_per_s",
                "knn_points_per_s", "time_ratio")
PIPELINE_KEYS = ("points", "workers", "points_per_s", "points_per_s_one_worker", "speedup",
                 "chunk_overhead", "peak_rss_per_worker_mib", "points_per_worker_cpu_s")
HAS_PEER = any(importlib.util.find_spec(name) for name in bench_module.PEERS)


def _last_json(result) -> dict:
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout.strip().splitlines()[-1])


def _positive(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


@pytest.fixture(scope="module")
def tiny(tiny_survey) -> dict:
    """A 6 m training and test plot (a few thousand points each), as 3 m tiles."""
    return tiny_survey


@pytest.fixture(scope="module")
def tile(tiny):
    return sorted(tiny["test"].glob("*.laz"))[0]


# -- features ----------------------------------------------------------------------------------
@pytest.mark.skipif(not HAS_PEER, reason="no peer library: pip install -e '.[bench]'")
def test_bench_features_gives_every_figure(tile):
    result = silva("bench", "features", tile, "--points", 1500, "--repeat", 1,
                   "--reference-points", 30, "--json")
    figures = _last_json(result)
    assert set(FEATURE_KEYS) <= figures.keys()
    assert figures["points"] == 1500 and figures["baseline_name"] in bench_module.PEERS
    for key in FEATURE_KEYS:
        if key != "baseline_name":
            assert _positive(figures[key]), (key, figures[key])
    assert "time ratio Silva / " in result.stdout and "neighbour search" in result.stdout


def test_bench_features_without_a_peer_says_how_to_install_one(tile, monkeypatch):
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name in bench_module.PEERS else find_spec(name, *a))
    result = silva("bench", "features", tile, "--points", 500, "--repeat", 1,
                   "--reference-points", 0, "--json")
    figures = _last_json(result)
    assert figures["baseline_name"] is None and _positive(figures["silva_points_per_s"])
    assert [line for line in result.stdout.splitlines() if "bench extra" in line] == [
        bench_module.INSTALL_PEERS]


def test_bench_features_threads_give_the_same_invariants(tile):
    xyz = bench_module.load_cloud(tile, 2000)
    query = np.arange(len(xyz), dtype=np.int64)
    one = bench_module.silva_invariants(xyz, 0.5, 64, 1)
    two = bench_module.silva_invariants(xyz, 0.5, 64, 2, bench_module._blocks(query, 2))
    assert np.array_equal(one, two, equal_nan=True)


def test_pgeof_rows_are_silva_rows_in_point_order():
    query = np.array([2, 0, 1])
    nbr_idx = np.array([2, 1, 0, 1, 2, 0, 1])
    nbr_ptr = np.array([0, 2, 5, 7])  # rows of points 2, 0, 1
    idx, ptr = bench_module._pgeof_inputs(3, query, nbr_idx, nbr_ptr)
    assert ptr.tolist() == [0, 3, 5, 7]
    assert idx.tolist() == [0, 1, 2, 0, 1, 2, 1]


def test_bench_features_of_a_missing_file_is_one_line(tmp_path):
    line = error_line(silva("bench", "features", tmp_path / "nope.laz"))
    assert "nope.laz not found" in line


# -- pipeline ----------------------------------------------------------------------------------
def test_bench_pipeline_gives_every_figure(tiny, tmp_path, monkeypatch):
    config = write_config(tmp_path / "tiny.yaml", tiny, tiling={"chunk_size": 4.0},
                          cascade={"stages": 1, "n_estimators": 4, "max_train_points": 2000})
    workers_of_runs, one_run = [], bench_module.one_run

    def recording(config, overrides, out, model, client):
        workers_of_runs.append(frozenset(bench_module._worker_pids(client)))
        return one_run(config, overrides, out, model, client)

    monkeypatch.setattr(bench_module, "one_run", recording)
    result = silva("bench", "pipeline", config, "--workers", 1, "--repeat", 2, "--json", "-q")
    figures = _last_json(result)
    # every run on fresh workers, as a user's command: none pays or skips another's first run
    assert len(workers_of_runs) == 4 and len(set(workers_of_runs)) == 4
    assert set(PIPELINE_KEYS) <= figures.keys()
    assert figures["workers"] == 1 and figures["speedup"] == 1.0
    # two rounds, each ratio within its round, the figures their medians
    assert figures["rounds"] == 2
    assert all(len(v) == 2 for v in figures["seconds_per_round"].values())
    assert figures["chunk_overhead"] == pytest.approx(
        np.median(figures["chunk_overhead_per_round"]), abs=2e-3)
    assert figures["seconds_one_chunk"] == pytest.approx(
        np.median(figures["seconds_per_round"]["1 worker, one chunk per scene"]), abs=0.01)
    assert figures["chunks"] > 1 and figures["chunks_one_chunk_run"] == 2  # train, test
    for key in PIPELINE_KEYS:
        assert _positive(figures[key]) or key == "chunk_overhead", (key, figures[key])
    assert math.isfinite(figures["chunk_overhead"]) and figures["chunk_overhead"] > -1
    assert "chunk overhead" in result.stdout


def test_bench_pipeline_of_a_missing_config_or_model_is_one_line(tiny, tmp_path):
    assert "not found" in error_line(silva("bench", "pipeline", tmp_path / "none.yaml"))
    config = write_config(tmp_path / "tiny.yaml", tiny)
    line = error_line(silva("bench", "pipeline", config, "--model", tmp_path / "no-model"))
    assert "no-model not found" in line



def test_the_machines_scaling_is_what_its_workers_do_side_by_side(capsys, dask_cluster):
    from distributed import Client

    from pipeline.features.sets import FeatureParams

    assert bench_module.scaling(2.0, [2.0, 2.0]) == 2.0  # no slower side by side
    assert bench_module.scaling(2.0, [2.5, 4.0]) == 1.0  # the slower one decides
    with Client(dask_cluster["address"]) as client:  # the session's 2 workers
        allowed = bench_module.machine_scaling(client, FeatureParams(set="paper", r1=0.5),
                                               n_points=3000)
    assert _positive(allowed)
    # the figures of a 2-worker bench: the run's speed-up against what the machine allowed
    run = {"points": 10, "chunks": 2, "chunk size (m)": "test 3", "timings": {"apply": 1.0},
           "cpu_seconds": 1.0}
    rounds = [{"1 worker": {**run, "seconds": 10.0},
               "1 worker, one chunk per scene": {**run, "seconds": 9.0, "chunks": 1},
               "2 workers": {**run, "seconds": seconds, "machine_scaling": allowed}}
              for seconds, allowed in ((6.25, 1.6), (5.0, 1.8), (5.0, 2.0))]
    figures = bench_module._pipeline_figures("c.yaml", None, 2, rounds, [100.0])
    assert figures["speedup_per_round"] == [1.6, 2.0, 2.0]
    assert figures["machine_scaling"] == 1.8
    assert figures["speedup_of_machine_scaling"] == 1.0  # the median of 1.0, 1.11, 1.0
    assert "the machine allowed 1.80x on 2 workers" in capsys.readouterr().out


def test_the_one_chunk_run_plans_one_chunk_whatever_the_workers(tiny, tmp_path):
    """A balanced scene is shared out among the workers its configuration plans for: the
    one-chunk run plans for one, or a 2-worker configuration cut its 2 chunks again."""
    from workflows.config import load_config
    from workflows.run.autoparams import resolve_run
    from workflows.run.directory import Run
    from workflows.steps.ingest import scene_target

    config = write_config(tmp_path / "c.yaml", tiny, cluster={"n_workers": 4})
    run = Run(resolve_run(load_config(config, bench_module.ONE_CHUNK)), tmp_path / "out",
              quiet=True)
    assert scene_target(run, 1_000_000) == 1_000_000


def test_a_primed_worker_holds_the_models_forests():
    """The bench loads a saved model's forests on its workers before timing anything: the
    first timed run finds them loaded."""
    from pathlib import Path

    import workflows
    from pipeline.model import read_model_file
    from workflows.steps import cascade

    model = Path(workflows.__file__).parent / "models" / "forest-tls-synthetic"
    paths = [str(model / stage["file"]) for stage in read_model_file(model)[0]["stages"]]
    cascade._loaded_forest.cache_clear()
    bench_module.prime_worker((), paths)
    assert cascade._loaded_forest.cache_info().currsize == len(paths) == 2
    cascade.cached_forest(paths[0])
    assert cascade._loaded_forest.cache_info().hits == 1
