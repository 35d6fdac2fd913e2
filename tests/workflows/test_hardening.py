"""What a careful user can do wrong, or the system can do to a run, gives one clear line and
exit code 1 (or a correct result), never silently wrong data, a hang or a traceback."""

import errno
import http.server
import json
import os
import socket
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import ConfigError, InputError
from workflows.cli.status import run_status
from workflows.config import load_config
from workflows.exec.probe import check_scheduler
from workflows.run.autoparams import resolve_run
from workflows.run.directory import OutputError, Run, prepare_output, read_paths
from workflows.run.lock import LOCK_NAME, LockedError, acquire, read_lock
from workflows.steps.export import remove_stale
from pipeline.io.catalogue import tile_name
from workflows.steps.ingest import plan_tiles
from workflows.steps.table import STEPS
from tests.workflows.conftest import error_line, silva, write_config


@pytest.fixture
def sleeper():
    """A live process of this host that is not this one."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc
    proc.kill()
    proc.wait()


def _fake_lock(out: Path, pid: int, host: str | None = None):
    out.mkdir(parents=True, exist_ok=True)
    (out / LOCK_NAME).write_text(json.dumps({
        "pid": pid, "host": host or socket.gethostname(), "started": time.time(),
        "command": "silva run first.yaml", "token": "x"}))


# -- 2: the same tile in train and test --------------------------------------------------
def test_same_tile_in_train_and_test_is_refused(tmp_path, survey):
    one = sorted(survey["train"].glob("*.laz"))[0]
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "out", "--in-process", "-q",
                   "--set", f"data.test=[{survey['test']}/*.laz, {one}]")
    line = error_line(result)
    assert one.name in line and "data.train" in line and "data.allow_overlap" in line
    assert not (tmp_path / "out" / "store.zarr").exists()


def test_overlap_through_another_name_is_refused(tmp_path, survey):
    link = tmp_path / "elsewhere"
    link.symlink_to(survey["train"])
    cfg = load_config(write_config(tmp_path / "c.yaml", survey),
                      [f"data.test=[{link}/*.laz]"])
    with pytest.raises(ConfigError, match="both in data.test and in data.train"):
        plan_tiles(Run(resolve_run(cfg), tmp_path / "out", steps=STEPS))


def test_allowed_overlap_keeps_one_output_per_scene(tmp_path, survey):
    cfg = load_config(write_config(tmp_path / "c.yaml", survey),
                      [f"data.test=[{survey['train']}/*.laz]", "data.allow_overlap=true"])
    tiles = plan_tiles(Run(resolve_run(cfg), tmp_path / "out", steps=STEPS))
    names = [t.name for t in tiles]
    assert len(set(names)) == len(names) == 2 * len(list(survey["train"].glob("*.laz")))
    assert all(n.endswith("-test") for t, n in zip(tiles, names) if t.scene == "test")


# -- 11: tile names ----------------------------------------------------------------------
@pytest.mark.parametrize("file, name", [("plot.v1.laz", "plot.v1"), ("plot.v2.laz", "plot.v2"),
                                        (".hidden.laz", "hidden"), ("a.copc.laz", "a.copc")])
def test_tile_names_keep_everything_but_the_suffix(file, name):
    assert tile_name(Path("/d") / file) == name


def test_tile_without_a_name_is_refused():
    with pytest.raises(InputError, match="no name"):
        tile_name(Path("/d/..laz"))


# -- 3: --overwrite never deletes what the command reads ---------------------------------
def test_overwrite_keeps_the_model_config_and_inputs_inside_out(tmp_path):
    out = tmp_path / "out"
    for name in ("store.zarr/x", "model/model.json", "model/stage1.skops", "work/f",
                 "predictions/a.laz", "data/train/t.laz", "data/train/u.laz", "run.yaml"):
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_text("x")
    keep = [out / "model", out / "run.yaml", out / "data" / "train" / "t.laz"]
    with prepare_output(out, overwrite=True, keep=keep):
        left = sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file())
    assert left == ["data/train/t.laz", "model/model.json", "model/stage1.skops", "run.yaml",
                    LOCK_NAME]
    assert not (out / LOCK_NAME).exists()  # released


def test_read_paths_are_the_config_the_model_and_every_input(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    cfg = load_config(config, [])
    paths = read_paths(cfg, config, tmp_path / "model")
    assert paths[:2] == [config, tmp_path / "model"]
    assert set(paths[2:]) == set(survey["train"].glob("*.laz")) | set(survey["test"].glob("*.laz"))


# -- 5: one command per output directory -------------------------------------------------
def test_second_run_refuses_at_once_naming_the_first(tmp_path, survey, sleeper):
    out = tmp_path / "out"
    _fake_lock(out, sleeper.pid)
    config = write_config(tmp_path / "c.yaml", survey)
    started = time.monotonic()
    result = silva("run", config, "--out", out, "--in-process", "-q", "--overwrite")
    line = error_line(result)
    assert time.monotonic() - started < 10
    assert f"pid {sleeper.pid}" in line and "silva run first.yaml" in line
    assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing touched
    assert run_status(out)[0].startswith("running now: 'silva run first.yaml'")


def test_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    _fake_lock(tmp_path, proc.pid)
    with acquire(tmp_path, "silva run again.yaml"):
        assert read_lock(tmp_path)["pid"] == os.getpid()
    assert not (tmp_path / LOCK_NAME).exists()


def test_lock_of_another_host_is_refused_with_how_to_remove_it(tmp_path):
    _fake_lock(tmp_path, 1, host="some-other-node")
    with pytest.raises(LockedError, match=rf"some-other-node.*delete {tmp_path / LOCK_NAME}"):
        acquire(tmp_path, "silva run")


def test_ingest_checks_the_points_read_against_the_header(tmp_path, survey):
    from workflows.steps.ingest import IngestTask, ingest_tile

    cfg = load_config(write_config(tmp_path / "c.yaml", survey), [])
    run = Run(resolve_run(cfg), tmp_path / "out", steps=STEPS)
    tile = plan_tiles(run)[0]
    tile = replace(tile, n_points=tile.n_points + 5)
    from workflows.steps.ingest import plan_scenes

    grid = plan_scenes(run, [tile])[tile.scene].grid
    run.store  # creates it
    with pytest.raises(InputError, match=rf"announces {tile.n_points} points but "
                                         rf"{tile.n_points - 5} were read"):
        ingest_tile(IngestTask(str(run.store_path), tile.scene, tile, grid, run.halo,
                               "classification", run.code_to_class, None, 100_000, "fp"))


# -- 4: an address that is not a Dask scheduler ------------------------------------------
@pytest.fixture
def web_server():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             http.server.SimpleHTTPRequestHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"tcp://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_web_server_is_not_a_scheduler(web_server):
    started = time.monotonic()
    with pytest.raises(ConfigError, match="is not a Dask scheduler: it sent no Dask handshake"):
        check_scheduler(web_server, timeout=1.0)
    assert time.monotonic() - started < 3


def test_a_server_that_talks_first_but_not_dask(tmp_path):
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def banner():
        conn, _ = listener.accept()
        conn.sendall(b"SSH-2.0-OpenSSH_9.6\r\n")
        time.sleep(1)
        conn.close()

    threading.Thread(target=banner, daemon=True).start()
    with pytest.raises(ConfigError, match="not a Dask handshake"):
        check_scheduler(f"tcp://127.0.0.1:{port}", timeout=5.0)
    listener.close()


def test_nothing_listening_is_a_clear_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConfigError, match="cannot connect.*Connection refused"):
        check_scheduler(f"tcp://127.0.0.1:{port}", timeout=2.0)


@pytest.mark.slow
def test_run_against_a_web_server_stops_within_its_deadline(tmp_path, survey, web_server):
    config = write_config(tmp_path / "c.yaml", survey,
                          cluster={"kind": "address", "address": web_server})
    started = time.monotonic()
    result = silva("run", config, "--out", tmp_path / "out", "-q")
    assert "cluster.address" in error_line(result)
    assert time.monotonic() - started < 30


# -- 7: a run owns its outputs -----------------------------------------------------------
def test_stale_predictions_are_removed(tmp_path):
    for name in ("a.laz", "b.laz", "a.las", "notes.txt"):
        (tmp_path / name).write_text("x")
    removed = remove_stale(tmp_path, [str(tmp_path / "a.laz")])
    assert sorted(p.name for p in removed) == ["a.las", "b.laz"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.laz", "notes.txt"]


# -- 8: operating-system errors ----------------------------------------------------------
def test_out_below_a_regular_file(tmp_path, survey):
    (tmp_path / "file").write_text("x")
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("run", config, "--out", tmp_path / "file" / "out", "--in-process", "-q")
    assert "which is a file, not a directory" in error_line(result)


def test_out_that_cannot_be_created(tmp_path, monkeypatch):
    def refuse(self, *args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(self))

    monkeypatch.setattr(Path, "mkdir", refuse)
    with pytest.raises(OutputError, match="Permission denied.*choose another --out"):
        prepare_output(tmp_path / "new", overwrite=False)


def test_os_error_in_a_step_is_one_line(tmp_path, monkeypatch):
    import workflows.cli.commands

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "report.html"))

    monkeypatch.setattr(workflows.cli.commands, "start_run", full)
    result = silva("run", tmp_path / "c.yaml")
    line = error_line(result)
    assert "No space left on device" in line and "report.html" in line
    assert "run the same command again" in line


# -- 6: workers that cannot run ----------------------------------------------------------
# (the restart count and its diagnosis: tests/workflows/test_watch.py)


def test_memory_limit_too_small_for_a_worker_stops_the_run(tmp_path, survey):
    """Refused before the cluster starts (a limit that workers reach while they run:
    tests/workflows/test_watch.py)."""
    config = write_config(tmp_path / "c.yaml", survey)
    started = time.monotonic()
    result = silva("run", config, "--out", tmp_path / "out", "-q",
                   "--set", "cluster.memory_limit=120MiB")
    assert "cluster.memory_limit (120.00 MiB per worker) is too small" in error_line(result)
    assert time.monotonic() - started < 15
    assert not (tmp_path / "out" / "metrics.json").exists()


@pytest.mark.slow
def test_workers_over_their_memory_limit_stop_the_run_with_the_fix(tmp_path, survey):
    """A limit the workers reach while they run (the check before the start only foresees
    the largest chunk from the headers): the run stops and names the limit."""
    from distributed import Client, LocalCluster

    from workflows.config import load_config
    from workflows.exec.engine import Engine
    from workflows.exec.watch import NoWorkerCanRun
    from workflows.run.directory import Run
    from workflows.run.loop import execute

    config = write_config(tmp_path / "c.yaml", survey)
    started = time.monotonic()
    with LocalCluster(n_workers=1, threads_per_worker=1, memory_limit="120MiB",
                      host="127.0.0.1", dashboard_address=None, processes=True) as cluster, \
            Client(cluster) as client:
        run = Run(resolve_run(load_config(config)), tmp_path / "out", quiet=True, steps=STEPS)
        run.save_config()
        with pytest.raises(NoWorkerCanRun, match=r"cluster\.memory_limit \(120\.00 MiB per "
                                                 r"worker\) is too small"):
            execute(run, Engine(client, quiet=True), "report")
    assert time.monotonic() - started < 120
    assert not (tmp_path / "out" / "metrics.json").exists()


# -- 11: smaller things ------------------------------------------------------------------
def test_broken_symlink_in_a_glob_is_named(tmp_path, survey):
    from pipeline.errors import MissingFileError
    from workflows.config.inputs import expand_inputs

    shutil_dir = tmp_path / "tiles"
    shutil_dir.mkdir()
    (shutil_dir / "good.laz").symlink_to(sorted(survey["test"].glob("*.laz"))[0])
    (shutil_dir / "gone.laz").symlink_to(tmp_path / "nowhere.laz")
    with pytest.raises(MissingFileError, match=r"gone.laz' \(matched by .*data.test\) is a "
                                               r"broken symbolic link"):
        expand_inputs([f"{shutil_dir}/*.laz"], key="data.test")
    with pytest.raises(MissingFileError, match="broken symbolic link"):
        expand_inputs([shutil_dir / "gone.laz"])


def test_chunk_that_does_not_exist_is_an_error(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey)
    result = silva("features", config, "--out", tmp_path / "out", "-q", "--chunk", "test/9_9")
    line = error_line(result)
    assert "--chunk test/9_9: no such chunk" in line and "test/0_0" in line


def test_parts_a_killed_writer_left_are_cleared(tmp_path):
    out = tmp_path / "out"
    (out / "model").mkdir(parents=True)
    (out / "store.zarr").mkdir()
    part = out / "model" / ".stage1.skops.0123456789ab.part"
    part.write_bytes(b"half")
    with prepare_output(out, overwrite=False):
        assert not part.exists()


def test_a_real_scheduler_passes_the_check_and_connects():
    from distributed import LocalCluster

    from workflows.config import validate_config
    from workflows.exec.cluster import open_client

    with LocalCluster(n_workers=1, processes=False, protocol="tcp", host="127.0.0.1",
                      dashboard_address=None) as cluster:
        check_scheduler(cluster.scheduler_address, timeout=5.0)
        cfg = validate_config({"cluster": {"kind": "address",
                                           "address": cluster.scheduler_address}}).cluster
        with open_client(cfg) as client:
            assert client.submit(sum, [1, 2]).result() == 3


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A complete run on two tiny plots: its config and output directory."""
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("finished")
    for role, seed in (("train", 1), ("test", 2)):
        write_synthetic_plot(root / role, seed=seed, size=8.0, tile_size=8.0)
    config = write_config(root / "c.yaml", {"train": root / "train", "test": root / "test"},
                          cascade={"n_estimators": 4, "max_train_points": 3000})
    out = root / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return config, out


def test_report_shows_the_models_importances_and_the_points_without_features(finished_run):
    from workflows.report import format_score
    from tests.workflows.conftest import read_predictions

    _, out = finished_run
    page = (out / "report.html").read_text(encoding="utf-8")
    stages = json.loads((out / "model" / "model.json").read_text())["stages"]
    assert len(stages) == 2
    for number, stage in enumerate(stages):
        top = sorted(stage["importances"].items(), key=lambda kv: (-kv[1], kv[0]))[0]
        first = page[page.index('<table class="importances">'):].split("</tr>")[1]
        cells = first.split("</td><td>")
        assert cells[1 + 2 * number].removeprefix("<td>") == top[0], first
    flagged = sum(int(dims["NoFeatures"].sum()) for dims in read_predictions(out).values())
    total = sum(len(dims["xyz"]) for dims in read_predictions(out).values())
    # metrics.json counts those of the scored test points: the test plot's labelled points
    codes = [1, 2, 5, 64]  # write_config's classes
    scored = sum(int((dims["NoFeatures"].astype(bool)
                      & np.isin(dims["classification"], codes)).sum())
                 for name, dims in read_predictions(out).items()
                 if name.startswith("plot_s2"))  # the test plot, seed 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["points_without_features"] == scored
    if flagged:
        assert f"{flagged:,} of the {total:,} points written" in page
    else:
        assert f"Every one of the {total:,} points written has its features." in page
    assert format_score(stages[1]["importances"][top[0]]) in page


def test_rerun_that_changes_nothing_keeps_metrics_and_report(finished_run):
    from pipeline.store import open_store

    config, out = finished_run
    results = [out / "metrics.json", out / "report.html"]
    before = [p.read_bytes() for p in results]
    chunk = open_store(out / "store.zarr").attrs["layout"]["scenes"]["test"]["chunks"][0]
    for args in (("ingest",), ("features", "--chunk", f"test/{chunk}"),
                 ("export", "--set", "cluster.n_workers=2")):  # no result depends on it
        result = silva(*args[:1], config, "--out", out, "--in-process", "-q", *args[1:])
        assert result.exit_code == 0, result.output
        assert [p.read_bytes() for p in results] == before, args
    # a change the results follow from removes them before any step writes
    result = silva("ingest", config, "--out", out, "--in-process", "-q",
                   "--set", "output.probabilities=false")
    assert result.exit_code == 0, result.output
    assert not any(p.exists() for p in results)


def test_corrupt_root_store_metadata_is_one_line(tmp_path, survey):
    from pipeline.store import open_store

    out = tmp_path / "out"
    open_store(out / "store.zarr")
    (out / "store.zarr" / "zarr.json").write_text("{not json")
    config = write_config(tmp_path / "c.yaml", survey)
    for args in (("status", out), ("ingest", config, "--out", out, "-q", "--in-process")):
        line = error_line(silva(*args))
        assert f"store {out / 'store.zarr'} is damaged" in line and "--overwrite" in line


def test_a_store_of_the_schema_before_terrain_blocks_is_refused_then_redone(tmp_path, survey):
    """A store written before the terrain blocks (schema 6: one terrain raster per scene, cell
    minima without positions, tiles' boxes from their headers) is never read as if it had
    them: one line asks for --overwrite, which makes it again."""
    from pipeline.store import SCHEMA_VERSION, open_store

    out = tmp_path / "out"
    open_store(out / "store.zarr").attrs["schema_version"] = 6
    assert SCHEMA_VERSION > 6
    config = write_config(tmp_path / "c.yaml", survey)
    for args in (("status", out), ("ingest", config, "--out", out, "-q", "--in-process")):
        line = error_line(silva(*args))
        assert "schema version 6" in line and "--overwrite" in line, line
    result = silva("ingest", config, "--out", out, "-q", "--in-process", "--overwrite")
    assert result.exit_code == 0, result.output
    assert open_store(out / "store.zarr").attrs["schema_version"] == SCHEMA_VERSION


def test_a_done_mark_without_its_summary_runs_the_step_again(tmp_path, survey):
    """A chunk marked done whose stored summary is missing: the step runs again for it (the
    same outputs) instead of handing the coordinator nothing."""
    from pipeline.store import open_store
    from workflows.store.layout import chunk_path

    config = write_config(tmp_path / "c.yaml", survey,
                          cascade={"n_estimators": 4, "max_train_points": 3000})
    out = tmp_path / "out"
    assert silva("run", config, "--out", out, "--in-process", "-q").exit_code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    root = open_store(out / "store.zarr")
    chunk = root.attrs["layout"]["scenes"]["train"]["chunks"][0]
    group = root[chunk_path("train", chunk)]
    assert "features" in group.attrs["done"]
    group.update_attributes({"results": {k: v for k, v in group.attrs["results"].items()
                                         if k != "features"}})
    result = silva("run", config, "--out", out, "--in-process", "-q")
    assert result.exit_code == 0, result.output
    assert "features" in root[chunk_path("train", chunk)].attrs["results"]
    assert json.loads((out / "metrics.json").read_text()) == metrics
