"""Expensive fixtures computed in the background, in fresh processes, while the suite runs its other tests.

A test module that defines ``BACKGROUND_JOB(out: Path, started) -> result`` has it started by
tests/conftest.py as soon as the module is collected; the jobs of all collected modules run one after
another (in the order the tests need them) on one daemon thread, each in its own folder ``out``. A job runs its work in a
child process (the second core: a thread of the suite's process would share its GIL) and calls
``started(popen)`` once that runs, so that an interrupted session can kill it. The module's fixture then
takes the result with ``background.get(request.module.__name__)`` (tests/conftest.py: the ``background``
fixture), which waits for it. ``TORCHBLUR_TEST_BACKGROUND=0`` runs each job only there, in the foreground,
as the suite did before (to compare the two on one machine); so does a pytest-xdist worker (``-n 2``, the
README's command), whose modules with a job come first (tests/conftest.py) while the other worker fills
the second core. Measured on the shared 2-core machine: the experiment batches' ~40 CPU-seconds
and the multisine local-minimum fit's ~15 ran beside the rest instead of before it."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

TESTS = Path(__file__).resolve().parent


class Background:
    """Jobs ``{key: fn(out, started) -> result}`` run one after another on a daemon thread, each
    into ``out / key``. ``get(key)`` waits for its job and returns its result (or raises what the job
    raised); ``done()`` whether all have finished; ``stop()`` kills the child running now and skips
    the rest."""

    def __init__(self, out: Path, jobs: dict, *, inline: bool = False):
        self._jobs, self._results, self._out, self._inline = dict(jobs), {}, Path(out), inline
        self._events = {key: threading.Event() for key in self._jobs}
        self._proc, self._stopped = None, False
        self._thread = threading.Thread(target=self._run, daemon=True)
        if not inline:
            self._thread.start()

    def _run(self) -> None:
        for key in self._jobs:
            self._run_one(key)

    def _run_one(self, key: str) -> None:
        try:
            if self._stopped:
                raise RuntimeError("stopped before it ran")
            (self._out / key).mkdir(parents=True)
            self._results[key] = self._jobs[key](self._out / key, self._started)
        except BaseException as exc:  # noqa: BLE001 - re-raised by get() in the test that needs it
            self._results[key] = exc
        finally:
            self._events[key].set()

    def _started(self, proc) -> None:
        self._proc = proc
        if self._stopped:
            proc.kill()

    def get(self, key: str, timeout_s: float = 1200):
        if self._inline and not self._events[key].is_set():
            self._run_one(key)  # the job, where the test needs it (TORCHBLUR_TEST_BACKGROUND=0)
        assert self._events[key].wait(timeout_s), f"the background job {key} did not finish in {timeout_s} s"
        result = self._results[key]
        if isinstance(result, BaseException):
            raise result
        return result

    def done(self) -> bool:
        return not self._thread.is_alive()

    def stop(self) -> None:
        self._stopped = True
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
        if self._thread.is_alive():
            self._thread.join(30)


def run(argv: list[str], started, *, env: dict | None = None, cwd=None, timeout_s: float = 600) -> subprocess.CompletedProcess:
    """``argv`` in a fresh process (one torch thread; text output captured) -> the finished process."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", **(env or {})}
    with subprocess.Popen(argv, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) as popen:
        started(popen)
        try:
            stdout, stderr = popen.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            popen.kill()
            raise
    return subprocess.CompletedProcess(popen.args, popen.returncode, stdout, stderr)


def run_python(code: str, started, *, timeout_s: float = 600) -> subprocess.CompletedProcess:
    """``python -c CODE`` in a fresh process (cwd tests/, on its path; one torch thread) -> the finished
    process; asserts it exited 0."""
    proc = run([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(TESTS)!r})\n{code}"], started, cwd=TESTS,
               timeout_s=timeout_s)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def started_fleet(procs: dict) -> dict:
    """``procs`` ``{name: emulator process}`` once each has printed its start line (``.info`` waits
    for it): a module's BACKGROUND_JOB that starts its emulators at once, their start-ups overlapping."""
    for p in procs.values():
        p.info  # noqa: B018 - waits for its start line
    return procs


def stop_fleet(procs: dict) -> None:
    """Stop every emulator of ``procs`` (a module fixture's teardown)."""
    for p in procs.values():
        p.stop()
