"""A wheel install (not editable) carries the configs and the models: ``silva init``, the demo
config and ``silva models`` work.

Builds the wheel from a copy of the source tree (offline: no build isolation), installs it
with ``--no-deps`` into a fresh venv that sees this environment's packages, and runs the
venv's ``silva`` from a directory outside the source tree.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
SKIP = shutil.ignore_patterns(".git", "build", "dist", "*.egg-info", "__pycache__",
                              ".hypothesis", ".pytest_cache", ".benchmarks", "silva-*")


def run(*args, cwd):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # the venv's own paths
    done = subprocess.run([str(a) for a in args], capture_output=True, text=True, cwd=cwd,
                          env=env)
    assert done.returncode == 0, f"{args}:\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("wheel")
    source = root / "source"
    shutil.copytree(REPO, source, ignore=SKIP)
    run(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
        "--wheel-dir", root / "dist", source, cwd=root)
    wheels = list((root / "dist").glob("silva-*.whl"))
    assert len(wheels) == 1, wheels
    # without a pip of its own (ensurepip takes longer than the rest): the venv's python
    # runs this environment's pip, which installs into the venv
    run(sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", root / "venv",
        cwd=root)
    bin_dir = root / "venv" / ("Scripts" if sys.platform == "win32" else "bin")
    run(bin_dir / "python", "-m", "pip", "install", "--no-deps", "--no-index", wheels[0],
        cwd=root)
    return bin_dir


def test_wheel_ships_the_configs_and_init_writes_them(venv, tmp_path):
    for name in ("forest", "demo", "oakland", "urban"):
        target = tmp_path / f"{name}.yaml"
        run(venv / "silva", "init", "--template", name, target, cwd=tmp_path)
        assert target.read_text() == (REPO / "configs" / f"{name}.yaml").read_text()


def test_wheel_loads_its_packaged_demo_config(venv, tmp_path):
    code = (
        "import workflows\n"
        "from workflows.config import load_config\n"
        "from workflows.cli.templates import template_path\n"
        "with template_path('demo') as path:\n"
        "    cfg = load_config(path)\n"
        "print(workflows.__file__)\n"
        "print(path)\n"
        "print(cfg.tiling.chunk_size, ','.join(cfg.data.class_names))\n"
    )
    module, path, values = run(venv / "python", "-c", code, cwd=tmp_path).splitlines()
    site = str(venv.parent)
    assert module.startswith(site) and path.startswith(site), (module, path)  # not the checkout
    assert values == "15.0 terrain,tree,dead_wood,misc"


def test_wheel_ships_the_models_whole(venv, tmp_path):
    import json

    listed = json.loads(run(venv / "silva", "models", "--json", cwd=tmp_path))
    names = sorted(p.name for p in (REPO / "workflows" / "models").iterdir()
                   if (p / "model.json").is_file())
    assert sorted(m["name"] for m in listed) == names and len(names) >= 2
    site = str(venv.parent)
    code = ("from workflows.models import installed_models\n"
            "from pipeline.model import read_description, verify_stage_files\n"
            "for name, path in installed_models().items():\n"
            "    verify_stage_files(path, read_description(path))\n"
            "    print(path)\n")
    paths = run(venv / "python", "-c", code, cwd=tmp_path).split()
    assert len(paths) == len(names) and all(p.startswith(site) for p in paths)
