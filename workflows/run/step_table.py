"""What a table of steps is: its rows (:class:`Step`, with its :class:`Weight` in the
progress and its :class:`Fingerprint`) and the :class:`StepTable` that the run's loop
(:func:`workflows.run.loop.execute`), its progress, the fingerprints and the per-step
commands read.

This floor knows no step: the table of the built-in steps stands on the steps' floor
(``steps/table.py``, where its docstring says how a step is added), and the commands hand it
to the run (:class:`workflows.run.directory.Run`), which runs its rows in order.
"""

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

from pipeline.errors import ConfigError
from workflows.run.fingerprint import fingerprint

#: How a fingerprint part is found: a configuration path as written ("trees": the whole
#: section, "output.trees": one key) or a rule of its own, a function of the configuration
#: and its JSON dump.
Rule = str | Callable[[Any, dict], Any]


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
class Fingerprint:
    """What a step's fingerprint hashes: every part of the fingerprint named ``after``
    (the step it builds on) and its own ``parts``, each under its name (:data:`Rule`).
    ``name``: the fingerprint's name when it is not the step's."""

    parts: Mapping[str, Rule] = field(default_factory=dict)
    after: str | None = None
    name: str | None = None


@dataclass(frozen=True)
class Step:
    """One row of a table of steps.

    ``function``: runs the step; it takes the run's state (an instance of the table's
    ``state``). ``needs``: the state's attributes the steps before it set and it reads;
    ``sets``: those it sets. ``check``: what can be checked of it
    before the cluster starts, a function of the run and its planned tiles raising the error
    the step would raise later. ``fingerprint``: what its fingerprint hashes (None: it has
    none). ``weight``: its share in the progress. ``per_chunk``: a ``--chunk`` run (one chunk,
    in this process) runs it. ``per_stage``: its tasks run once per cascade stage
    (``predict-3``: stage 3 in its progress). ``command``: the help of its ``silva`` command,
    which runs every step up to it (None: no command, no line of its own in the progress).
    ``applying``: its name and weight in a run that applies a saved model. ``when``: a
    configuration path (``"output.trees"``) without whose true value the step is not part
    of the run (no work, no line in the progress).
    """

    name: str
    function: Callable[[Any], None]
    needs: tuple[str, ...] = ()
    sets: tuple[str, ...] = ()
    check: Callable[[Any, list], None] | None = None
    fingerprint: Fingerprint | None = None
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

    def shown_name(self, applies_model: bool) -> str:
        """The step's name in the progress (and in the timings)."""
        return self.applying[0] if applies_model and self.applying else self.name


class StepTable:
    """The steps of a run, in order: what runs (:meth:`until`), what the progress shows
    and weighs, what each fingerprint hashes; and ``state``, the class of what its steps
    hand on to each other (a :class:`~workflows.run.state.RunState` with the fields their
    ``needs`` and ``sets`` name)."""

    def __init__(self, *steps: Step, state: type):
        self.steps = steps
        self.state = state
        self.by_name = {step.name: step for step in steps}
        if len(self.by_name) < len(steps):
            raise ValueError("two steps of the table have one name")
        held = {f.name for f in fields(state)}
        unknown = [f"{step.name}: {name}" for step in steps
                   for name in (*step.needs, *step.sets) if name not in held]
        if unknown:
            raise ValueError(f"{state.__name__} holds no {', '.join(unknown)}: the steps "
                             "need and set fields of the table's state")
        #: The steps that are commands (a command runs every step up to its own), in order.
        self.targets = tuple(step.name for step in steps if step.command is not None)
        self._fingerprinted = {step.fingerprint.name or step.name: step.fingerprint
                               for step in steps if step.fingerprint is not None}
        #: The names of the fingerprints, in the order of their steps.
        self.fingerprinted = tuple(self._fingerprinted)

    def __iter__(self):
        return iter(self.steps)

    def __getitem__(self, name: str) -> Step:
        return self.by_name[name]

    def until(self, target: str, cfg=None) -> tuple[Step, ...]:
        """The steps a run up to ``target`` (a step's name) runs, in order: with ``cfg`` only
        those its configuration asks for (:meth:`Step.active`)."""
        until = self.steps[: self.steps.index(self.by_name[target]) + 1]
        return tuple(step for step in until if step.active(cfg))

    def progress_steps(self, target: str, applies_model: bool = False,
                       cfg=None) -> list[str]:
        """The steps with a line in the progress of a run up to ``target`` (with ``cfg``: of
        the steps its configuration asks for)."""
        return [step.shown_name(applies_model) for step in self.until(target, cfg)
                if step.command is not None]

    def weights(self, spent: Mapping[str, float] | None = None) -> dict[str, float]:
        """Each shown step's weight in a run's progress, under its name and, for a step named
        otherwise when a model is applied, that name too: the typical shares, or with
        ``spent`` (:func:`workflows.cli.plan.estimated_seconds`) its estimated seconds."""
        weights = {}
        for step in self.steps:
            if step.command is None:
                continue
            for name, weight in ((step.name, step.weight), *filter(None, [step.applying])):
                weights[name] = weight.share if spent is None else weight.seconds(spent)
        return weights

    def per_stage_names(self) -> set[str]:
        """The progress names of the steps whose tasks run once per cascade stage."""
        return {name for step in self.steps if step.per_stage
                for name in (step.name, *(step.applying[:1] if step.applying else ()))}

    def fingerprint_parts(self, name: str) -> dict[str, Rule]:
        """Every part the fingerprint ``name`` hashes: those of the fingerprints it builds
        on, then its own."""
        own = self._fingerprinted[name]
        before = {} if own.after is None else self.fingerprint_parts(own.after)
        return {**before, **own.parts}

    def fingerprint(self, cfg, name: str) -> str:
        """The fingerprint ``name`` of the configuration ``cfg``
        (:func:`workflows.run.fingerprint.fingerprint` of its parts)."""
        if name not in self._fingerprinted:
            raise ConfigError(f"config error: unknown step '{name}' for a fingerprint; "
                              f"use one of {', '.join(self.fingerprinted)}")
        return fingerprint(cfg, self.fingerprint_parts(name))


def examples(*lines: str) -> str:
    """A help text's example invocations: a paragraph click keeps line by line."""
    return "\n\n\b\nExamples:\n" + "\n".join(f"  {line}" for line in lines)
