"""One compile per install: the first command that compiles kernels compiles every kernel a
model installed with Silva or a template can use, with the signatures their runs call, so a
later command with another of them (``silva predict --model NAME`` after ``silva demo``)
compiles nothing."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numba

from pipeline.features import numba_cache
from pipeline.features.numba_cache import kernel_groups, source_digest
from pipeline.features.sets import FeatureParams, auto_voxel
from workflows.config.loading import load_config
from workflows.exec.kernels import SHIPPED_GROUPS, prepare_kernels
from workflows.models import installed_models

ROOT = Path(__file__).resolve().parents[2]
TEMPLATES = sorted((ROOT / "configs").glob("*.yaml"))


def shipped_profiles() -> dict[str, tuple[FeatureParams, str, int]]:
    """name -> (features, cascade.context, number of classes) of every model installed with
    Silva and every template ('auto' r1 and voxel resolved as a run resolves them, 'auto' echoes on)."""
    found = {}
    for name, path in installed_models().items():
        d = json.loads((path / "model.json").read_text())
        found[name] = (FeatureParams(
            d["features.set"], d["features.r1"], d["features.r2"], d["features.max_neighbors"],
            d["features.context_max_neighbors"], d["features.plane"],
            tuple(d["features.scales"]), d["features.column"], d["features.cell"],
            d["features.voxel"], echoes=d.get("features.echoes", False)),
            d["cascade.context"], len(d["classes"]))
    for path in TEMPLATES:
        cfg = load_config(path, ())
        f = cfg.features
        r1 = 0.5 if f.r1 == "auto" else f.r1
        voxel = auto_voxel(r1, f.max_neighbors) if f.voxel == "auto" else f.voxel
        found[path.stem] = (FeatureParams(
            f.set, r1, f.r2, f.max_neighbors, f.context_max_neighbors, f.plane,
            tuple(f.scales), f.column, f.cell, voxel,
            echoes=f.echoes in (True, "auto")),  # 'auto' turns them on for airborne tiles
            cfg.cascade.context, len(cfg.data.classes))
    return found


def test_every_shipped_model_and_template_is_profiled():
    profiles = shipped_profiles()
    assert set(installed_models()) < set(profiles)
    assert {"demo", "forest", "urban", "oakland"} < set(profiles)
    # among them echo features, voxels, both kinds of context, both planes
    assert any(p.echoes for p, _, _ in profiles.values())
    assert {p.voxel is None for p, _, _ in profiles.values()} == {True, False}
    assert {context for _, context, _ in profiles.values()} == {"hard", "soft"}


def test_the_shipped_groups_hold_every_group_a_shipped_model_or_template_uses():
    for name, (params, _, _) in shipped_profiles().items():
        assert set(kernel_groups(params.set, params.voxel is not None)) <= set(SHIPPED_GROUPS), name


def test_the_demo_compiles_the_kernels_of_every_shipped_model(tmp_path, monkeypatch, capsys):
    # a private, empty cache: the demo's command is the first to compile
    folder = tmp_path / "numba" / "silva-numba" / source_digest()
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(folder))
    started = []

    class Recorded:
        seconds = 0.0

        def __init__(self, groups, nice=0):
            started.extend(groups)

        def done(self):
            return True

        def wait(self):
            return []

        def stop(self):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            pass

    monkeypatch.setattr(numba_cache, "Warming", Recorded)
    demo = shipped_profiles()["demo"][0]
    with prepare_kernels(True, demo) as kernels:
        assert kernels.groups == kernel_groups(demo.set, demo.voxel is not None)
    for name, (params, _, _) in shipped_profiles().items():
        assert set(kernel_groups(params.set, params.voxel is not None)) <= set(started), name
    # once compiled and recorded, no command announces or compiles again
    numba_cache.mark_warm(started, folder)
    started.clear()
    for name, (params, _, _) in shipped_profiles().items():
        with prepare_kernels(False, params):
            pass
    assert started == [] and capsys.readouterr().err == ""


def signatures_report():
    """Run in a new process: print, as JSON, the kernel signatures the warm-up compiles and
    those each shipped model's and template's features, pile-up checks and context call on a
    small cloud, as a run's chunks call them (float64 xyz, int64 ids and rows, uint8 returns,
    float32 probabilities)."""
    import numpy as np
    from numba.core.dispatcher import Dispatcher

    from pipeline.cascade.stage import stage_context
    from pipeline.features.sets import feature_set
    from workflows.steps.features import neighbourhood_checks

    def signatures():
        found = set()
        for module in list(sys.modules.values()):
            name = getattr(module, "__name__", "")
            if not name.startswith(("pipeline.", "workflows.")):
                continue
            for key, value in vars(module).items():
                if isinstance(value, Dispatcher) and value.__module__ == name:
                    found |= {f"{name}.{key}{sig}" for sig in value.signatures}
        return found

    for name in SHIPPED_GROUPS:
        numba_cache.GROUPS[name]()
    warmed = signatures()
    rng = np.random.default_rng(0)
    xy = rng.uniform(0.0, 6.0, (1500, 2))
    xyz = np.vstack([np.c_[xy, 0.1 * np.sin(xy[:, 0])], rng.normal([3, 3, 2], 0.5, (500, 3))])
    xyz += [500000.0, 5500000.0, 400.0]
    ids = np.arange(len(xyz), dtype=np.int64) * 3 + 7
    query = np.arange(len(xyz) // 2, dtype=np.int64)
    ground = np.full(len(xyz), 400.0)
    returns = (rng.integers(1, 3, len(xyz)).astype(np.uint8), np.full(len(xyz), 2, np.uint8))
    used = {}
    for name, (params, context, n_classes) in shipped_profiles().items():
        before = signatures()
        compute = feature_set(params)
        compute(xyz, query, ids, ground if compute.uses_ground else None,
                returns if compute.uses_returns else None)
        neighbourhood_checks(xyz, ids, query, params.r1)
        proba = rng.dirichlet(np.ones(n_classes), len(xyz)).astype(np.float32)
        stage_context(xyz, proba, context, r1=params.r1, r2=params.r2,
                      max_neighbors=params.context_max_neighbors, query=query, ids=ids)
        used[name] = sorted(signatures() - before)
    print(json.dumps({"warmed": sorted(warmed), "new": used}))


def test_after_the_warm_up_no_shipped_model_or_template_needs_another_kernel():
    # a new process, so that no kernel of this one counts: the warm-up's groups, then each
    # profile; every signature a profile calls must be one the warm-up compiled (numba loads
    # it from the cache instead of compiling it)
    code = "from tests.workflows.test_kernel_warmup import signatures_report; signatures_report()"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, cwd=ROOT, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.splitlines()[-1])
    assert report["warmed"], "the warm-up compiled no kernel"
    assert report["new"] == {name: [] for name in report["new"]}
    assert set(report["new"]) == set(shipped_profiles())
