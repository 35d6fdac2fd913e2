"""Packaged configs and ``silva init``: templates a user edits, the same as configs/."""

from pathlib import Path

import pytest
from click.testing import CliRunner

from workflows.cli.main import main
from workflows.cli.templates import TEMPLATES, template_path, template_text
from workflows.config import load_config

REPO = Path(__file__).resolve().parents[2]


def silva(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _error_line(result) -> str:
    lines = [line for line in result.output.splitlines() if line.startswith("silva: error:")]
    assert len(lines) == 1 and "Traceback" not in result.output, result.output
    return lines[0]


def test_every_config_of_the_repository_is_a_packaged_template():
    assert sorted(TEMPLATES) == sorted(p.stem for p in (REPO / "configs").glob("*.yaml"))
    for name in TEMPLATES:
        assert template_text(name) == (REPO / "configs" / f"{name}.yaml").read_text()


def test_the_demo_template_loads():
    with template_path("demo") as path:
        cfg = load_config(path)
    assert cfg.data.class_names == ["terrain", "tree", "dead_wood", "misc"]


@pytest.mark.parametrize("template", [None, "forest", "demo", "oakland", "urban"])
def test_init_writes_the_template(tmp_path, template):
    target = tmp_path / "my-survey.yaml"
    args = ["init", target] if template is None else ["init", "--template", template, target]
    result = silva(*args)
    assert result.exit_code == 0, result.output
    assert target.read_text() == template_text(template or "forest")
    assert result.output.count("\n") == 1 and f"silva run {target}" in result.output
    assert [p.name for p in tmp_path.iterdir()] == ["my-survey.yaml"]  # no temporary left


def test_init_refuses_to_overwrite_without_force(tmp_path):
    target = tmp_path / "mine.yaml"
    target.write_text("data: {}\n")
    result = silva("init", target)
    assert result.exit_code == 1
    line = _error_line(result)
    assert str(target) in line and "--force" in line
    assert target.read_text() == "data: {}\n"
    assert silva("init", "--force", target).exit_code == 0
    assert target.read_text() == template_text("forest")


@pytest.mark.parametrize("args, expected", [
    (["init", "--template", "city", "x.yaml"], "Invalid value for '--template'"),
    (["init"], "Missing argument 'PATH'"),
])
def test_init_usage_errors_are_one_line(args, expected):
    result = silva(*args)
    assert result.exit_code == 1 and expected in _error_line(result)


def test_init_into_a_directory_names_a_file_to_give(tmp_path):
    result = silva("init", tmp_path)
    assert result.exit_code == 1
    assert f"{tmp_path} is a directory" in _error_line(result)


def test_the_urban_template_loads_with_the_best_documented_setting():
    with template_path("urban") as path:
        cfg = load_config(path)
    assert cfg.features.set == "default" and cfg.features.r1 == 0.6
    assert cfg.cascade.context == "soft" and cfg.cascade.out_of_fold
    assert (cfg.cascade.n_estimators, cfg.cascade.min_samples_leaf) == (100, 1)
    assert cfg.data.class_codes == [2, 5, 6, 14, 15, 1]
