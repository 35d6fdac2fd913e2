"""Echo features in a run (``features.echoes``): which tiles carry the return numbers they
are computed from, and the one line that refuses a tile without them.

A run computes echo features when its configuration sets ``features.echoes: true`` or when
the model it applies was trained with them (:func:`workflows.run.autoparams.adopt_model` takes
the key from the model). Every tile must then record each point's return number and number
of returns: a format without the fields (Oakland text) is refused when the tiles are
planned, from the header (:func:`check_return_fields`); a LAS tile whose points all have
invalid values (1 <= return_number <= number_of_returns nowhere, e.g. a writer that left
them at 0, as ``silva synth`` does) when ingest reads it (:meth:`EchoNeed.check_read`).
Without the refusal such a tile would get NaN echo columns everywhere: points without
features, never a silent wrong class, but no classification either.
"""

from dataclasses import dataclass

from pipeline.errors import InputError
from pipeline.io.base import resolve_fields
from workflows.store.layout import RETURNS


@dataclass(frozen=True)
class EchoNeed:
    """What needs the points' return numbers in a run (``who``, for messages) and how a
    user does without them (``fix``)."""

    who: str
    fix: str

    def refuse(self, path, what: str) -> InputError:
        """The one-line refusal of tile ``path``, which ``what`` (a phrase)."""
        return InputError(f"tile {path} {what}, which {self.who} needs: {self.fix}")

    def check_read(self, path, seen_returns: bool, span=None) -> None:
        """InputError when ingest read no point with returns in tile ``path`` (or in its
        point range ``span``, (start, stop))."""
        if not seen_returns:
            where = f" (points {span[0]:,} to {span[1]:,})" if span else ""
            raise self.refuse(path, f"has no valid return numbers{where}: "
                                    "1 <= return_number <= number_of_returns holds for none "
                                    "of its points (the fields were left empty)")


def echo_need(run) -> EchoNeed | None:
    """What needs the return numbers in ``run`` (a :class:`workflows.run.directory.Run`), or
    None when its features use none."""
    if not run.features.echoes:
        return None
    if run.model_dir is not None:
        return EchoNeed(f"the model {run.model_dir} (trained with features.echoes: true)",
                        "apply a model trained without echo features, or give LAS tiles "
                        "whose points record their return numbers")
    return EchoNeed("features.echoes: true",
                    "set features.echoes: false, or give LAS tiles whose points record their "
                    "return numbers")


def has_return_fields(dimensions) -> bool:
    """Whether a tile with these ``dimensions`` (its header's) records return numbers."""
    try:
        resolve_fields(RETURNS, dimensions, "")
    except InputError:
        return False
    return True


def check_return_fields(run, path, info) -> None:
    """InputError when ``run`` computes echo features and the tile ``path`` (header
    ``info``, a :class:`pipeline.io.base.TileInfo`) has no return fields; a format whose
    header lists no dimensions is checked when it is read."""
    need = echo_need(run)
    if need is not None and info.dimensions and not has_return_fields(info.dimensions):
        raise need.refuse(path, f"records no return numbers (its {info.format} format has no "
                                "return_number and number_of_returns)")
