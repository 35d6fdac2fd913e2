"""Echo features in a run (``features.echoes``): which tiles carry the return numbers they
are computed from (and, for ``auto``, which are multi-return surveys: :func:`multi_return`),
and the one line that refuses a tile without them.

A run computes echo features when its configuration sets ``features.echoes: true`` or when
the model it applies was trained with them (:func:`workflows.run.autoparams.adopt_model` takes
the key from the model). Every tile must then record each point's return number and number
of returns: a format without the fields (Oakland text) is refused when the tiles are
planned, from the header (:func:`check_return_fields`); a LAS tile whose points all have
invalid values (1 <= return_number <= number_of_returns nowhere, e.g. a writer that left
them at 0, as ``silva synth`` does) before any worker starts when its header counts no point
by return number (a read of its return fields confirms it), else once ingest has read all
of it (:meth:`EchoNeed.check_tile`): the verdict is the tile's, whatever ranges it is read in.
Without the refusal such a tile would get NaN echo columns everywhere: points without
features, never a silent wrong class, but no classification either.
"""

from dataclasses import dataclass

from pipeline.errors import InputError
from pipeline.features.echo import return_counts
from pipeline.io import iter_points
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

    def check_tile(self, path, counts) -> None:
        """InputError when no point of tile ``path`` has returns: ``counts`` are the tile's
        (valid, empty, above) of :func:`pipeline.features.echo.return_counts`, over all its
        points, however they were read."""
        valid, empty, above = counts
        if valid:
            return
        why = "the fields were left empty"
        if above:
            why = (f"return_number > number_of_returns for {above:,} of them"
                   + (f", the fields of {empty:,} left empty" if empty else ""))
        raise self.refuse(path, "has no valid return numbers: 1 <= return_number <= "
                                f"number_of_returns holds for none of its points ({why})")


def scan_returns(path, read_batch: int = 1_000_000) -> tuple[int, int, int]:
    """The (valid, empty, above) return counts of tile ``path``
    (:func:`pipeline.features.echo.return_counts`), read from its return fields alone and
    stopped at the first batch holding a point with returns."""
    total = (0, 0, 0)
    for batch in iter_points(path, batch_size=read_batch, fields=RETURNS):
        counts = return_counts(*(batch.fields[name] for name in RETURNS))
        total = tuple(a + b for a, b in zip(total, counts))
        if total[0]:
            break
    return total


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


def multi_return(tiles) -> bool:
    """Whether every tile of the catalogue ``tiles`` counts, in its header, points of a
    second or later return: a multi-return survey, whose echoes tell crowns from roofs.
    Text files, single-return scans and headers that count no returns (as ``silva synth``
    writes them) do not."""
    counts = [None if t.header is None else t.header.points_by_return for t in tiles]
    return bool(counts) and all(c is not None and sum(c[1:]) > 0 for c in counts)


def has_return_fields(dimensions) -> bool:
    """Whether a tile with these ``dimensions`` (its header's) records return numbers."""
    try:
        resolve_fields(RETURNS, dimensions, "")
    except InputError:
        return False
    return True


def check_return_fields(run, path, info) -> None:
    """InputError when ``run`` computes echo features and the tile ``path`` (header
    ``info``, a :class:`pipeline.io.base.TileInfo`) has no return fields, or its header
    counts no point by return number and a read of its return fields finds no valid one
    (before any worker starts); a format whose header lists no dimensions is checked when it
    is read."""
    need = echo_need(run)
    if need is None:
        return
    if info.dimensions and not has_return_fields(info.dimensions):
        raise need.refuse(path, f"records no return numbers (its {info.format} format has no "
                                "return_number and number_of_returns)")
    if info.points_by_return is not None and not any(info.points_by_return):
        need.check_tile(path, scan_returns(path, run.cfg.tiling.read_batch))
