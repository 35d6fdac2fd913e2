"""How far one long computation has come (a chunk's surfaces), told to whoever runs it.

The science says how far it is (:func:`advance`); a caller that wants to know listens for
the duration of the work (:func:`reporting`): a worker forwards it to the run's progress
bar, so the bar moves during a long chunk. Nobody listening, :func:`advance` costs a lookup.
"""

import contextvars
from collections.abc import Callable, Iterator
from contextlib import contextmanager

_LISTENER: contextvars.ContextVar[Callable[[float], None] | None] = contextvars.ContextVar(
    "pipeline_progress", default=None)


@contextmanager
def reporting(listener: Callable[[float], None]) -> Iterator[None]:
    """Call ``listener(fraction)`` with the share done of the work run in this block."""
    token = _LISTENER.set(listener)
    try:
        yield
    finally:
        _LISTENER.reset(token)


def advance(done: int, total: int) -> None:
    """``done`` of ``total`` items of the current work are finished."""
    listener = _LISTENER.get()
    if listener is not None and total > 0:
        listener(min(done / total, 1.0))
