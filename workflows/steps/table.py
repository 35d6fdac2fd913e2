"""The steps of a run, declared once: :data:`STEPS`, read by the run's loop
(:func:`workflows.run.loop.execute`), its progress and ETA (:mod:`workflows.run.progress`,
:func:`workflows.cli.plan.step_weights`), the fingerprints (:meth:`StepTable.fingerprint
<workflows.run.step_table.StepTable.fingerprint>`), the checks before a run starts
(:func:`workflows.cli.commands.check_before_start`) and the per-step commands
(:data:`workflows.cli.commands.STEP_COMMANDS`). The commands hand it to the run; the run's
floor never imports it.

Each row (:class:`~workflows.run.step_table.Step`) gives its name, the function that runs
it, what it needs from the steps before it and what it sets for those after it, its check
before the cluster starts, what its fingerprint hashes, its weight in the run's progress
and, for a step with its own ``silva`` command, the command's help. This module stays as
light as the command line that reads it: the step functions (:mod:`workflows.steps.flow`)
import their work when they run.

Adding a step (for example ``trees``, per scene after the cascade, before the export):

1. write its work in its own module and its function in :mod:`workflows.steps.flow`; it
   takes the run's state (:class:`workflows.steps.state.StepState`), reads what its
   ``needs`` name there, sets what its ``sets`` name and times its work under its name::

       def trees_step(state):
           from workflows.steps.trees import trees

           state.trees = state.timed("trees", trees, state.run, state.engine, ...)

   ``state.run.fingerprint("trees")`` in its work is its fingerprint: its parts and the
   inputs' digest.

2. add one row to :data:`STEPS`, at its place in the run (here after ``train``)::

       Step("trees", trees_step, needs=("layout", "stages"), sets=("trees",),
            check=check_trees, fingerprint=Fingerprint({"trees": _trees_part}, after="stage"),
            weight=Weight(0.05, other=0.1), per_chunk=False, when="output.trees",
            command="Find the trees of every scene (after train)."
            + examples("silva trees survey.yaml --out results/")),

   and what it sets (``trees``) to :class:`~workflows.steps.state.StepState`;

3. and its configuration section to the schema (:mod:`workflows.config.schema`).

The loop then runs it (``silva run`` and every command after it), ``silva trees`` exists,
the progress shows its line and weighs it (``share`` before a plan, else its estimated
seconds), ``check`` refuses a mistake before the cluster starts, and
``run.fingerprint("trees")`` hashes what the fingerprint it builds on (``after``) hashes and
its own parts: rules of their own or configuration paths as written (``"trees"``: the whole
section, ``"output.trees"``: one key). A step without ``command`` has no command and no line
in the progress (its tasks count in the progress of the step they run in); a step with
``per_chunk=False`` is left out of a ``--chunk`` run; ``needs`` are checked before it runs.

The fingerprints hash:

==========  ========================================================================
step        hashed keys (each step includes the rows above it, except evaluate,
            export and trees, which each build on stage)
==========  ========================================================================
ingest      data.train/test/predict (patterns, order ignored), data.label_field,
            data.classes, data.ignore, data.split, data.drop_unlisted,
            data.exclude_codes and data.exclude_withheld (when set);
            data.densities with cascade.seed, which seeds the copies (when set);
            tiling.chunk_size, tiling.halo, tiling.target_points and tiling.layout
            (only with chunk_size auto), output.keep_features (unless auto: it
            chooses each scene's halo), features.echoes (when set: ingest then
            stores each point's return numbers)
terrain     + terrain.*
features    + features.set, r1, max_neighbors, plane, scales, column, cell, voxel
stage       + features.r2, features.context_max_neighbors, every cascade key except
            cascade.stages (adding stages keeps the finished ones when tiling.halo
            is set; unset, it grows with the stages, see below)
trees       stage + trees.* and output.canopy_classes (with output.trees)
export      stage + output.* (except output.keep_store and output.keep_features),
            + trees.* and output.canopy_classes with output.trees
evaluate    stage + data.background
==========  ========================================================================

Never hashed: cluster.*, tiling.read_batch (they change how, not what, is computed).
The halo is hashed resolved, so with ``tiling.halo`` unset, changing ``features.r1``
(or ``cascade.stages``, which the default halo reaches across) also changes the halo
and thus ``ingest``. With ``chunk_size: auto`` the size ingest resolves also depends on the
tiles' headers, which the run's inputs digest covers. Globs are hashed as written, not the
files they match.
"""

from workflows.run.step_table import Fingerprint, Step, StepTable, Weight, examples
from workflows.steps.flow import (
    cascade_step,
    check_export,
    check_trees,
    evaluate_step,
    export_step,
    features_step,
    ingest_step,
    report_step,
    survey_step,
    terrain_step,
    trees_step,
)
from workflows.steps.state import StepState

#: The keys of the features section that change the features (r2 and the context cap change
#: only the cascade's context).
FEATURE_KEYS = ("set", "r1", "max_neighbors", "plane", "scales", "column", "cell", "voxel",
                "version")


def _ingest_part(cfg, d: dict) -> dict:
    from workflows.config.inputs import SCENES  # the configuration: loaded by then

    data = d["data"]
    part = {
        **{scene: sorted(set(data[scene])) for scene in SCENES},
        **{k: data[k] for k in ("label_field", "ignore", "split", "drop_unlisted")},
        # a list of pairs: the class order is the class index (sort_keys would lose it)
        "classes": [[name, codes] for name, codes in data["classes"].items()],
        "chunk_size": cfg.tiling.chunk_size,
        "halo": cfg.halo,
    }
    if cfg.output.keep_features != "auto":
        # it chooses each scene's halo; only when set, so the default keeps its fingerprint
        part["keep_features"] = cfg.output.keep_features
    for key in ("exclude_codes", "exclude_withheld"):
        if data[key]:  # only when set: a config without filters keeps its fingerprint
            part[key] = sorted(set(data[key])) if key == "exclude_codes" else True
    if cfg.features.echoes:
        # the store then holds the return numbers; only when set, so a run without echoes
        # keeps its fingerprint (and the features step, built on it, its own)
        part["echoes"] = True
    if data["densities"]:  # only when set: a config without copies keeps its fingerprint
        part["densities"] = sorted(set(data["densities"]))
        part["thinning_seed"] = cfg.cascade.seed
    if cfg.tiling.chunk_size == "auto":
        # only then does it matter; an explicit size keeps the fingerprint it always had
        part["target_points"] = cfg.tiling.target_points
        part["layout"] = cfg.tiling.layout
    return part


def _terrain_part(cfg, d: dict) -> dict:
    """The terrain section, and the version of the code that makes the DTM: a store made by
    another version redoes its terrain, and every step built on it, when resumed."""
    from pipeline.terrain.version import TERRAIN_VERSION

    return {**d["terrain"], "version": TERRAIN_VERSION}


def _trees_part(cfg, d: dict) -> dict | None:
    """The trees, with the classes their crowns grow on; nothing when none are found."""
    return ({**d["trees"], "canopy_classes": d["output"]["canopy_classes"]}
            if cfg.output.trees else None)


def _output_part(cfg, d: dict) -> dict:
    """What is written; what the store keeps does not change it."""
    return {k: v for k, v in d["output"].items()
            if k not in ("keep_store", "keep_features", "trees")}


STEPS = StepTable(
    Step("ingest", ingest_step, sets=("layout",),
         fingerprint=Fingerprint({"ingest": _ingest_part}), weight=Weight(0.1, other=0.3),
         command="Stream the input tiles of CONFIG into chunks with halos (store.zarr)."
         + examples("silva ingest survey.yaml --out results/")),
    Step("terrain", terrain_step, needs=("layout",),
         fingerprint=Fingerprint({"terrain": _terrain_part}, after="ingest")),
    Step("features", features_step, needs=("layout",), sets=("staged", "one_pass", "counts"),
         fingerprint=Fingerprint(
             {"features": lambda cfg, d: {k: d["features"][k] for k in FEATURE_KEYS}},
             after="terrain"),
         weight=Weight(0.6, features=1.0),
         command="Compute the moment invariants of every chunk (after ingest)." + examples(
             "silva features survey.yaml --out results/",
             "silva features survey.yaml --out results/ --chunk test/0_0")),
    Step("train", cascade_step, needs=("layout", "counts", "staged", "one_pass"),
         sets=("stages",),
         fingerprint=Fingerprint(
             {"context": lambda cfg, d: {
                 "r2": cfg.features.radius2,
                 "context_max_neighbors": cfg.features.context_max_neighbors},
              "cascade": lambda cfg, d: {k: v for k, v in d["cascade"].items()
                                         if k != "stages"}},
             after="features", name="stage"),
         weight=Weight(0.2, training=1.0, other=0.4), per_stage=True,
         applying=("apply", Weight(0.2, other=0.4)),
         command="Train the cascade and predict every stage (after features); saves "
                 "OUT/model." + examples("silva train survey.yaml --out results/")),
    Step("trees", trees_step, needs=("layout", "stages"), sets=("trees",), check=check_trees,
         fingerprint=Fingerprint({"trees": _trees_part}, after="stage"),
         weight=Weight(0.03, other=0.1), per_chunk=False, when="output.trees",
         command="Find the trees of every scene (after train; with output.trees): "
                 "PredictedTreeID per point, trees/<tile>.csv and .gpkg." + examples(
                     "silva trees survey.yaml --out results/ --set output.trees=true")),
    Step("survey", survey_step, needs=("layout", "stages"), sets=("drawn",),
         per_chunk=False),
    Step("export", export_step, needs=("layout", "stages"), check=check_export,
         fingerprint=Fingerprint({"output": _output_part, "trees": _trees_part},
                                 after="stage"),
         weight=Weight(0.04, other=0.2), per_chunk=False,
         command="Write predictions/<tile>.laz for every input tile (after train)."
         + examples("silva export survey.yaml --out results/ --set output.format=las")),
    Step("evaluate", evaluate_step, needs=("layout", "stages"), sets=("metrics", "plots"),
         fingerprint=Fingerprint({"background": lambda cfg, d: d["data"]["background"]},
                                 after="stage"),
         weight=Weight(0.02, other=0.05), per_chunk=False,
         command="Write metrics.json for the test points (after export)."
         + examples("silva evaluate survey.yaml --out results/")),
    Step("report", report_step, needs=("layout", "stages"),
         weight=Weight(0.04, other=0.05), per_chunk=False,
         command="Write report.html with its plots (after evaluate)."
         + examples("silva report survey.yaml --out results/")),
    state=StepState,
)
