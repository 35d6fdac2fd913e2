"""One check for a finite number > 0: every parameter set refuses with a ConfigError that names
its key, every function of arrays with an InputError naming its argument."""

import math

import pytest

from pipeline.cascade import CascadeParams
from pipeline.cascade.thinning import point_density
from pipeline.checks import finite_number, finite_numbers
from pipeline.errors import ConfigError, InputError
from pipeline.features.sets import FeatureParams
from pipeline.grid import Raster
from pipeline.terrain import TerrainParams
from pipeline.trees import TreeParams


@pytest.mark.parametrize("raw", [0, -1.0, math.nan, math.inf, "two", None, True])
def test_finite_number_refuses_what_is_not_a_finite_number_above_0(raw):
    with pytest.raises(ConfigError, match=r"^terrain\.cell must be a finite number > 0, got "):
        finite_number(raw, "terrain.cell")


def test_finite_number_takes_0_when_asked_and_says_the_hint():
    assert finite_number(0, "terrain.scalar", positive=False) == 0.0
    assert finite_number("2.5", "x") == 2.5
    with pytest.raises(InputError, match=r"^x must be a finite number >= 0, got -1; use 0$"):
        finite_number(-1, "x", positive=False, hint="use 0", error=InputError)


def test_finite_numbers_are_distinct_and_above_0():
    assert finite_numbers([1, 2.5], "radii") == (1.0, 2.5)
    for raw in ([], [1.0, -1.0], [1.0, 1.0]):
        with pytest.raises(ConfigError, match="^radii must"):
            finite_numbers(raw, "radii")


@pytest.mark.parametrize("make, key", [
    (lambda: TerrainParams(cell=math.nan), "terrain.cell"),
    (lambda: TerrainParams(scalar=-1), "terrain.scalar"),
    (lambda: TreeParams(resolution=0), "trees.resolution"),
    (lambda: TreeParams(min_height=math.inf), "trees.min_height"),
    (lambda: FeatureParams(r1=math.inf), "features.r1"),
    (lambda: FeatureParams(column=-3.0), "features.column"),
    (lambda: FeatureParams(cell=0.0), "features.cell"),
    (lambda: FeatureParams(voxel=math.nan), "features.voxel"),
    (lambda: CascadeParams(stages=0), "cascade.stages"),
    (lambda: CascadeParams(context="fuzzy"), "cascade.context"),
])
def test_every_parameter_set_names_the_key_in_a_config_error(make, key):
    with pytest.raises(ConfigError, match=f"^{key.replace('.', '[.]')} must "):
        make()


def test_functions_of_arrays_name_their_argument_in_an_input_error():
    with pytest.raises(InputError, match="^Raster cell must be a finite number > 0"):
        Raster([[1.0]], 0.0, 0.0, 0.0)
    with pytest.raises(InputError, match="^cell must be a finite number > 0"):
        point_density([[0.0, 0.0]], cell=math.nan)
