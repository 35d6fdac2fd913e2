"""One run: its configuration, output directory layout, store and class table.

The output directory of a run::

    OUT/
      config.yaml        the resolved configuration
      store.zarr/        chunks, features, per-stage context and probabilities
      model/             model.json + one forest per stage (loadable by 'silva predict')
      work/              out-of-fold forests and other intermediate files
      predictions/       <input tile name>.laz, every input point with its prediction
      metrics.json       test-set metrics, written last, only by a complete evaluation
      report.html        the report with its plots
"""

import hashlib
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.atomic import atomic_write_text
from pipeline.cascade import CascadeParams
from pipeline.errors import ConfigError
from pipeline.features.sets import FeatureParams, feature_set
from pipeline.store import open_store
from workflows.config import SilvaConfig, dump_config, fingerprint

SCENES = ("train", "test", "predict")


def has_test_points(layout: dict, split) -> bool:
    """Whether a run holds labelled test points: a test scene, or a train scene split in two."""
    return "test" in layout["scenes"] or ("train" in layout["scenes"] and split is not None)


@dataclass
class Run:
    """Everything the steps of one run share."""

    cfg: SilvaConfig
    out: Path
    quiet: bool = False
    model_dir: Path | None = None  # a saved model to apply instead of training
    inputs_digest: str = ""  # the input files as ingest found them (paths, sizes, times)
    _store: object = field(default=None, repr=False)

    # -- layout ---------------------------------------------------------------------------
    @property
    def store_path(self) -> Path:
        return self.out / "store.zarr"

    @property
    def model_path(self) -> Path:
        return self.model_dir if self.model_dir is not None else self.out / "model"

    @property
    def work_path(self) -> Path:
        return self.out / "work"

    @property
    def predictions_path(self) -> Path:
        return self.out / "predictions"

    @property
    def metrics_path(self) -> Path:
        return self.out / "metrics.json"

    @property
    def report_path(self) -> Path:
        return self.out / "report.html"

    @property
    def store(self):
        if self._store is None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._store = open_store(self.store_path)
        return self._store

    # -- derived configuration ------------------------------------------------------------
    @property
    def features(self) -> FeatureParams:
        """The resolved feature and context parameters."""
        return self.cfg.features.params

    def cascade_params(self, n_jobs: int = 1) -> CascadeParams:
        """The resolved cascade parameters; ``n_jobs`` threads per forest fit."""
        return self.cfg.cascade.params(n_jobs)

    @property
    def r1(self) -> float:
        return self.features.r1

    @property
    def r2(self) -> float:
        return self.features.r2

    @property
    def halo(self) -> float:
        return float(self.cfg.halo)

    @property
    def classes(self) -> list[str]:
        """Class names the model learns and predicts (ignored classes removed), in order."""
        return self.cfg.data.class_names

    @property
    def class_codes(self) -> list[int]:
        """The output code of each class: the first of its source codes."""
        return self.cfg.data.class_codes

    @property
    def code_to_class(self) -> dict[int, int]:
        """Source label code -> class index; ignored codes and classes are absent."""
        return self.cfg.data.code_to_class

    @property
    def n_classes(self) -> int:
        return len(self.classes)

    def fingerprint(self, step: str) -> str:
        """Fingerprint of a step: its configuration and the input files it reads."""
        digest = hashlib.sha256(f"{fingerprint(self.cfg, step)}|{self.inputs_digest}".encode())
        return digest.hexdigest()[:16]

    def stage_fingerprint(self, stage: int) -> str:
        """Fingerprint of cascade stage ``stage`` (0-based): its config and its stage number."""
        return f"{self.fingerprint('stage')}-{stage + 1}"

    def feature_description(self) -> dict:
        """What a model must agree with to be applied to this run's features."""
        # keyed by config path, so a mismatch names the key to set
        params = self.features
        return {
            "features.set": params.set,
            "features.columns": list(feature_set(params).columns),
            "features.r1": params.r1,
            "features.r2": params.r2,
            "features.max_neighbors": params.max_neighbors,
            "features.context_max_neighbors": params.context_max_neighbors,
            "cascade.context": self.cfg.cascade.context,
        }

    # -- housekeeping ---------------------------------------------------------------------
    def save_config(self) -> str:
        """Write OUT/config.yaml (the resolved configuration) and return its text."""
        text = dump_config(self.cfg)
        atomic_write_text(self.out / "config.yaml", text)
        return text

    def forget_results(self) -> None:
        """Remove metrics and report: they are rewritten only when a run completes."""
        for path in (self.metrics_path, self.report_path):
            path.unlink(missing_ok=True)


def prepare_output(out: Path, *, overwrite: bool) -> None:
    """Create the output directory; with ``overwrite`` start from an empty one."""
    if overwrite and out.exists():
        if not (out / "store.zarr").exists() and any(out.iterdir()):
            raise ConfigError(
                f"--overwrite refuses to empty {out}: it does not look like a Silva output "
                "directory (no store.zarr); choose another --out"
            )
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
