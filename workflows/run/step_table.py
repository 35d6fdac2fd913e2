"""The steps of a run, declared once: :data:`STEPS`, read by the run's loop
(:func:`workflows.run.loop.execute`), its progress and ETA (:mod:`workflows.run.progress`,
:func:`workflows.cli.plan.step_weights`), the fingerprints
(:mod:`workflows.run.fingerprint`) and the per-step commands
(:data:`workflows.cli.commands.STEP_COMMANDS`).

Each :class:`Step` gives its name, the function that runs it (``"module:function"``,
imported only when the step runs, so that this table stays as light as the modules that
read it), what it needs from the steps before it, the configuration parts its fingerprint
hashes, its weight in the run's progress and, for a step with its own ``silva`` command,
the command's help.

Adding a step (for example ``trees``, per scene after the cascade, before the export):

1. write its function in its own module; it takes the run's state
   (:class:`workflows.run.state.RunState`), reads what its ``needs`` name there and times
   its work under its name::

       def trees_step(state):
           fingerprint = state.run.fingerprint("trees")  # its parts and the inputs' digest
           state.timed("trees", find_trees, state.run, state.engine, state.layout,
                       state.stages, fingerprint)

2. add one row to :data:`STEPS`, at its place in the run (here after ``train``)::

       Step("trees", "workflows.steps.trees:trees_step", needs=("layout", "stages"),
            fingerprint=(*CASCADE_PARTS, "trees", "output.trees"),
            weight=Weight(0.05, other=0.1), per_chunk=False,
            command="Find the trees of every scene (after train)."
            + examples("silva trees survey.yaml --out results/")),

The loop then runs it (``silva run`` and every command after it), ``silva trees`` exists,
the progress shows its line and weighs it (``share`` before a plan, else its estimated
seconds), and ``run.fingerprint("trees")`` hashes what it names: :data:`PARTS
<workflows.run.fingerprint.PARTS>` (rules of their own) and configuration paths as written
(``"trees"``: the whole section, ``"output.trees"``: one key; the configuration schema
declares them). A step without ``command`` has no command and no line in the progress (its
tasks count in the progress of the step they run in); a step with ``per_chunk=False`` is
left out of a ``--chunk`` run; ``needs`` are checked before it runs.
"""

from collections.abc import Mapping
from dataclasses import dataclass
from pkgutil import resolve_name


@dataclass(frozen=True)
class Weight:
    """A step's share of a run's time: ``share`` before anything is known (the demo and the
    benchmarks), else a sum of the run's estimated seconds
    (:func:`workflows.cli.plan.estimated_seconds`): of the features, the forests' training and
    the other chunk work, each times its factor."""

    share: float = 0.0
    features: float = 0.0
    training: float = 0.0
    other: float = 0.0

    def seconds(self, spent: Mapping[str, float]) -> float:
        return (self.features * spent["features"] + self.training * spent["training"]
                + self.other * spent["other"])


@dataclass(frozen=True)
class Step:
    """One step of a run (see the module's docstring for how a step is added).

    ``function``: ``"module:function"`` taking the run's state. ``needs``: the state's
    attributes the steps before it set and it reads. ``fingerprint``: the configuration parts
    its fingerprint hashes (empty: it has none; ``fingerprint_name`` names it when the step's
    name does not). ``weight``: its share in the progress. ``per_chunk``: a ``--chunk`` run
    (one chunk, in this process) runs it. ``per_stage``: its tasks run once per cascade
    stage (``predict-3``: stage 3 in its progress). ``command``: the help of its ``silva`` command,
    which runs every step up to it (None: no command, no line of its own in the progress).
    ``applying``: its name and weight in a run that applies a saved model. ``when``: a
    configuration path (``"output.trees"``) without whose true value the step is not part
    of the run (no work, no line in the progress).
    """

    name: str
    function: str
    needs: tuple[str, ...] = ()
    fingerprint: tuple[str, ...] = ()
    fingerprint_name: str | None = None
    weight: Weight = Weight()
    per_chunk: bool = True
    per_stage: bool = False
    command: str | None = None
    applying: tuple[str, Weight] | None = None
    when: str | None = None

    def active(self, cfg) -> bool:
        """Whether the step is part of a run with the configuration ``cfg`` (None: every
        step that may be)."""
        if self.when is None or cfg is None:
            return True
        value = cfg
        for key in self.when.split("."):
            value = getattr(value, key)
        return bool(value)

    def run(self, state) -> None:
        resolve_name(self.function)(state)

    def shown_name(self, applies_model: bool) -> str:
        """The step's name in the progress (and in the timings)."""
        return self.applying[0] if applies_model and self.applying else self.name


def examples(*lines: str) -> str:
    """A help text's example invocations: a paragraph click keeps line by line."""
    return "\n\n\b\nExamples:\n" + "\n".join(f"  {line}" for line in lines)


INGEST_PARTS = ("ingest",)
TERRAIN_PARTS = (*INGEST_PARTS, "terrain")
FEATURE_PARTS = (*TERRAIN_PARTS, "features")
#: what a cascade stage follows from; the steps after the cascade build on it
CASCADE_PARTS = (*FEATURE_PARTS, "context", "cascade")

STEPS: tuple[Step, ...] = (
    Step("ingest", "workflows.steps.flow:ingest_step", fingerprint=INGEST_PARTS,
         weight=Weight(0.1, other=0.3),
         command="Stream the input tiles of CONFIG into chunks with halos (store.zarr)."
         + examples("silva ingest survey.yaml --out results/")),
    Step("terrain", "workflows.steps.flow:terrain_step", needs=("layout",),
         fingerprint=TERRAIN_PARTS),
    Step("features", "workflows.steps.flow:features_step", needs=("layout",),
         fingerprint=FEATURE_PARTS, weight=Weight(0.6, features=1.0),
         command="Compute the moment invariants of every chunk (after ingest)." + examples(
             "silva features survey.yaml --out results/",
             "silva features survey.yaml --out results/ --chunk test/0_0")),
    Step("train", "workflows.steps.flow:cascade_step", needs=("layout", "counts"),
         fingerprint=CASCADE_PARTS, fingerprint_name="stage",
         weight=Weight(0.2, training=1.0, other=0.4), per_stage=True,
         applying=("apply", Weight(0.2, other=0.4)),
         command="Train the cascade and predict every stage (after features); saves "
                 "OUT/model." + examples("silva train survey.yaml --out results/")),
    Step("trees", "workflows.steps.flow:trees_step", needs=("layout", "stages"),
         fingerprint=(*CASCADE_PARTS, "trees"), weight=Weight(0.03, other=0.1),
         per_chunk=False, when="output.trees",
         command="Find the trees of every scene (after train; with output.trees): "
                 "PredictedTreeID per point, trees/<tile>.csv and .gpkg." + examples(
                     "silva trees survey.yaml --out results/ --set output.trees=true")),
    Step("survey", "workflows.steps.flow:survey_step", needs=("layout", "stages"),
         per_chunk=False),
    Step("export", "workflows.steps.flow:export_step", needs=("layout", "stages"),
         fingerprint=(*CASCADE_PARTS, "output", "trees"), weight=Weight(0.04, other=0.2),
         per_chunk=False,
         command="Write predictions/<tile>.laz for every input tile (after train)."
         + examples("silva export survey.yaml --out results/ --set output.format=las")),
    Step("evaluate", "workflows.steps.flow:evaluate_step", needs=("layout", "stages"),
         fingerprint=(*CASCADE_PARTS, "background"), weight=Weight(0.02, other=0.05),
         per_chunk=False,
         command="Write metrics.json for the test points (after export)."
         + examples("silva evaluate survey.yaml --out results/")),
    Step("report", "workflows.steps.flow:report_step", needs=("layout", "stages"),
         weight=Weight(0.04, other=0.05), per_chunk=False,
         command="Write report.html with its plots (after evaluate)."
         + examples("silva report survey.yaml --out results/")),
)

BY_NAME = {step.name: step for step in STEPS}
#: The steps that are commands (targets: a command runs every step up to its own), in order.
TARGETS = tuple(step.name for step in STEPS if step.command is not None)
#: The fingerprinted steps, by the name of their fingerprint.
FINGERPRINTED = {step.fingerprint_name or step.name: step for step in STEPS if step.fingerprint}


def steps_until(target: str, cfg=None) -> tuple[Step, ...]:
    """The steps a run up to ``target`` (one of :data:`TARGETS`) runs, in order: with ``cfg``
    only those its configuration asks for (:meth:`Step.active`)."""
    until = STEPS[: STEPS.index(BY_NAME[target]) + 1]
    return tuple(step for step in until if step.active(cfg))


def progress_steps(target: str, applies_model: bool = False, cfg=None) -> list[str]:
    """The steps with a line in the progress of a run up to ``target`` (with ``cfg``: of
    the steps its configuration asks for)."""
    return [step.shown_name(applies_model) for step in steps_until(target, cfg)
            if step.command is not None]


def step_weights(spent: Mapping[str, float] | None = None) -> dict[str, float]:
    """Each shown step's weight in a run's progress, under its name and, for a step named
    otherwise when a model is applied, that name too: the typical shares, or with ``spent``
    (:func:`workflows.cli.plan.estimated_seconds`) its estimated seconds."""
    weights = {}
    for step in STEPS:
        if step.command is None:
            continue
        for name, weight in ((step.name, step.weight), *filter(None, [step.applying])):
            weights[name] = weight.share if spent is None else weight.seconds(spent)
    return weights


def per_stage_names() -> set[str]:
    """The progress names of the steps whose tasks run once per cascade stage."""
    return {name for step in STEPS if step.per_stage
            for name in (step.name, *(step.applying[:1] if step.applying else ()))}
