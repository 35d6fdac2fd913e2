"""Many small tiles cost about what one tile of their points costs: the small tiles of a
chunk are read by one ingest task and stored as one part, and the predictions are those of
the same points as one tile, bit for bit."""

import laspy
import numpy as np
import pytest

from pipeline.store import open_store
from workflows.exec.engine import Engine
from tests.workflows.conftest import silva

MODEL = "forest-tls-synthetic"
CUTS = 8  # the plot cut into CUTS x CUTS small tiles


@pytest.fixture(scope="module")
def cloud(tmp_path_factory):
    """A synthetic plot as one tile and as the same points in CUTS x CUTS small tiles.

    The one tile holds the points in the order of the small tiles (by name), so global ids
    (tile, index in tile) order the points alike in both: neighbourhoods are ordered by id.
    """
    from pipeline.synth import write_synthetic_plot

    root = tmp_path_factory.mktemp("small_tiles")
    (path,) = write_synthetic_plot(root / "plot", seed=2, size=8.0, tile_size=8.0)
    las = laspy.read(path)
    x, y = np.asarray(las.x), np.asarray(las.y)
    ix = np.clip(((x - x.min()) / np.ptp(x) * CUTS).astype(int), 0, CUTS - 1)
    iy = np.clip(((y - y.min()) / np.ptp(y) * CUTS).astype(int), 0, CUTS - 1)
    cell = ix * CUTS + iy
    for name in ("one", "many"):
        (root / name).mkdir()
    one = laspy.LasData(las.header)
    one.points = las.points[np.argsort(cell, kind="stable")].copy()
    one.write(root / "one" / "plot.laz")
    for c in np.unique(cell):
        tile = laspy.LasData(las.header)
        tile.points = las.points[cell == c].copy()
        tile.write(root / "many" / f"t{c:03d}.laz")
    return root


@pytest.fixture
def task_counts(monkeypatch):
    """The number of tasks of each step the runs of a test map."""
    counts: dict[str, list[int]] = {}
    mapped = Engine.map

    def counting(self, step, tasks):
        counts.setdefault(step, []).append(len(tasks))
        return mapped(self, step, tasks)

    monkeypatch.setattr(Engine, "map", counting)
    return counts


def _predict(out, tiles, *settings):
    args = ["predict", "--model", MODEL, "--out", out, str(tiles), "--in-process", "-q",
            "--set", "output.keep_store=true"]
    for setting in settings:
        args += ["--set", setting]
    result = silva(*args)
    assert result.exit_code == 0, result.output


def _outputs(out) -> list[laspy.LasData]:
    return [laspy.read(p) for p in sorted((out / "predictions").glob("*.laz"))]


def _assert_same_points(many: list[laspy.LasData], one: laspy.LasData) -> None:
    """The small tiles' outputs, in name order, are the one tile's output point by point,
    in every dimension."""
    names = list(one.point_format.dimension_names)
    for las in many:
        assert list(las.point_format.dimension_names) == names
    for name in names:
        joined = np.concatenate([np.asarray(las[name]) for las in many])
        assert np.array_equal(joined, np.asarray(one[name]), equal_nan=True), name


@pytest.fixture(scope="module")
def reference(cloud, tmp_path_factory) -> laspy.LasData:
    """The output of the points as one tile (one chunk, defaults)."""
    out = tmp_path_factory.mktemp("one") / "out"
    _predict(out, cloud / "one" / "plot.laz")
    (one,) = _outputs(out)
    return one


@pytest.mark.parametrize("settings, budget", [
    ((), 250_000),  # the scene is one chunk: one group
    (("tiling.target_points=10000", "tiling.read_batch=700"), 2_500),  # small groups,
    # written in batches of 700 points
    (("tiling.chunk_size=4",), 250_000),  # several chunks: the tiles of each in one group
], ids=["one-chunk", "small-groups", "grid"])
def test_many_small_tiles_are_read_in_few_tasks_and_predict_the_same_bits(
        cloud, reference, tmp_path, task_counts, settings, budget):
    sources = sorted((cloud / "many").glob("*.laz"))
    assert len(sources) > 50
    _predict(tmp_path / "many", cloud / "many" / "*.laz", *settings)

    # one ingest task per group of small tiles, not per tile
    (n_tasks,) = task_counts["ingest"]
    assert n_tasks < len(sources) / 4, n_tasks
    layout = open_store(tmp_path / "many" / "store.zarr").attrs["layout"]
    scene = layout["scenes"]["predict"]
    n_chunks = len(scene["chunks"])
    n_points = sum(t["n_points"] for t in layout["tiles"])
    assert n_tasks == len(scene["groups"]) <= 2 * n_points / budget + n_chunks
    assert sorted(i for group in scene["groups"] for i in group) == list(range(len(sources)))
    for group in scene["groups"]:
        assert len(group) == 1 or sum(layout["tiles"][i]["n_points"] for i in group) <= budget
    assert scene["tiles"] == [group[0] for group in scene["groups"]]  # the chunks' parts
    if "tiling.chunk_size=4" in settings:
        assert n_chunks > 1

    # every small tile is written as its own file, with its points and dimensions ...
    many = _outputs(tmp_path / "many")
    assert [p.name for p in sorted((tmp_path / "many" / "predictions").glob("*.laz"))] == [
        p.name for p in sources]
    for las, source in zip(many, sources):
        original = laspy.read(source)
        assert len(las.points) == len(original.points)
        assert set(original.point_format.dimension_names) <= set(las.point_format.dimension_names)
        assert np.array_equal(las.X, original.X) and np.array_equal(las.Z, original.Z)
    # ... and the predictions are those of the one tile, bit for bit, whatever the chunks
    _assert_same_points(many, reference)

    if not settings:  # a rerun keeps the ingested groups: no tile is read again
        root = open_store(tmp_path / "many" / "store.zarr")
        markers = sorted(root["scenes/predict/parts"].group_keys())
        assert markers == sorted(str(group[0]) for group in scene["groups"])
        task_counts.clear()
        _predict(tmp_path / "many", cloud / "many" / "*.laz", *settings)
        assert "ingest" not in task_counts
