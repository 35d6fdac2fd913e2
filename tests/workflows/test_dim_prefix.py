"""Inputs that already carry a dimension of a name Silva adds: refused before any work when
the types differ, and written beside them under output.dim_prefix."""

import laspy
import numpy as np
import pytest

from tests.workflows.conftest import error_line, read_predictions, silva, write_config

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def clashing(survey, tmp_path_factory):
    """The survey's test tiles with a float32 PredictedClassification of their own."""
    root = tmp_path_factory.mktemp("clash")
    for tile in sorted(survey["test"].glob("*.laz")):
        las = laspy.read(tile)
        las.add_extra_dim(laspy.ExtraBytesParams("PredictedClassification", np.float32))
        las.PredictedClassification = np.full(len(las.points), 0.25, np.float32)
        las.write(root / tile.name)
    return root


def test_a_clash_of_types_is_refused_before_any_work(clashing, survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", survey, data={"test": [str(clashing / "*.laz")]})
    out = tmp_path / "out"
    line = error_line(silva("run", config, "--out", out, "--in-process"))
    assert "already has a dimension 'PredictedClassification' of type float32" in line
    assert "--set output.dim_prefix=silva_" in line and "clash" in line
    assert not (out / "store.zarr").exists()


def test_a_prefix_writes_silvas_dimensions_beside_the_inputs(clashing, survey, tmp_path):
    config = write_config(tmp_path / "c.yaml", survey, data={"test": [str(clashing / "*.laz")]},
                          cascade={"stages": 1})
    out = tmp_path / "out"
    result = silva("run", config, "--out", out, "--in-process", "-q",
                   "--set", "output.dim_prefix=silva_")
    assert result.exit_code == 0, result.output
    dims = read_predictions(out)
    tile = next(t for t in dims if t.startswith("plot_s2"))
    assert np.all(dims[tile]["PredictedClassification"] == np.float32(0.25))  # kept as it was
    assert set(np.unique(dims[tile]["silva_PredictedClassification"])) <= {1, 2, 5, 64}
    assert {"silva_Confidence", "silva_HeightAboveGround", "silva_Probability_tree"} <= set(
        dims[tile])


def test_a_prefix_too_long_for_las_names_is_refused(survey, tmp_path):
    from pipeline.errors import ConfigError
    from workflows.config import load_config

    config = write_config(tmp_path / "c.yaml", survey)
    with pytest.raises(ConfigError, match="longer than the 32-byte LAS limit"):
        load_config(config, ["output.dim_prefix=a_very_long_prefix_"])
    with pytest.raises(ConfigError, match="letters, digits and _"):
        load_config(config, ["output.dim_prefix=si.va"])
