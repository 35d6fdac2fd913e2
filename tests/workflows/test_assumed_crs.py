"""A tile without a CRS beside tiles with one: taken in their CRS, with a warning naming it,
and its rasters and trees written in it."""

import logging

import laspy

from pipeline.io import read_info
from pipeline.io.crs import crs_name
from tests.workflows.conftest import silva, write_config
from workflows.run.autoparams import run_config
from workflows.run.directory import Run
from workflows.steps.ingest import plan_tiles
from workflows.steps.table import STEPS


def _survey(tiny_survey, root):
    """The tiny survey's tiles (in the synthetic plots' CRS), the first of each scene
    without a CRS."""
    dirs = {}
    for scene in ("train", "test"):
        dirs[scene] = root / scene
        dirs[scene].mkdir(parents=True)
        for i, path in enumerate(sorted(tiny_survey[scene].glob("*.laz"))):
            las = laspy.read(path)
            if i == 0:
                header = laspy.LasHeader(point_format=las.header.point_format,
                                         version=las.header.version)
                header.scales, header.offsets = las.header.scales, las.header.offsets
                bare = laspy.LasData(header)
                bare.points = las.points
                las = bare
            las.write(dirs[scene] / path.name)
    return dirs


def test_a_tile_without_crs_is_taken_in_its_scenes_crs_saying_so(tiny_survey, tmp_path,
                                                                  caplog):
    survey = _survey(tiny_survey, tmp_path)
    bare, other = sorted(survey["train"].glob("*.laz"))[:2]
    assert read_info(bare).crs_wkt is None
    crs = read_info(other).crs_wkt
    config = write_config(tmp_path / "c.yaml", survey)
    with caplog.at_level(logging.WARNING):
        run = Run(run_config(config), tmp_path / "out", steps=STEPS)  # headers read: said then
        tiles = plan_tiles(run)
        assert all(t.crs_wkt == crs for t in tiles)
        plan_tiles(run)  # ingest plans the tiles again: said once
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 2, warnings  # one tile a scene
    assert warnings[0].startswith(f"tile {bare} of data.train records no CRS, beside tiles in "
                                  f"{crs_name(crs)} (")
    assert (f"it is taken as {crs_name(crs)}, and its rasters and trees are written in it"
            in warnings[0])


def test_silva_plan_shows_the_assumed_crs(tiny_survey, tmp_path, caplog):
    config = write_config(tmp_path / "c.yaml", _survey(tiny_survey, tmp_path))
    with caplog.at_level(logging.WARNING):
        result = silva("plan", config)
    assert result.exit_code == 0, result.output
    assert sum("records no CRS, beside tiles in " in r.getMessage()
               for r in caplog.records) == 2
