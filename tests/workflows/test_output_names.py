"""Output dimension names are checked when the config is read, not at export after training."""

import pytest

from pipeline.errors import ConfigError
from pipeline.io import ExtraDim
from tests.workflows.conftest import error_line, silva, write_config
from workflows.config import validate_config
from workflows.config.schema import MAX_CLASS_NAME_BYTES, PROBABILITY_PREFIX, feature_dim_name
from workflows.steps.export import probability_dim

LONGEST = "x" * MAX_CLASS_NAME_BYTES


def _classes(*names):
    return {"data": {"classes": {name: [i + 1] for i, name in enumerate(names)}}}


def test_the_limit_is_what_las_allows():
    assert probability_dim("tree") == PROBABILITY_PREFIX + "tree"
    ExtraDim(probability_dim(LONGEST), "float32")  # the longest accepted name fits LAS
    with pytest.raises(ValueError):
        ExtraDim(probability_dim(LONGEST + "x"), "float32")


def test_longest_class_name_is_accepted():
    cfg = validate_config(_classes(LONGEST, "tree"))
    assert cfg.data.class_names == [LONGEST, "tree"]


@pytest.mark.parametrize("name", ["standing_dead_wood_on_slope", "é" * 11])
def test_too_long_class_name_is_a_config_error(name):
    with pytest.raises(ConfigError) as err:
        validate_config(_classes("tree", name))
    message = str(err.value)
    assert "\n" not in message
    assert f"data.classes: class name '{name}'" in message
    assert "32-byte" in message and f"at most {MAX_CLASS_NAME_BYTES} bytes" in message


def test_run_refuses_a_long_class_name_before_any_work(tmp_path, survey):
    classes = {"terrain": [2], "tree": [5], "coarse_woody_debris_pieces": [64], "misc": [1]}
    config = write_config(tmp_path / "c.yaml", survey, data={"classes": classes})
    out = tmp_path / "out"
    line = error_line(silva("run", config, "--out", out, "--quiet"))
    assert "coarse_woody_debris_pieces" in line
    assert not (out / "store.zarr").exists()


# -- output.feature_dims: feature columns as extra dimensions --------------------------------
def test_feature_dim_names_are_valid_las_and_pdal_names():
    assert feature_dim_name("linearity_r0.5") == "linearity_r0_5"
    assert feature_dim_name("I2_22") == "I2_22"
    ExtraDim(feature_dim_name("change_of_curvature_r12.3457"), "float32")


def test_unknown_feature_column_is_a_one_line_config_error():
    with pytest.raises(ConfigError) as err:
        validate_config({"features": {"set": "paper"},
                         "output": {"feature_dims": ["I2_22", "linearity_r0.5"]}})
    message = str(err.value)
    assert "\n" not in message
    assert ("output.feature_dims[1] 'linearity_r0.5' is not a column of feature set "
            "'paper'") in message
    assert "valid: I2_22, I2_222," in message and "I3_3111" in message


def test_feature_columns_are_chosen_by_name_pattern_or_all():
    def chosen(value, **features):
        cfg = validate_config({"features": {"set": "default", "r1": 0.5, **features},
                               "output": {"feature_dims": value}})
        return cfg.feature_dim_columns

    assert chosen("relative_height_above_ground") == ["relative_height_above_ground"]
    assert chosen(["linearity_*", "I2_22"]) == [
        "linearity_r0.25", "linearity_r0.5", "linearity_r1", "linearity_r2", "I2_22"]
    from pipeline.features.sets import FeatureParams, feature_set

    columns = feature_set(FeatureParams(set="default", r1=0.5)).columns
    assert chosen("all") == list(columns) and chosen([]) == []


def test_run_refuses_an_unknown_feature_column_before_any_work(tmp_path, survey):
    config = write_config(tmp_path / "c.yaml", survey, output={"feature_dims": ["planarity"]})
    out = tmp_path / "out"
    line = error_line(silva("run", config, "--out", out, "--quiet"))
    assert "output.feature_dims[0] 'planarity'" in line
    assert not (out / "store.zarr").exists()


def test_the_reserved_names_are_the_exported_ones():
    from workflows.config.schema import SILVA_DIMS
    from workflows.steps import export

    names = (export.PREDICTED, export.CONFIDENCE, export.ENTROPY, export.NO_FEATURES,
             export.HEIGHT_ABOVE_GROUND, export.EXCLUDED)
    assert set(SILVA_DIMS) == set(names)
    dims = export.extra_dims(["tree"], [5], True, excluded=True, features=("linearity_r0.5",))
    assert [d.name for d in dims] == [*names, "Probability_tree", "linearity_r0_5"]
