"""The input tiles of a run: the scenes data paths belong to, and globs expanded to files."""

import glob
import os
import stat
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import InputError, MissingFileError

SCENES = ("train", "test", "predict")


@dataclass(frozen=True)
class InputFile:
    """An input tile as the run found it: its scene, path, size and modification time."""

    scene: str
    path: Path
    size: int
    mtime_ns: int


def find_inputs(patterns: Mapping[str, Sequence]) -> tuple[InputFile, ...]:
    """Every input file of the data paths and globs ``patterns`` (scene -> list), scene by
    scene in their order (data.train, data.test, data.predict), each scene's files in
    :func:`expand_inputs` order: each glob expanded once. Raises its errors."""
    found = []
    for scene in SCENES:
        scene_patterns = list(patterns.get(scene) or ())
        for path in expand_inputs(scene_patterns, key=f"data.{scene}") if scene_patterns else ():
            stat_ = path.stat()
            found.append(InputFile(scene, path, stat_.st_size, stat_.st_mtime_ns))
    return tuple(found)


def written_inputs(raw: dict) -> tuple[InputFile, ...] | None:
    """The input files (:func:`find_inputs`) of ``raw`` (a configuration as written, its
    paths resolved), found before anything is written: a wrong path must not leave an
    output directory behind. None when a data path is of another type, which the validation
    refuses."""
    data = raw.get("data") if isinstance(raw, dict) else None
    if not isinstance(data, dict):
        return None
    patterns = {}
    for scene in SCENES:
        value = data.get(scene) or []
        value = [value] if isinstance(value, (str, Path)) else value
        if not isinstance(value, list) or not all(isinstance(p, (str, Path)) for p in value):
            return None
        patterns[scene] = value
    return find_inputs(patterns)


def expand_inputs(patterns: Sequence[str | Path], *, key: str | None = None) -> list[Path]:
    """The files matched by paths and globs, sorted and without duplicates.

    ``**`` matches any number of directories; directories a glob matches besides files are
    skipped. ``key`` (e.g. ``"data.train"``) is named in errors. Raises
    :class:`MissingFileError` naming a pattern that matches no file or a broken symbolic
    link, and :class:`InputError` for a directory given where files are expected, a glob
    that matches only directories, and a path that is no regular file (a FIFO, a device, a
    socket: reading one would block or never end).
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
                kind = _special(p)
                if kind:
                    raise InputError(f"'{p}' (matched by '{text}'{where}) is {kind}, not a "
                                     "regular file; remove it or narrow the glob")
            matches = [Path(p) for p in matched if os.path.isfile(p)]
            folders = [p for p in matched if os.path.isdir(p)]
            if not matches and folders:
                raise InputError(f"'{text}'{where} matches only directories, not LAS/LAZ "
                                 f"files ({_some(folders)}); give their files, e.g. "
                                 f"'{os.path.join(folders[0], '*.laz')}'")
        elif os.path.isdir(text):
            raise InputError(f"input '{text}'{where} is a directory, not a LAS/LAZ file; give "
                             f"its files, e.g. '{os.path.join(text, '*.laz')}'")
        elif os.path.islink(text) and not os.path.exists(text):
            raise MissingFileError(f"input '{text}'{where} is a broken symbolic link; fix it "
                                   "or remove it")
        elif _special(text):
            raise InputError(f"input '{text}'{where} is {_special(text)}, not a regular file; "
                             "give a LAS/LAZ file (copy the data to one first)")
        else:
            matches = [Path(text)] if os.path.isfile(text) else []
        if not matches:
            raise MissingFileError(f"no file matches '{text}'{where}; check the path or glob")
        for match in matches:
            found.setdefault(match.resolve(), match)
    return sorted(found.values(), key=lambda p: str(p))


_KINDS = ((stat.S_ISFIFO, "a named pipe (FIFO)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _special(path: str) -> str | None:
    """What ``path`` (followed through symbolic links) is when it exists and is neither a
    regular file nor a directory: a FIFO, a device or a socket (None otherwise)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    target = os.path.realpath(path)
    via = f" ({target})" if target != os.path.abspath(path) else ""
    return next((f"{kind}{via}" for test, kind in _KINDS if test(mode)),
                f"a special file{via}")


def _some(paths: list[str], n: int = 3) -> str:
    """Up to ``n`` of ``paths``, and how many more."""
    shown = ", ".join(sorted(paths)[:n])
    return shown + (f" and {len(paths) - n} more" if len(paths) > n else "")
