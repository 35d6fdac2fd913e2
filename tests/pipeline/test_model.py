"""A model directory ties each forest file to its description by digest."""

import json

import numpy as np
import pytest

from pipeline.errors import ModelError
from pipeline.model import (
    MODEL_FILE,
    load_forest,
    read_description,
    save_forest,
    stage_file,
    verify_stage_files,
    write_description,
)
from tests.pipeline.conftest import small_forest


@pytest.fixture
def model(tmp_path):
    for stage in range(2):
        save_forest(stage_file(tmp_path, stage), small_forest(stage, 2))
    write_description(tmp_path, {
        "classes": [{"name": "a", "code": 1}, {"name": "b", "code": 2}],
        "stages": [{"index": k + 1, "fingerprint": f"f{k}", "file": stage_file(tmp_path, k).name}
                   for k in range(2)],
    })
    return tmp_path


def test_description_records_a_digest_of_every_stage_file(model):
    description = read_description(model)
    assert all(len(stage["sha256"]) == 64 for stage in description["stages"])
    verify_stage_files(model, description)
    assert load_forest(stage_file(model, 1)).n_estimators == 2


def test_swapped_stage_files_are_refused(model):
    one, two = stage_file(model, 0), stage_file(model, 1)
    a, b = one.read_bytes(), two.read_bytes()
    one.write_bytes(b)
    two.write_bytes(a)
    with pytest.raises(ModelError, match="stage1.skops does not match the digest"):
        verify_stage_files(model, read_description(model))
    with pytest.raises(ModelError, match="stage2.skops does not match the digest"):
        load_forest(two)


def test_missing_stage_file_is_refused(model):
    stage_file(model, 1).unlink()
    with pytest.raises(ModelError, match="stage2.skops is missing"):
        verify_stage_files(model, read_description(model))


@pytest.mark.parametrize("change, message", [
    (lambda d: d.pop("classes"), "lists no classes"),
    (lambda d: d.update(stages=[]), "lists no stages"),
    (lambda d: d["stages"][0].pop("sha256"), r"stages\[0\] has no valid 'sha256'"),
    (lambda d: d["classes"][1].update(code="2"), r"classes\[1\] has no valid 'code'"),
])
def test_incomplete_description_is_a_clear_error(model, change, message):
    path = model / MODEL_FILE
    description = json.loads(path.read_text())
    change(description)
    path.write_text(json.dumps(description))
    with pytest.raises(ModelError, match=message):
        read_description(model)


def test_description_that_is_not_an_object(model):
    (model / MODEL_FILE).write_text("[1, 2]")
    with pytest.raises(ModelError, match="not a JSON object"):
        read_description(model)


def test_a_model_records_versions_and_refuses_another_scikit_learn(tmp_path):
    import json

    from pipeline.errors import ModelError
    from pipeline.model import check_versions, software_versions, write_description

    write_description(tmp_path, {"classes": [], "stages": []})
    saved = json.loads((tmp_path / "model.json").read_text())
    assert set(saved["versions"]) == {"silva", "scikit-learn", "skops", "numpy", "numba"}
    check_versions(saved, tmp_path)  # the same versions pass
    saved["versions"]["scikit-learn"] = "0.9.1"
    with pytest.raises(ModelError, match=r"scikit-learn 0\.9\.1.*retrain"):
        check_versions(saved, tmp_path)


def test_other_feature_columns_are_refused_with_advice_that_works():
    from pipeline.errors import ModelError
    from pipeline.model import check_compatible

    trained = {"features.set": "default", "features.columns": ["a", "b"]}
    with pytest.raises(ModelError) as err:
        check_compatible(trained, {"features.columns": ["a", "b", "c"]}, "m")
    message = str(err.value)
    assert "retrain the model with this version" in message
    assert "set features.columns" not in message  # not a key anyone can set
