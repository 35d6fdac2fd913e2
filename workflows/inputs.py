"""The input tiles of a run: the scenes data paths belong to, and globs expanded to files."""

import glob
import os
from collections.abc import Sequence
from pathlib import Path

from pipeline.errors import InputError, MissingFileError

SCENES = ("train", "test", "predict")


def expand_inputs(patterns: Sequence[str | Path], *, key: str | None = None) -> list[Path]:
    """The files matched by paths and globs, sorted and without duplicates.

    ``**`` matches any number of directories. ``key`` (e.g. ``"data.train"``) is named in
    errors. Raises :class:`MissingFileError` naming a pattern that matches no file or a
    broken symbolic link, and :class:`InputError` for a directory given where files are
    expected.
    """
    where = f" in {key}" if key else ""
    found: dict[Path, Path] = {}
    for pattern in patterns:
        text = os.path.expanduser(os.fspath(pattern))
        if glob.has_magic(text):
            matched = glob.glob(text, recursive=True)
            for p in matched:
                if os.path.islink(p) and not os.path.exists(p):
                    raise MissingFileError(f"'{p}' (matched by '{text}'{where}) is a broken "
                                           "symbolic link; fix it or remove it")
            matches = [Path(p) for p in matched if os.path.isfile(p)]
        elif os.path.isdir(text):
            raise InputError(f"input '{text}'{where} is a directory; give its files, e.g. "
                             f"'{os.path.join(text, '*.laz')}'")
        elif os.path.islink(text) and not os.path.exists(text):
            raise MissingFileError(f"input '{text}'{where} is a broken symbolic link; fix it "
                                   "or remove it")
        else:
            matches = [Path(text)] if os.path.isfile(text) else []
        if not matches:
            raise MissingFileError(f"no file matches '{text}'{where}; check the path or glob")
        for match in matches:
            found.setdefault(match.resolve(), match)
    return sorted(found.values(), key=lambda p: str(p))
