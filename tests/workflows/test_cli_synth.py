"""``silva synth``: a labelled synthetic plot as LAZ tiles, one printed path per tile."""

from pathlib import Path

import numpy as np
from click.testing import CliRunner

from pipeline.io import read_info
from pipeline.synth import SYNTH_CLASSES, synthetic_plot
from workflows.cli.main import main


def silva(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_synth_writes_the_tiles_and_prints_their_paths(tmp_path):
    out = tmp_path / "plot"
    result = silva("synth", out, "--seed", 3, "--size", 10, "--tile-size", 5)
    assert result.exit_code == 0, result.output
    printed = result.stdout.splitlines()
    assert printed == [str(out / f"plot_s3_{ix}_{iy}.laz") for ix in range(2) for iy in range(2)]
    assert sorted(out.glob("*.laz")) == sorted(Path(p) for p in printed)
    _, labels = synthetic_plot(3, 10.0)
    infos = [read_info(p) for p in printed]
    assert sum(info.n_points for info in infos) == len(labels)
    assert all(info.version == "1.4" and info.crs_wkt for info in infos)
    assert set(np.unique(labels)) == set(SYNTH_CLASSES.values())


def test_synth_default_tiling_and_seed(tmp_path):
    # 12 m is smaller than the default 15 m tile: one tile, seed 0.
    result = silva("synth", tmp_path, "--size", 12)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [str(tmp_path / "plot_s0_0_0.laz")]


def test_synth_bad_size_is_one_error_line(tmp_path):
    result = silva("synth", tmp_path / "plot", "--size", -3)
    assert result.exit_code == 1
    assert result.output.startswith("silva: error: size")
    assert "Traceback" not in result.output
    assert not (tmp_path / "plot").exists()


def test_synth_writes_a_real_stand_on_request(tmp_path):
    """--stand real: suppressed trees and touching crowns make more trees than the plain
    plot of the same seed; the plain stand is the default."""
    import csv

    def trees(*extra):
        out = tmp_path / "-".join(("plot", *extra))
        result = silva("synth", out, "--seed", 4, "--size", 20, *extra)
        assert result.exit_code == 0, result.output
        with open(out / "trees.csv", newline="") as f:
            return list(csv.DictReader(f))

    plain, real = trees(), trees("--stand", "real")
    assert trees("--stand", "plain") == plain
    assert len(real) > len(plain)
    refused = silva("synth", tmp_path / "x", "--stand", "dense")
    assert refused.exit_code != 0 and "--stand" in refused.output


def test_synth_writes_a_hillside_on_request(tmp_path):
    """--slope 40: the plot's ground rises about 0.84 m a metre (its terrain points span
    far more height than the plain plot's); --ridge folds it; a slope beyond 60 degrees is
    one error line."""
    from pipeline.io import read_points

    def terrain_span(*extra):
        out = tmp_path / "-".join(("plot", *extra))
        result = silva("synth", out, "--seed", 4, "--size", 10, "--tile-size", 10, *extra)
        assert result.exit_code == 0, result.output
        points = read_points(next(out.glob("*.laz")))
        z = points.xyz[points.fields["classification"] == SYNTH_CLASSES["terrain"], 2]
        return np.ptp(z)

    plain, hill, ridge = terrain_span(), terrain_span("--slope", "40"), terrain_span(
        "--slope", "40", "--ridge")
    assert plain < 3.0 and hill > 6.0 and 2.5 < ridge < hill
    refused = silva("synth", tmp_path / "x", "--slope", "70")
    assert refused.exit_code == 1 and refused.output.startswith("silva: error: stand.slope")


def test_synth_places_a_plot_at_the_origin_asked(tmp_path):
    """--origin X Y Z moves the plot (its points, not their arrangement) so that plots
    written apart lie side by side in one scene."""
    from pipeline.io import read_points

    def xyz(*extra):
        out = tmp_path / "-".join(("plot", *extra))
        assert silva("synth", out, "--seed", 2, "--size", 6, "--tile-size", 6,
                     *extra).exit_code == 0
        return read_points(next(out.glob("*.laz"))).xyz

    plain, moved = xyz(), xyz("--origin", "500100", "5500000", "410")
    assert np.allclose(moved - plain, [100.0, 0.0, 10.0], atol=2e-3)
