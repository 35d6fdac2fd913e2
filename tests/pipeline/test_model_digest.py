"""The whole model bundle is under one digest: model.json records the digest of itself (its
classes, radii and stages, the stage files' digests included), so an edit of model.json or of
a forest file is refused in one line; a model.json that cannot be parsed is one line too."""

import json
import logging

import numpy as np
import pytest

from pipeline.errors import ModelError
from pipeline.model import (
    MODEL_FILE,
    file_digest,
    load_forest,
    read_description,
    save_forest,
    stage_file,
    verify_stage_files,
    write_description,
)
from tests.conftest import edit_model_json
from tests.pipeline.conftest import small_forest


@pytest.fixture
def model(tmp_path):
    for stage in range(2):
        save_forest(stage_file(tmp_path, stage), small_forest(stage, 3))
    write_description(tmp_path, {
        "features.set": "paper", "features.r1": 0.5,
        "classes": [{"name": "terrain", "code": 2}, {"name": "tree", "code": 5},
                    {"name": "misc", "code": 1}],
        "seed": 3,
        "stages": [{"index": k + 1, "fingerprint": f"f{k}", "file": stage_file(tmp_path, k).name}
                   for k in range(2)],
    })
    return tmp_path


def test_a_saved_model_records_its_digest_and_loads(model):
    description = read_description(model)
    assert len(description["digest"]) == 64
    verify_stage_files(model, description)
    assert load_forest(stage_file(model, 1)).n_estimators == 2


EDITS = {
    "class order": lambda d: d.update(classes=d["classes"][::-1]),
    "class code": lambda d: d["classes"][1].update(code=6),
    "class name": lambda d: d["classes"][0].update(name="ground"),
    "r1": lambda d: d.update({"features.r1": 0.75}),
    "feature set": lambda d: d.update({"features.set": "covariance"}),
    "one stage dropped": lambda d: d.update(stages=d["stages"][:1]),
    "stages swapped": lambda d: d.update(stages=d["stages"][::-1]),
    "stage fingerprint": lambda d: d["stages"][0].update(fingerprint="other"),
    "seed": lambda d: d.update(seed=4),
    "a key added": lambda d: d.update(note="checked by hand"),
    "a digest that is no text": lambda d: d.update(digest=[d["digest"]]),
}


@pytest.mark.parametrize("name", sorted(EDITS))
def test_an_edited_description_is_refused(model, name):
    edit_model_json(model, EDITS[name])
    for read in (read_description, lambda m: load_forest(stage_file(m, 0))):
        with pytest.raises(ModelError) as caught:
            read(model)
        message = str(caught.value)
        assert str(model / MODEL_FILE) in message and "\n" not in message
        assert "was changed after the model was saved" in message
        assert "restore the model's own model.json or retrain" in message


def test_a_replaced_forest_with_its_digest_edited_in_is_refused(model):
    save_forest(stage_file(model, 1), small_forest(7, 3))
    edit_model_json(model, lambda d: d["stages"][1].update(sha256=file_digest(stage_file(model, 1))))
    with pytest.raises(ModelError, match="was changed after the model was saved"):
        load_forest(stage_file(model, 1))


def test_a_replaced_forest_is_refused_naming_the_file(model):
    save_forest(stage_file(model, 1), small_forest(7, 3))
    with pytest.raises(ModelError, match=r"stage2\.skops does not match the digest .* "
                                         "restore the model's own files or retrain"):
        load_forest(stage_file(model, 1))


def test_layout_and_key_order_are_not_edits(model):
    path = model / MODEL_FILE
    description = json.loads(path.read_text())
    path.write_text(json.dumps(dict(reversed(description.items())), separators=(",", ":")))
    assert read_description(model)["classes"][0]["name"] == "terrain"


def test_rewriting_a_description_gives_it_a_fresh_digest(model):
    description = read_description(model)
    write_description(model, {**description, "stages": description["stages"][:1]})
    assert len(read_description(model)["stages"]) == 1


def test_a_description_saved_without_a_digest_still_loads(model, caplog):
    edit_model_json(model, lambda d: d.pop("digest"))
    with caplog.at_level(logging.WARNING, logger="pipeline.model"):
        assert len(read_description(model)["stages"]) == 2
    assert "records no digest" in caplog.text


@pytest.mark.parametrize("text, reason", [
    ("[" * 100_000 + "]" * 100_000, "nests lists or objects too deeply"),
    ('{"classes": ' + "{\"a\": " * 50_000 + "1" + "}" * 50_001, "nests lists or objects"),
    ('{"seed": 1' + "0" * 5000 + "}", "is not valid JSON"),
    ('{"classes": [', "is not valid JSON"),
    (b"\xff\xfe{}", "is not valid JSON"),
], ids=["deep list", "deep object", "huge integer", "cut off", "not UTF-8"])
def test_an_unparsable_description_is_one_line(model, text, reason):
    path = model / MODEL_FILE
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    for read in (read_description, lambda m: load_forest(stage_file(m, 0))):
        with pytest.raises(ModelError) as caught:
            read(model)
        message = str(caught.value)
        assert message.startswith(f"model description {path} {reason}")
        assert "\n" not in message and "retrain" in message
