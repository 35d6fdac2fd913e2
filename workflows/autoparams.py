"""The values a configuration leaves to the data ('auto') or to the model it applies,
resolved once as a run starts.

``features.r1: auto`` comes from the point density of the training tiles' headers (or, when
a saved model is applied, from the model: its forests know only the radius they were
trained with); ``features.voxel: auto`` from r1 and ``features.max_neighbors``. The run
then holds an ordinary, fully resolved configuration: saved in OUT/config.yaml, hashed by the
fingerprints, shown by the report.
"""

import logging

from pipeline.features.sets import auto_radius, auto_voxel
from pipeline.io import read_info
from pipeline.model import read_description
from pipeline.tiling import tile_area
from workflows.config import SilvaConfig, validate_config
from workflows.inputs import expand_inputs

log = logging.getLogger(__name__)


def header_density(cfg: SilvaConfig) -> float:
    """Points per m² (XY) of the training tiles (of all tiles without training tiles), from
    their headers: the sum of points over the sum of the tiles' XY boxes."""
    scenes = ["train"] if cfg.data.train else ["test", "predict"]
    points, area = 0, 0.0
    for scene in scenes:
        for path in expand_inputs(list(getattr(cfg.data, scene)), key=f"data.{scene}"):
            info = read_info(path)
            points += int(info.n_points)
            area += tile_area(info.mins, info.maxs)
    return points / area if area else 0.0


def resolve_auto(cfg: SilvaConfig, model_dir=None) -> SilvaConfig:
    """``cfg`` with ``features.r1`` and ``features.voxel`` as numbers, and, when a model is
    applied and ``data.classes`` is empty, the model's classes (each with its output code)."""
    features = cfg.features
    takes_classes = model_dir is not None and not cfg.data.classes
    if features.resolved and not takes_classes:
        return cfg
    trained = read_description(model_dir) if model_dir is not None else {}
    raw = cfg.model_dump(mode="json")
    if takes_classes:
        raw["data"]["classes"] = {c["name"]: [c["code"]] for c in trained["classes"]}
    r1 = features.r1
    if r1 == "auto":
        if "features.r1" in trained:
            r1 = trained["features.r1"]
        else:
            density = header_density(cfg)
            r1 = auto_radius(density) if density > 0 else 0.5
            log.info("features.r1 auto: %.3g points/m² in the headers -> r1 = %g m", density, r1)
    voxel = features.voxel
    if voxel == "auto":
        voxel = trained.get("features.voxel") or auto_voxel(float(r1), int(features.max_neighbors))
    raw["features"].update(r1=r1, voxel=voxel)
    return validate_config(raw)
