"""A run folder is owned (docs/protocol.md, "A run folder is owned"): :class:`RunLock`, an exclusive
OS lock on ``<experiment>/run.lock`` (``fcntl.flock``; Windows: ``msvcrt.locking`` of one byte far past
the holder's pid), re-entrant within one process; :func:`check_out_folder`, the ``--out`` checks; and
:func:`inside`, a recording's path kept inside the run folder.
"""
from __future__ import annotations

import os
import threading
from pathlib import Path

from torchblur.files import resolve_inside
from torchblur.hardware.errors import RecordingError

try:  # Linux, macOS
    import fcntl
except ImportError:
    fcntl = None
try:  # Windows
    import msvcrt
except ImportError:
    msvcrt = None

__all__ = ["LOCK_NAME", "OUTPUT_NAMES", "RESULT_FILES", "RunLock", "check_out_folder", "inside"]

LOCK_NAME = "run.lock"
RESULT_FILES = ("frf.json", "frf.csv", "model.json", "report.txt")
#: what torchblur writes into an ``--out`` folder; a folder holding anything else is the user's
OUTPUT_NAMES = frozenset(RESULT_FILES) | {"frf.mat", "bode.png", "residuals.png", "ptc.png", "config.yaml", "source.json",
                                          "model_two_step.json", "experiment", "dm"}  # dm: a DM run's outputs (torchblur.identify.dm_outputs)

_held: dict[str, list] = {}  # real path of the folder -> [fd, count]
_guard = threading.Lock()
#: the byte ``msvcrt.locking`` locks (Windows locks are mandatory: the pid at offset 0 stays readable)
_WIN_LOCK_OFFSET = 1 << 20


def _try_lock(fd: int) -> bool:
    """Take the exclusive lock on the open file ``fd`` without waiting; False if another process holds it.

    Raises:
        RecordingError: this platform has neither ``fcntl`` nor ``msvcrt``.
    """
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        elif msvcrt is not None:
            os.lseek(fd, _WIN_LOCK_OFFSET, os.SEEK_SET)
            msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
        else:
            raise RecordingError("run lock: this platform offers neither fcntl nor msvcrt file locks; a run folder "
                                 "cannot be owned here")
    except OSError:
        return False
    return True


def _unlock(fd: int) -> None:
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_UN)
    elif msvcrt is not None:
        os.lseek(fd, _WIN_LOCK_OFFSET, os.SEEK_SET)
        msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _read_head(fd: int) -> str:
    os.lseek(fd, 0, os.SEEK_SET)
    return os.read(fd, 32).decode("ascii", "replace").strip()


def _write_pid(fd: int) -> None:
    os.lseek(fd, 0, os.SEEK_SET)
    os.write(fd, f"{os.getpid()}\n".ljust(32).encode())  # fixed width: no truncation (Windows: a locked region cannot shrink)


class RunLock:
    """An exclusive OS lock on the experiment folder ``path`` (``path/run.lock``).

    Raises:
        RecordingError: another process holds it (its pid is named), or the lock file cannot
            be created (a read-only folder).
    """

    def __init__(self, path: str | Path):
        self.key = os.path.realpath(path)
        self._held = False
        with _guard:
            if self.key in _held:
                _held[self.key][1] += 1
                self._held = True
                return
            lock_path = os.path.join(self.key, LOCK_NAME)
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0), 0o644)
            except OSError as exc:
                raise RecordingError(f"{path}: cannot create the run's lock file {LOCK_NAME} ({exc.strerror}); "
                                     f"is the folder read-only?") from None
            try:
                locked = _try_lock(fd)
            except RecordingError:
                os.close(fd)
                raise
            if not locked:
                holder = _read_head(fd) or "?"
                os.close(fd)
                raise RecordingError(f"{path}: another process (pid {holder}) is writing this run; wait for it to end "
                                     f"or choose another --out") from None
            _write_pid(fd)
            _held[self.key] = [fd, 1]
            self._held = True

    @property
    def held(self) -> bool:
        """Whether this object still holds the lock."""
        return self._held

    def release(self) -> None:
        """Give the lock back (idempotent); the last holder in this process unlocks the file."""
        with _guard:
            if not self._held:
                return
            self._held = False
            entry = _held.get(self.key)
            if entry is None:
                return
            entry[1] -= 1
            if entry[1] == 0:
                del _held[self.key]
                try:
                    _unlock(entry[0])
                finally:
                    os.close(entry[0])

    def __del__(self):
        try:
            self.release()
        except Exception:  # interpreter shutdown
            pass


def inside(root: Path, rel, what: str) -> Path:
    """``root / rel`` for a relative POSIX path ``rel`` from a recording, refused unless it
    stays inside ``root`` after resolving every symlink.

    Raises:
        RecordingError: ``rel`` is not a string, is absolute, holds ``..`` or a backslash, or
            resolves outside ``root``.
    """
    return resolve_inside(root, rel, what, error=RecordingError)


def check_out_folder(out: str | Path, *, command: str, force: bool = False, own_run: Path | None = None) -> Path:
    """Check an ``--out`` folder before anything is written; return it resolved.

    Refused: a path that is a file or lies under one; a folder that cannot be written; a
    folder inside another run's record (``R/experiment/...``) or inside another run's
    output folder; unless ``force``, a folder holding anything torchblur does not write there
    (:data:`OUTPUT_NAMES`: the user's own files); for ``command="fit"``, a run's own output folder or a folder that holds
    results (``frf.json``, ...) unless ``force``. ``own_run``: the run being resumed (its
    own folder is allowed).

    Raises:
        RecordingError: naming ``--out`` and the path.
    """
    out = Path(out)
    resolved = Path(os.path.realpath(out))
    for p in (resolved, *resolved.parents):
        if p.exists():
            if not p.is_dir():
                where = "is a file" if p == resolved else f"lies under the file {p}"
                raise RecordingError(f"--out {out}: {where}; give a folder")
            if not os.access(p, os.W_OK | os.X_OK):
                raise RecordingError(f"--out {out}: {p} is not writable")
            break
    own = Path(os.path.realpath(own_run)) if own_run is not None else None
    for p in (resolved, *resolved.parents):
        if own is not None and p == own:
            break
        if (p / "experiment.json").is_file():
            raise RecordingError(f"--out {out}: inside the record of the run {p.parent} ({p}); a run's record is "
                                 f"never written by another run, choose another folder")
        if p != resolved and (p / "experiment" / "experiment.json").is_file():
            raise RecordingError(f"--out {out}: inside the run folder {p}; choose a folder outside it")
    if not force and (own is None or resolved != own) and resolved.is_dir():
        foreign = sorted(p.name for p in resolved.iterdir() if p.name not in OUTPUT_NAMES)
        if foreign:
            shown = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            raise RecordingError(f"--out {out}: holds files that are not a torchblur run's ({shown}); choose an empty "
                                 f"or new folder, or --force to write beside them")
    if command == "fit" and not force:
        if (resolved / "experiment" / "experiment.json").is_file():
            raise RecordingError(f"--out {out}: the folder of a recorded run; its results would be overwritten "
                                 f"(--force to overwrite them)")
        held = [n for n in RESULT_FILES if (resolved / n).exists()]
        if held:
            raise RecordingError(f"--out {out}: already holds results ({', '.join(held)}); choose another folder "
                                 f"or --force to overwrite them")
    return resolved
