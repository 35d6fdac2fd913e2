"""The models installed with Silva: listed by 'silva models', usable by name."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.errors import ModelError
from tests.workflows.conftest import silva
from workflows.models import installed_models, model_path

ROOT = Path(__file__).resolve().parents[2]


def test_silva_models_lists_every_installed_model_with_its_card():
    result = silva("models", "--json")
    assert result.exit_code == 0, result.output
    listed = json.loads(result.output)
    assert [m["name"] for m in listed] == list(installed_models())
    for model in listed:
        assert {"name", "kind", "classes", "training_data", "licences", "scores"} <= set(model)
        assert model["size_bytes"] < 8 * 2**20  # small enough for the wheel
        assert model_path(model["name"]) == installed_models()[model["name"]]
    text = silva("models")
    assert text.exit_code == 0
    for model in listed:
        assert model["name"] in text.output


def test_the_installed_models_are_an_airborne_and_a_forest_model():
    listed = json.loads(silva("models", "--json").output)
    kinds = {m["kind"]: m for m in listed}
    assert set(kinds) >= {"als", "tls"}
    assert kinds["als"]["classes"] == {"ground": 2, "vegetation": 5, "building": 6}


def test_an_installed_name_is_not_taken_for_a_directory_of_that_name(tmp_path, monkeypatch):
    name = next(iter(installed_models()))
    monkeypatch.chdir(tmp_path)
    (tmp_path / name / "predictions").mkdir(parents=True)  # an earlier run's --out
    assert model_path(name) == installed_models()[name]
    (tmp_path / name / "model.json").write_text("{}")
    with pytest.raises(ModelError, match=f"--model ./{name}"):
        model_path(name)  # both could be meant: said, not guessed
    assert model_path(f"./{name}").absolute() == tmp_path / name


def test_a_directory_without_a_model_json_is_refused(tmp_path):
    with pytest.raises(ModelError, match="without a model.json"):
        model_path(tmp_path)


def test_silva_models_prints_a_table_of_kind_classes_densities_echoes_and_score():
    result = silva("models")
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    header = lines[0].split()
    assert header == ["MODEL", "KIND", "CLASSES", "(CODE)", "TRAINED", "AT", "ECHOES", "SCORE"]
    n = len(installed_models())
    rows = {line.split()[0]: line for line in lines[1:1 + n]}
    assert set(rows) == set(installed_models())
    als, tls = rows["als-ground-vegetation-building"], rows["forest-tls-synthetic"]
    assert lines[1] == als  # sorted by name
    # every column starts where its header does
    for name in ("KIND", "CLASSES", "TRAINED", "ECHOES", "SCORE"):
        column = lines[0].index(name)
        assert als[column - 2:column] == "  " and als[column] != " "
        assert tls[column - 2:column] == "  " and tls[column] != " "
    assert "  airborne  " in als and "  terrestrial  " in tls
    assert "ground 2, vegetation 5, building 6" in als
    assert "terrain 2, tree 5, dead_wood 64, misc 1" in tls
    assert als[lines[0].index("ECHOES"):].startswith("yes ")
    assert tls[lines[0].index("ECHOES"):].startswith("no ")
    assert "0.9-559 pts/m²" in als
    assert als.endswith("0.974 macro F1, held-out halves of 5 tiles")
    assert tls.endswith("0.957 macro F1, held-out synthetic plot, without misc")
    assert "1 pt/m²" in rows["als-sparse-ground-vegetation-building"]
    assert "silva models --json" in result.output


def test_each_cards_headline_score_is_one_of_its_scores():
    def numbers(value):
        if isinstance(value, dict):
            for v in value.values():
                yield from numbers(v)
        elif isinstance(value, (int, float)):
            yield value

    for model in json.loads(silva("models", "--json").output):
        assert model["headline"]["value"] in set(numbers(model["scores"])), model["name"]
        assert model["trained_density"]


def test_a_model_trained_on_thinned_copies_lists_their_densities():
    from workflows.cli.commands import models_table

    model = json.loads(silva("models", "--json").output)[1]
    model["densities"] = [10.0, 5.0]
    (row,) = [line for line in models_table([model]) if line.startswith(model["name"])]
    assert "; copies at 10, 5 pts/m²" in row


def test_silva_models_reads_no_forest(monkeypatch):
    import builtins

    import pipeline.model

    def refuse(*args, **kwargs):
        raise AssertionError("silva models loaded a forest")

    def guarded_open(file, *args, **kwargs):
        if str(file).endswith(".skops"):
            refuse()
        return real_open(file, *args, **kwargs)

    real_open = builtins.open
    monkeypatch.setattr(pipeline.model, "load_forest", refuse)
    monkeypatch.setattr(builtins, "open", guarded_open)
    for args in (("models",), ("models", "--json")):
        result = silva(*args)
        assert result.exit_code == 0, result.output
    with pytest.raises(AssertionError, match="loaded a forest"):  # the guard guards
        open(next(installed_models()["forest-tls-synthetic"].glob("*.skops")), "rb")


def test_silva_models_imports_neither_the_forests_nor_the_run_machinery():
    # a fresh interpreter: what listing the models imports, skops and scikit-learn above all
    code = ("import sys; from workflows.cli.main import main\n"
            "try:\n    main(['models'], prog_name='silva')\nexcept SystemExit:\n    pass\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & "
            "{'skops', 'sklearn', 'numba', 'dask', 'distributed', 'zarr', 'laspy', 'scipy', "
            "'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": str(ROOT)}).stdout
    assert out.splitlines()[-1] == "[]"
