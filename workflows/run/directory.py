"""One run: its configuration, output directory layout, store and class table.

The output directory of a run::

    OUT/
      config.yaml        the resolved configuration
      store.zarr/        chunks; features, per-stage context and probabilities of the scenes
                         trained on; the results of scenes classified in one pass
      model/             model.json + one forest per stage (loadable by 'silva predict')
      work/              out-of-fold forests and other intermediate files
      predictions/       <input tile name>.laz, every input point with its prediction
      metrics.json       test-set metrics, written last, only by a complete evaluation
      report.html        the report with its plots
      work/results.json  what metrics and report were made from (see forget_stale_results)
"""

import hashlib
import json
import logging
import os
import shlex
import shutil
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

from pipeline.atomic import atomic_write_text, remove_parts
from pipeline.cascade import CascadeParams
from pipeline.errors import ConfigError, SilvaError
from pipeline.features.sets import FeatureParams
from pipeline.store import open_store
from pipeline.terrain import TerrainParams
from workflows.config import SilvaConfig, dump_config
from workflows.run.lock import LOCK_NAME, acquire, check_free
from workflows.run.plan import AppliedModel, RunPlan, config_inputs, feature_description
from workflows.run.step_table import StepTable

log = logging.getLogger(__name__)


def has_test_points(scenes, split) -> bool:
    """Whether a run of ``scenes`` (their names) holds labelled test points: a test scene,
    or a train scene split in two."""
    return "test" in scenes or ("train" in scenes and split is not None)


@dataclass
class Run:
    """The paths and the store of one run, its plan (:class:`RunPlan`: built once by
    :func:`workflows.run.autoparams.resolve_run`), which everything it computes follows, and
    its table of steps (``steps``, which the commands give: the loop runs its rows, and the
    fingerprints hash what they name; None: a run that computes no fingerprint)."""

    plan: RunPlan
    out: Path
    quiet: bool = False
    steps: StepTable | None = None
    _store: object = field(default=None, repr=False)

    @property
    def cfg(self) -> SilvaConfig:
        """The resolved configuration."""
        return self.plan.cfg

    @property
    def model(self) -> AppliedModel | None:
        """The saved model the run applies, read and checked (None: it trains its own)."""
        return self.plan.model

    @property
    def model_dir(self) -> Path | None:
        return None if self.plan.model is None else self.plan.model.path

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

    def rerun(self, verb: str, *options: str) -> str:
        """The command that runs ``silva VERB`` on this run's output directory with
        ``options`` (:func:`rerun_command`; ``silva predict`` with the model it applies)."""
        if verb == "predict" and self.model_dir is not None:
            options = ("--model", str(self.model_dir), *options)
        return rerun_command(self.out, verb, *options)

    @property
    def store(self):
        if self._store is None:
            self.out.mkdir(parents=True, exist_ok=True)
            self._store = open_store(self.store_path)
        return self._store

    # -- derived configuration ------------------------------------------------------------
    @cached_property
    def features(self) -> FeatureParams:
        """The resolved feature and context parameters (with the terrain model's): built
        and validated once, as the plan they follow is."""
        return replace(self.cfg.features.params, terrain=self.terrain)

    @property
    def terrain(self) -> TerrainParams:
        """The resolved parameters of each scene's terrain model."""
        return self.cfg.terrain.params

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
        return self.cfg.halo

    @property
    def n_stages(self) -> int:
        return self.plan.n_stages

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

    @property
    def table(self) -> StepTable:
        """The run's table of steps (:attr:`steps`), which it was given."""
        if self.steps is None:
            raise RuntimeError("this run was given no table of steps (Run(..., steps=)): "
                               "it computes no fingerprint and runs no step")
        return self.steps

    def fingerprint(self, step: str) -> str:
        """Fingerprint of a step: its configuration and the input files it reads."""
        config = self.table.fingerprint(self.cfg, step)
        digest = hashlib.sha256(f"{config}|{self.plan.inputs_digest}".encode())
        return digest.hexdigest()[:16]

    def stage_fingerprint(self, stage: int) -> str:
        """Fingerprint of cascade stage ``stage`` (0-based): its config and its stage number."""
        return f"{self.fingerprint('stage')}-{stage + 1}"

    def feature_description(self) -> dict:
        """What a model must agree with to be applied to this run's features."""
        return feature_description(self.cfg)

    # -- housekeeping ---------------------------------------------------------------------
    def save_config(self) -> str:
        """Write OUT/config.yaml (the resolved configuration) and return its text."""
        text = dump_config(self.cfg)
        atomic_write_text(self.out / "config.yaml", text)
        return text

    @property
    def stamp_path(self) -> Path:
        return self.work_path / "results.json"

    def results_stamp(self) -> str:
        """A digest of everything metrics and report follow from: the configuration of
        every step, the number of stages, the input files (paths, sizes, modification times)
        and the description of the applied model."""
        inputs = [[f.scene, str(f.path), f.size, f.mtime_ns] for f in self.plan.inputs]
        model = None if self.model is None else self.model.digest
        steps = self.table
        state = {"steps": [steps.fingerprint(self.cfg, name) for name in steps.fingerprinted],
                 "stages": self.cfg.cascade.stages, "inputs": inputs, "model": model}
        return hashlib.sha256(json.dumps(state).encode()).hexdigest()[:16]

    def drop_results(self) -> None:
        """Remove metrics and report: what they were made from is gone or damaged."""
        for path in (self.metrics_path, self.report_path):
            path.unlink(missing_ok=True)

    def forget_stale_results(self) -> str:
        """Remove metrics and report unless they were made from what this run would make
        them from (:meth:`results_stamp`); record the new stamp and return it.

        A rerun that changes nothing (``silva ingest``, ``--chunk`` on a finished run)
        keeps them; any change removes them before a step writes anything, so a killed run
        never leaves metrics of another configuration beside its store. The rest of the run
        rewrites them when it gets that far.
        """
        stamp = self.results_stamp()
        try:
            recorded = json.loads(self.stamp_path.read_text()).get("stamp")
        except (OSError, ValueError, AttributeError):
            recorded = None
        if recorded != stamp:
            self.drop_results()
            self.work_path.mkdir(parents=True, exist_ok=True)
            atomic_write_text(self.stamp_path, json.dumps({"stamp": stamp}))
        return stamp


class OutputError(SilvaError, OSError):
    """The output directory cannot be created or written."""


def rerun_command(out, verb: str, *options: str) -> str:
    """The command that runs ``silva VERB`` on the output directory ``out`` with
    ``options``: with the configuration every command saves there (OUT/config.yaml), so that
    it fits whatever command started the run, a 'silva predict' without a configuration
    too (a later command on its output applies the same model)."""
    out = Path(out)
    return shlex.join(["silva", verb, str(out / "config.yaml"), "--out", str(out), *options])


def prepare_output(out: Path, *, overwrite: bool, keep=(), command: str = "silva"):
    """Create the output directory and take its lock (returned, a context manager that
    releases it); with ``overwrite`` empty it first, keeping the lock and every path of
    ``keep`` inside it (what the command is about to read: its config, model, inputs).

    Raises :class:`LockedError` when another run holds the directory, and
    :class:`OutputError` (one line) when the system refuses to create or write it.
    """
    out = Path(out)
    try:
        if out.exists() and not out.is_dir():
            raise OutputError(f"--out {out} is a file, not a directory; choose another --out")
        for path in (out, *out.parents):  # mkdir would only say "File exists"
            if path.is_symlink() and not path.exists():
                raise OutputError(f"--out {out}: {path} is a broken symbolic link (to "
                                  f"{os.readlink(path)}); remove it or choose another --out")
        for parent in out.parents:
            if parent.exists():
                if not parent.is_dir():
                    raise OutputError(f"--out {out} lies below {parent}, which is a file, "
                                      "not a directory; choose another --out")
                break
        if overwrite and out.exists():
            if not (out / "store.zarr").exists() and any(
                    p.name != LOCK_NAME for p in out.iterdir()):
                raise ConfigError(
                    f"--overwrite refuses to empty {out}: it does not look like a Silva output "
                    "directory (no store.zarr); choose another --out"
                )
        check_free(out)
        out.mkdir(parents=True, exist_ok=True)
        lock = acquire(out, command)
        try:
            if overwrite:
                _empty(out, [out / LOCK_NAME, *keep])
            for directory in (out, out / "model", out / "predictions", out / "plots"):
                remove_parts(directory)  # what a killed writer left
        except BaseException:
            lock.release()
            raise
        return lock
    except OSError as err:
        if isinstance(err, SilvaError):
            raise
        raise OutputError(f"cannot prepare the output directory {out}: "
                          f"{os_reason(err)}; choose another --out") from None


def os_reason(err: OSError) -> str:
    """An OS error as a short phrase: what failed on which file."""
    reason = err.strerror or type(err).__name__
    return f"{reason} ({err.filename})" if err.filename else reason


def _empty(directory: Path, keep) -> None:
    """Remove everything in ``directory`` except the paths of ``keep`` (and the
    directories on the way to them). Symbolic links are removed, never followed."""
    kept = {Path(f(p)) for p in keep for f in (os.path.abspath, os.path.realpath)}
    for entry in directory.iterdir():
        path = Path(os.path.realpath(entry.parent)) / entry.name  # the entry, not its target
        if path in kept:
            log.info("--overwrite keeps %s: this command reads it", entry)
            continue
        if entry.is_dir() and not entry.is_symlink():
            if any(path in k.parents for k in kept):
                _empty(entry, keep)
            else:
                shutil.rmtree(entry)
        else:
            entry.unlink()


#: The model a 'silva predict' output directory applies: later commands on it (silva report,
#: export, status) apply it too.
APPLIED_MODEL = Path("work") / "applied-model.txt"


def record_applied_model(out: Path, model_dir: Path) -> None:
    atomic_write_text(out / APPLIED_MODEL, str(Path(model_dir).resolve()))


def applied_model(out: Path) -> Path | None:
    """The model the output directory ``out`` applies (None: it trains its own)."""
    try:
        return Path((out / APPLIED_MODEL).read_text().strip())
    except OSError:
        return None


def read_paths(cfg: SilvaConfig, config_path, model_dir, inputs=None) -> list[Path]:
    """Every file or directory a command with ``cfg`` reads: its config file, the model it
    applies and the input tiles (``inputs`` when found already, else found now). Raises the
    errors of :func:`~workflows.config.inputs.expand_inputs`."""
    paths = ([Path(config_path)] if config_path is not None else []) + (
        [Path(model_dir)] if model_dir is not None else [])
    return paths + [f.path for f in (config_inputs(cfg) if inputs is None else inputs)]
