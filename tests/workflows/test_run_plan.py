"""The run plan: resolved once, frozen, the applied model read once."""

import dataclasses
import hashlib
import json
import os

import numpy as np
import pytest

import pipeline.model
from pipeline.io import write_las
from workflows.config import load_config
from workflows.models import model_path
from workflows.run import autoparams
from workflows.run.autoparams import resolve_run
from workflows.run.directory import Run
from workflows.steps import cascade
from workflows.steps.cascade import model_stages
from workflows.steps.table import STEPS

DEMO = "configs/demo.yaml"


def test_the_plan_is_frozen_and_digests_the_input_files(tmp_path):
    tiles = [tmp_path / "b.laz", tmp_path / "a.laz"]
    for i, tile in enumerate(tiles):
        write_las(tile, np.arange(3 * (i + 1), dtype=float).reshape(-1, 3))
    sizes = {tile.name: tile.stat().st_size for tile in tiles}
    plan = resolve_run(load_config(DEMO, [f"data.test=[{tmp_path}/*.laz]"]))
    assert [(f.scene, f.path.name, f.size) for f in plan.inputs] == [
        ("test", "a.laz", sizes["a.laz"]), ("test", "b.laz", sizes["b.laz"])]
    # each header read once, into the catalogue, in the inputs' order
    assert [(t.index, t.name, t.n_points) for t in plan.tiles] == [(0, "a", 2), (1, "b", 1)]
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.cfg = None
    state = [(str(tmp_path / name), "test", sizes[name], os.stat(tmp_path / name).st_mtime_ns)
             for name in ("a.laz", "b.laz")]
    assert plan.inputs_digest == hashlib.sha256(json.dumps(state).encode()).hexdigest()[:16]
    without_inputs = Run(resolve_run(load_config(DEMO)), tmp_path, steps=STEPS)
    # the inputs are part of every fingerprint
    with_inputs = Run(plan, tmp_path / "out", steps=STEPS)
    assert with_inputs.fingerprint("ingest") != without_inputs.fingerprint("ingest")


def test_the_applied_model_is_read_and_checked_once(tmp_path, monkeypatch):
    reads = []
    read = pipeline.model.read_model_file
    monkeypatch.setattr(autoparams, "read_model_file",
                        lambda path: reads.append(path) or read(path))
    for module in (pipeline.model, cascade):
        for name in ("read_model_file", "read_description"):
            monkeypatch.setattr(module, name, lambda path: pytest.fail("model.json read again"))
    model = model_path("forest-tls-synthetic")
    plan = resolve_run({}, model)
    run = Run(plan, tmp_path / "out", steps=STEPS)
    assert reads == [model] and plan.model.path == model
    assert model_stages(run) == plan.model.stages and len(plan.model.stages) == plan.n_stages
    digest = hashlib.sha256((model / "model.json").read_bytes()).hexdigest()
    assert plan.model.digest == digest
    assert run.results_stamp() and run.model_dir == model
