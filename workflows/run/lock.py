"""One command at a time per output directory: ``OUT/silva.lock``.

The lock file holds the process id, host, start time and command of the run that holds it.
A second command on the same directory refuses at once and names the first. A lock left by
a run that was killed (its process no longer exists on this host) is taken over; one from
another host cannot be checked from here, so the message says how to remove it by hand. A
lock file Silva did not write (not JSON, or a field of the wrong kind) holds nothing: it is
taken over with a warning.
"""

import json
import logging
import math
import os
import socket
import time
import uuid
from pathlib import Path

from pipeline.errors import SilvaError

LOCK_NAME = "silva.lock"
#: Process ids are positive and below this (Linux allows at most 2**22).
MAX_PID = 2**31
#: The latest start time a lock may record (year 3000): later is no time at all.
MAX_STARTED = 32_503_680_000.0

log = logging.getLogger(__name__)


class LockedError(SilvaError, RuntimeError):
    """Another Silva command is running on the same output directory."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def read_lock(out: Path) -> dict | None:
    """The holder recorded in ``out``'s lock file (None: no lock, or an unreadable one)."""
    return _read(Path(out) / LOCK_NAME)


def _read(path: Path) -> dict | None:
    try:
        holder = json.loads(Path(path).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return holder if odd_field(holder) is None else None


def odd_field(holder) -> str | None:
    """What makes ``holder`` something other than a lock record Silva writes (None: a
    record with a pid, a host, a start time and a command of the right kinds)."""
    if not isinstance(holder, dict):
        return "it is not a JSON object"
    pid, started = holder.get("pid"), holder.get("started")
    if type(pid) is not int or not 0 < pid < MAX_PID:
        return "its 'pid' is not a process id"
    if not isinstance(holder.get("host"), str) or not holder["host"]:
        return "its 'host' is not a host name"
    if type(started) not in (int, float) or not math.isfinite(started) \
            or not 0 <= started <= MAX_STARTED:
        return "its 'started' is not a time"
    if not isinstance(holder.get("command"), str):
        return "its 'command' is not text"
    return None


def held_by_other(holder: dict | None) -> bool:
    """Whether ``holder`` is a run other than this process that may still be running."""
    if not holder:
        return False
    pid = holder.get("pid")
    if holder.get("host") != socket.gethostname():
        return True  # cannot tell: assume it runs
    if not isinstance(pid, int) or pid == os.getpid():
        return False
    return _alive(pid)


def describe(holder: dict) -> str:
    started = holder.get("started")
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(started)) if started else "?"
    return (f"'{holder.get('command', 'silva')}' (pid {holder.get('pid')} on "
            f"{holder.get('host')}, started {when})")


class OutputLock:
    """The lock of one output directory, held from :func:`acquire` until :meth:`release`
    (or the end of a ``with`` block)."""

    def __init__(self, out: Path, token: str):
        self.path, self.token = Path(out) / LOCK_NAME, token

    def release(self) -> None:
        """Remove the lock file if it is still this lock's."""
        holder = read_lock(self.path.parent)
        if holder and holder.get("token") == self.token:
            self.path.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def check_free(out: Path) -> None:
    """LockedError when another live run holds ``out``."""
    holder = read_lock(out)
    if held_by_other(holder):
        lock = Path(out) / LOCK_NAME
        remote = holder.get("host") != socket.gethostname()
        hint = (f"if it no longer runs, delete {lock}" if remote
                else "wait for it to finish or stop it")
        raise LockedError(f"{out} is in use by {describe(holder)}; {hint}, or choose "
                          "another --out")


def acquire(out: Path, command: str) -> OutputLock:
    """Take the lock of ``out`` (which must exist) for ``command``; LockedError when
    another live run holds it. A stale lock (a dead process of this host, or this very
    process) is taken over."""
    out = Path(out)
    token = uuid.uuid4().hex
    record = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                         "started": time.time(), "command": command, "token": token})
    lock = out / LOCK_NAME
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            holder = read_lock(out)
            check_free(out)
            if holder is None:
                _warn_foreign(lock)
            _take_over(lock, holder)
            continue
        with os.fdopen(fd, "w") as f:
            f.write(record)
        return OutputLock(out, token)
    check_free(out)
    raise LockedError(f"cannot take the lock {lock}: other commands keep taking it; "
                      "run one Silva command per output directory")


def _warn_foreign(lock: Path) -> None:
    """Log why the lock file about to be taken over holds no run."""
    try:
        why = odd_field(json.loads(lock.read_text()))
    except (OSError, ValueError, RecursionError):
        why = "it is not JSON"
    if why:  # None: it became a valid lock meanwhile (the take-over checks it again)
        log.warning("%s was not written by Silva (%s): taking it over", lock, why)


def _take_over(lock: Path, holder: dict | None) -> None:
    """Move a stale lock aside, unless another process replaced it in the meantime."""
    aside = lock.with_name(f".{LOCK_NAME}.{uuid.uuid4().hex[:8]}.stale")
    try:
        os.rename(lock, aside)
    except FileNotFoundError:
        return  # someone else took it over first
    moved = _read(aside)
    if moved != holder and held_by_other(moved):
        os.replace(aside, lock)  # a fresh lock of a live run: put it back
        return
    aside.unlink(missing_ok=True)

