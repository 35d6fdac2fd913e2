"""What the built-in steps hand on to each other (:class:`StepState`): the chunk layout, the
training counts, the model's stages, the trees, the survey, the metrics. Each row of the
table of steps names the fields it ``needs`` and ``sets``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from workflows.run.state import RunState

if TYPE_CHECKING:
    from workflows.store.scenes import RunLayout


@dataclass
class StepState(RunState):
    """One execution of the built-in steps: its inputs (:class:`RunState`) and what the
    steps found."""

    layout: RunLayout | None = None  # ingest's chunk layout
    counts: object = None  # the training points per class (features)
    staged: RunLayout | None = None  # the layout's scenes classified stage by stage
    one_pass: RunLayout | None = None  # and those classified in one pass per chunk
    stages: list | None = None  # the model's stage records
    trees: dict | None = None  # the trees found per scene (output.trees)
    drawn: tuple | None = None  # an unlabelled run's survey and its figures (a future)
    metrics: dict | None = None
    plots: dict | None = None

    @property
    def outputs(self) -> RunLayout:
        """The layout without the thinned copies of the training scene (data.densities):
        the scenes the steps after the cascade export, score and survey."""
        return self.layout.without_copies()

    @property
    def labelled(self) -> bool:
        from workflows.run.directory import has_test_points  # the run's machinery: by now

        return has_test_points(self.layout.scenes, self.run.cfg.data.split)

    @property
    def n_stages(self) -> int:
        return len(self.stages)
