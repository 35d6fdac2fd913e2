"""Atomic file writes: a reader sees the old file or the complete new one, never a part.

Every output file of Silva (model files, LAS/LAZ tiles, metrics, reports, the saved
configuration) is written through :func:`atomic_path`: the content goes to a hidden
temporary file beside the target, which replaces the target in one ``os.replace`` only once
it is complete. A killed process leaves at worst a hidden ``.<name>.<random>.part`` file,
which :func:`remove_parts` clears; :func:`remove_stale` clears the outputs of an earlier run
that this one no longer writes.
"""

import os
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

PART_SUFFIX = ".part"


@contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``target``, on error it goes."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex[:12]}{PART_SUFFIX}")
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(target: str | Path, text: str) -> None:
    """Write ``text`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text)


def atomic_write_bytes(target: str | Path, data: bytes) -> None:
    """Write ``data`` to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)


def remove_parts(directory: str | Path) -> int:
    """Remove the temporary files a killed writer left in ``directory``; return how many."""
    directory = Path(directory)
    if not directory.is_dir():
        return 0
    parts = [p for p in directory.glob(f".*{PART_SUFFIX}") if p.is_file()]
    for path in parts:
        path.unlink(missing_ok=True)
    return len(parts)


def remove_stale(out_dir: Path, keep: list[str], suffixes=(".las", ".laz")) -> list[Path]:
    """Remove the files of ``out_dir`` with one of ``suffixes`` (by default point clouds)
    that are not in ``keep`` (what a run wrote there); return them."""
    kept = {Path(p).name for p in keep}
    stale = [p for p in out_dir.iterdir()
             if p.suffix.lower() in suffixes and p.name not in kept
             and (p.is_file() or p.is_symlink())]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale
