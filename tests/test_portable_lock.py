"""Issue 28: run locks that work where ``fcntl`` does not exist (Windows). Every module of the
recording imports without ``fcntl`` (a subprocess where it is hidden); the Windows path
(``msvcrt.locking`` of one byte past the holder's pid) runs here with ``msvcrt`` a stand-in built
on POSIX byte-range locks (``fcntl.lockf``, per process like Windows' locks) and a forked holder:
no Windows here."""
from __future__ import annotations

import os
import sys
import textwrap
import types
from pathlib import Path

import pytest

from torchblur.hardware import run_folder
from torchblur.hardware.errors import RecordingError

ROOT = Path(__file__).resolve().parents[1]

_NO_FCNTL = textwrap.dedent("""
    import sys
    sys.modules['fcntl'] = None  # as on Windows: `import fcntl` raises ImportError
    import torchblur.hardware.recording, torchblur.hardware.manifest, torchblur.hardware.outside
    print('imported')
    from torchblur.hardware.errors import RecordingError
    from torchblur.hardware.run_folder import RunLock
    try:
        RunLock(sys.argv[1])
        print('locked')
    except RecordingError as exc:
        print('refused:', exc)
""")


def BACKGROUND_JOB(tmp_path, started):
    """``_NO_FCNTL`` in a fresh process, run in the background by tests/background.py -> the finished process."""
    from background import run

    return run([sys.executable, "-c", _NO_FCNTL, str(tmp_path)], started, env={"PYTHONPATH": str(ROOT)}, timeout_s=120)


def test_recording_imports_without_fcntl(background, request):
    """`import torchblur.hardware.recording` (and what imports it) works with fcntl unavailable; with no
    OS lock at all (neither fcntl nor msvcrt) a run lock is refused with one clear error, never taken
    silently."""
    r = background.get(request.module.__name__)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.strip().splitlines()
    assert lines[0] == "imported"
    assert lines[1].startswith("refused:") and "neither fcntl nor msvcrt" in lines[1]


@pytest.fixture
def windows_locks(monkeypatch):
    """run_folder as on Windows: no fcntl, an msvcrt whose ``locking`` locks n bytes from the file position."""
    posix = run_folder.fcntl
    fake = types.SimpleNamespace(LK_UNLCK=0, LK_NBLCK=2)

    def locking(fd, mode, n):
        pos = os.lseek(fd, 0, os.SEEK_CUR)
        posix.lockf(fd, (posix.LOCK_EX | posix.LOCK_NB) if mode == fake.LK_NBLCK else posix.LOCK_UN, n, pos, os.SEEK_SET)

    fake.locking = locking
    monkeypatch.setattr(run_folder, "fcntl", None)
    monkeypatch.setattr(run_folder, "msvcrt", fake)


def test_windows_lock_refuses_a_second_process_with_the_holders_pid(tmp_path, windows_locks):
    """The msvcrt path: while a (forked) process holds the folder, this one is refused naming the holder's pid
    (readable beside the locked byte); after the holder exits the folder is taken, released and re-taken."""
    ready_r, ready_w = os.pipe()
    stop_r, stop_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the holder
        try:
            lock = run_folder.RunLock(tmp_path)
            os.write(ready_w, b"1" if lock.held else b"0")
            os.read(stop_r, 1)
        finally:
            os._exit(0)
    try:
        assert os.read(ready_r, 1) == b"1"
        with pytest.raises(RecordingError, match=f"pid {pid}\\)"):
            run_folder.RunLock(tmp_path)
    finally:
        os.write(stop_w, b"x")
        os.waitpid(pid, 0)
        for fd in (ready_r, ready_w, stop_r, stop_w):
            os.close(fd)
    lock = run_folder.RunLock(tmp_path)  # the holder exited: its lock went with it
    assert lock.held and (tmp_path / run_folder.LOCK_NAME).read_text().strip() == str(os.getpid())
    lock.release()
    again = run_folder.RunLock(tmp_path)
    assert again.held
    again.release()
