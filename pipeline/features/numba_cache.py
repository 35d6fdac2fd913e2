"""Where numba caches the compiled kernels: a directory named by a digest of their sources.

numba's own cache (``cache=True``) is checked against the timestamp of the file that defines
each kernel only. A kernel that inlines code from another file (the local moments kernel calls
the triangulation and the moment formulas) would keep running the old code after that other
file changed, e.g. after ``git pull`` in an editable install. Naming the cache directory after
a digest of every source file of this package makes any change start a fresh cache.

The directory is ``$NUMBA_CACHE_DIR`` (or ``$XDG_CACHE_HOME``, or ``~/.cache``) followed by
``silva-numba/<digest>``; when that cannot be created, the system's temporary directory.
"""

import getpass
import hashlib
import os
import tempfile
from pathlib import Path

import numba

SOURCES = Path(__file__).resolve().parent


def source_digest(folder: Path = SOURCES) -> str:
    """16 hex digits that change whenever any ``*.py`` file in ``folder`` changes."""
    digest = hashlib.sha256()
    for path in sorted(folder.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def _user() -> str:
    try:
        return getpass.getuser()
    except (KeyError, OSError):  # a container's uid without a passwd entry
        return "user"


def cache_dir(digest: str) -> Path:
    """A writable directory for the kernels of this source digest."""
    base = os.environ.get("NUMBA_CACHE_DIR") or os.environ.get("XDG_CACHE_HOME")
    candidates = [Path(base) if base else Path.home() / ".cache",
                  Path(tempfile.gettempdir()) / f"silva-{_user()}"]
    for root in candidates:
        folder = root / "silva-numba" / digest
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder
    return candidates[-1] / "silva-numba" / digest  # numba warns and compiles if unusable


def use_source_keyed_cache() -> Path:
    """Point numba's cache at this package's directory; call before any kernel is defined."""
    folder = cache_dir(source_digest())
    numba.config.CACHE_DIR = str(folder)
    return folder
