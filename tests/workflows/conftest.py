"""Fixtures for workflow tests: small synthetic surveys and configs that run in seconds."""

import signal
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pytest
import yaml

from pipeline.io.catalogue import Tile
from pipeline.store import open_store, read_array

SMALL_PLOT = 14.0  # metres: a few tens of thousands of points
SMALL_TILE = 7.0


@pytest.fixture(scope="session")
def survey(tmp_path_factory) -> dict[str, Path]:
    """A training and a test plot, each as several LAZ tiles."""
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("survey")
    for role, seed in (("train", 1), ("test", 2)):
        write_synthetic_plot(root / role, seed=seed, size=SMALL_PLOT, tile_size=SMALL_TILE)
    return {"train": root / "train", "test": root / "test"}


@pytest.fixture(scope="session")
def tiny_survey(tmp_path_factory) -> dict[str, Path]:
    """A 6 m training and test plot (a few thousand points each), as 3 m tiles: for tests
    of what a run shows or how it goes, not of what it finds."""
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("tiny")
    for role, seed in (("train", 1), ("test", 2)):
        write_synthetic_plot(root / role, seed=seed, size=6.0, tile_size=3.0)
    return {"train": root / "train", "test": root / "test"}


@pytest.fixture(scope="session")
def survey_run(survey, tmp_path_factory):
    """A complete run of ``survey`` with the defaults of :func:`write_config`, in this
    process: its config and output directory (read it; copy it before changing it)."""
    root = tmp_path_factory.mktemp("survey_run")
    config = write_config(root / "c.yaml", survey)
    result = silva("run", config, "--out", root / "out", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    return config, root / "out"


@pytest.fixture(scope="session")
def one_stage(survey, tmp_path_factory):
    """A complete run of ``survey`` whose model has one stage, in this process, and a config
    of the same survey that says two: (that config, the run's output directory; read it,
    copy it before changing it)."""
    root = tmp_path_factory.mktemp("one_stage")
    config = write_config(root / "c.yaml", survey, cascade={"stages": 1})
    result = silva("run", config, "--out", root / "out", "--in-process", "-q")
    assert result.exit_code == 0, result.output
    two = write_config(root / "two.yaml", survey)  # cascade.stages: 2
    return two, root / "out"


@pytest.fixture(scope="session")
def dask_cluster() -> dict:
    """The ``cluster`` section of a config that runs on a LocalCluster of 2 worker processes
    on loopback, started once per session (``kind: address``, as a user's running cluster):
    the runs whose results must not depend on the workers share its workers, which import
    Silva's modules once instead of once per run. Tests that kill, limit or watch the workers
    of a run, or the cluster a run starts itself, start their own."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0") as cluster:  # not 8787: others' default
        with Client(cluster) as client:
            assert len(client.scheduler_info()["workers"]) == 2
        yield {"kind": "address", "address": cluster.scheduler_address}


#: The runs of the terrain and trees steps' tests: the covariance set, one stage (the
#: context's chunk invariance is tested by the workflow's other runs), the trees, and the
#: DTM, DSM and canopy height rasters.
COVARIANCE = {"set": "covariance", "r1": 0.5}
ONE_STAGE = {"stages": 1, "n_estimators": 6, "min_samples_leaf": 15, "max_train_points": 8000,
             "seed": 3}
RASTERS = {"rasters": ["dtm", "dsm", "chm"], "raster_resolution": 2.0}
TREES_AND_RASTERS = {"trees": True, **RASTERS}
#: The side in metres of the blocks the shared runs find crowns in: several a plot.
TREE_BLOCK = 4.0


def covariance_config(path: Path, survey: dict, chunk_size: float, cluster=None,
                      output=TREES_AND_RASTERS, **sections) -> Path:
    """The config of :func:`covariance_runs` with ``chunk_size``, on ``cluster`` (a config's
    cluster section; None: the default, for a run in this process); trees are found by
    their crowns in blocks of 4 m (:data:`TREE_BLOCK`), so that a plot's trees span
    several blocks (the stems of its terrestrial scan have a test of their own)."""
    sections = {"trees": {"block": TREE_BLOCK, "method": "crowns"}, **sections}
    return write_config(path, survey, features=COVARIANCE, cascade=ONE_STAGE,
                        tiling={"chunk_size": chunk_size}, output=output,
                        cluster=cluster or {}, **sections)


@pytest.fixture(scope="session")
def covariance_runs(survey, tmp_path_factory, dask_cluster) -> tuple[Path, Path]:
    """Two runs of :func:`covariance_config`: one chunk a scene in this process, and 8 m
    chunks (2 x 2 a scene, their borders across the plots' middle) on the session's 2
    workers; their output directories, which the terrain and trees steps' tests share (read
    them; copy one before changing it)."""
    root = tmp_path_factory.mktemp("covariance_runs")
    outs = []
    for name, chunk_size, cluster in (("one", 100.0, None), ("many", 8.0, dask_cluster)):
        config = covariance_config(root / f"{name}.yaml", survey, chunk_size, cluster)
        here = ["--in-process"] if cluster is None else []
        result = silva("run", config, "--out", root / name, "-q", *here)
        assert result.exit_code == 0, result.output
        outs.append(root / name)
    return outs[0], outs[1]


@pytest.fixture(scope="session")
def survey_run_kept(survey_run, tmp_path_factory):
    """The run of :func:`survey_run` with ``output.keep_features: true`` (every scene's
    features stored, the test scene's classified stage by stage), in this process: its
    output directory (read it; copy it before changing it)."""
    config, _ = survey_run
    out = tmp_path_factory.mktemp("survey_run_kept") / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q",
                   "--set", "output.keep_features=true")
    assert result.exit_code == 0, result.output
    return out


def run_layout(out: Path) -> dict:
    """The chunk layout ingest recorded in the store of the run in ``out``."""
    from pipeline.store import open_store

    return open_store(out / "store.zarr", mode="r").attrs["layout"]


def assert_chunked(out: Path, minimum: int) -> None:
    """Every scene of the run in ``out`` was cut into at least ``minimum`` chunks, each
    read with a halo reaching into its neighbours: the results crossed chunk borders."""
    for scene, info in run_layout(out)["scenes"].items():
        assert len(info["chunks"]) >= minimum, (scene, len(info["chunks"]))
        assert info["halo"] > 0, (scene, info["halo"])


def a_tile(n_points=1000, mins=(0.0, 0.0, 0.0), maxs=(10.0, 10.0, 1.0), *, index=0,
           scene="test", name="t", path="t.laz", **more) -> Tile:
    """A tile of the catalogue, as its header would describe it."""
    return Tile(index, path, name, scene, n_points, tuple(mins), tuple(maxs), None, "laz",
                **more)


#: The ground rule's tolerance of the quick configs: every run of the workflow tests applies
#: the rule, so their invariances (chunks, workers, resume, the estimator) hold with it.
GROUND_TOLERANCE = 0.1


def write_config(path: Path, survey: dict, **sections) -> Path:
    """A quick config for ``survey``; keyword arguments update whole sections."""
    config = {
        "data": {
            "train": [str(survey["train"] / "*.laz")],
            "test": [str(survey["test"] / "*.laz")],
            "classes": {"terrain": [2], "tree": [5], "dead_wood": [64], "misc": [1]},
            "background": ["misc"],
        },
        "tiling": {"chunk_size": 100.0},
        "features": {"r1": 0.5},
        "terrain": {"ground_tolerance": GROUND_TOLERANCE},
        "cascade": {"stages": 2, "n_estimators": 6, "min_samples_leaf": 15,
                    "max_train_points": 8000, "seed": 3},
        "cluster": {"kind": "local", "n_workers": 1, "threads_per_worker": 1,
                    "dashboard": False},
    }
    for section, values in sections.items():
        config[section] = {**config.get(section, {}), **values}
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def scene_arrays(out: Path, scene: str, names=("xyz", "label", "role", "features")
                 ) -> dict[str, np.ndarray]:
    """The core arrays ``names`` (and ``gid``) of every chunk of a run's ``scene``, over its
    chunks, ordered by global id."""
    chunks = open_store(out / "store.zarr", mode="r")[f"scenes/{scene}/chunks"]
    parts = {name: [] for name in ("gid", *names)}
    for chunk in sorted(chunks.group_keys()):
        for name in parts:
            parts[name].append(read_array(chunks[chunk], name))
    arrays = {name: np.concatenate(values) for name, values in parts.items()}
    order = np.argsort(arrays["gid"])
    return {name: values[order] for name, values in arrays.items()}


def read_predictions(out: Path) -> dict[str, dict[str, np.ndarray]]:
    """Exported dimensions of every predictions/*.laz, by tile name."""
    result = {}
    for path in sorted((out / "predictions").glob("*.laz")):
        las = laspy.read(path)
        dims = {name: np.asarray(las[name]) for name in las.point_format.dimension_names}
        dims["xyz"] = np.c_[las.x, las.y, las.z]
        result[path.stem] = dims
    return result


def assert_same_predictions(a: Path, b: Path) -> None:
    """The exported class, confidence and one probability of every tile of two runs are
    equal bit for bit."""
    pa, pb = read_predictions(a), read_predictions(b)
    assert pa.keys() == pb.keys() and pa
    for tile in pa:
        for dim in ("PredictedClassification", "Confidence", "Probability_tree"):
            assert np.array_equal(pa[tile][dim], pb[tile][dim]), (tile, dim)


def sigkill_when(args, ready, timeout: float = 240) -> None:
    """Run ``python -m workflows ARGS`` and SIGKILL it as soon as ``ready()`` holds (or
    after ``timeout`` seconds)."""
    command = [sys.executable, "-m", "workflows", *map(str, args)]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not ready():
        time.sleep(0.1)
    process.send_signal(signal.SIGKILL)
    process.wait()


# -- the CLI as a user meets it ------------------------------------------------------------
def silva(*args):
    """Run the silva command in this process; the click Result."""
    from click.testing import CliRunner

    from workflows.cli.main import main

    return CliRunner().invoke(main, [str(a) for a in args])


def error_line(result) -> str:
    """The one 'silva: error:' line of a failed command (exit 1, no traceback)."""
    lines = [line for line in result.output.splitlines() if line.startswith("silva: error:")]
    assert len(lines) == 1, result.output
    assert "Traceback" not in result.output
    assert result.exit_code == 1
    return lines[0]
