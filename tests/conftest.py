import math
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
# Figures are only written to files in the tests: matplotlib's Agg backend, no GUI backend probed (here and in the
# fresh processes the tests start). Set for the tests only; the library never touches the backend.
os.environ.setdefault("MPLBACKEND", "Agg")

import torchblur as tb  # noqa: E402


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


@pytest.fixture(scope="session")
def small_quiet_run(background, tmp_path_factory):
    """``torchblur identify --out OUT --quiet`` of the default simulated rig at 4 frequencies
    (cli_run.SMALL), in a fresh process, once per session, started in the background as soon as a
    collected test asks for it -> ``(OUT, finished process)``. Several test files check this same run
    (its stdout, its verdict, refits of its recording); they only read OUT and write elsewhere.
    ``report.figures=false``: none of them looks at a figure (the figures of a CLI run are checked by
    test_identify, test_mimo, test_multisine_identify, test_outside_recording and test_photon_transfer),
    and a re-fit of it draws none either. pytest-xdist's workers (``-n 2``) share one run
    (:func:`_shared_small_quiet_run`)."""
    if XDIST_WORKER:
        out, proc = _shared_small_quiet_run(tmp_path_factory.getbasetemp().parent)
    else:
        out, proc = background.get("small_quiet_run")
    assert proc.returncode == 0, proc.stderr
    return out, proc


def _shared_small_quiet_run(root):
    """The small run once for all pytest-xdist workers of the session (``root``: their shared temp folder):
    the first to need it runs it under an exclusive lock and saves the finished process beside it, the
    others wait on the lock and read it -> ``(OUT, finished process)``."""
    import fcntl
    import json
    import subprocess

    saved = root / "small_quiet_run.json"
    with open(root / "small_quiet_run.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not saved.exists():
            (root / "small_quiet_run").mkdir()
            out, proc = _small_quiet_run(root / "small_quiet_run", lambda popen: None)
            saved.write_text(json.dumps({"out": str(out), "args": proc.args, "returncode": proc.returncode,
                                         "stdout": proc.stdout, "stderr": proc.stderr}))
        got = json.loads(saved.read_text())
    return Path(got["out"]), subprocess.CompletedProcess(got["args"], got["returncode"], got["stdout"], got["stderr"])


def _small_quiet_run(out, started):
    """The background job of :func:`small_quiet_run` -> ``(OUT, finished process)``."""
    from background import run
    from cli_run import ROOT, SMALL

    out = out / "run"
    proc = run([sys.executable, "-m", "torchblur.cli", "identify", "--out", str(out), "--quiet", *SMALL, "report.figures=false"],
               started, env={"PYTHONPATH": str(ROOT)})
    return out, proc


_BACKGROUND = pytest.StashKey()
XDIST_WORKER = "PYTEST_XDIST_WORKER" in os.environ  # this process is a pytest-xdist worker


def pytest_configure(config):
    """A pytest-xdist worker runs on one torch thread, it and its children (through OMP_NUM_THREADS): one worker
    per core, and two processes of two OpenMP threads on 2 cores spin-wait each other to a crawl."""
    if XDIST_WORKER:
        torch.set_num_threads(1)
        os.environ["OMP_NUM_THREADS"] = "1"


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``-n 2`` (the README's test command): each worker is sent whole modules (a module's fixtures and its
    background job are built once, in the worker that runs its tests), in the order of the collection
    (:func:`pytest_collection_modifyitems`), not xdist's largest-count-first."""
    from xdist.scheduler import LoadFileScheduling

    config.option.loadscopereorder = False
    return LoadFileScheduling(config, log)


def pytest_collection_modifyitems(config, items):
    """In a pytest-xdist worker, the modules whose work runs in fresh processes (a ``BACKGROUND_JOB``, the
    shared ``small_quiet_run``: the suite's longest) come first, each module's tests in their order: the
    workers take them first and the short modules fill the end, so neither waits long for the other."""
    if not XDIST_WORKER:
        return
    first = {item.module for item in items if hasattr(getattr(item, "module", None), "BACKGROUND_JOB")
             or "small_quiet_run" in getattr(item, "fixturenames", ())}
    items.sort(key=lambda item: getattr(item, "module", None) not in first)  # stable: the rest keep their order


def pytest_collection_finish(session):
    """The background jobs of the collected modules (each module's ``BACKGROUND_JOB``, tests/background.py,
    and the session's ``small_quiet_run``) start at once, one after another in the order the tests need
    them, in fresh processes of one torch thread, and this process runs the other tests meanwhile on one
    torch thread too (and its children, through OMP_NUM_THREADS): two processes of two OpenMP threads on
    2 cores spin-wait each other to a crawl. The threads are given back at the first module that starts
    after the jobs have finished (within a module, a fixture's run and a test's compared bit for bit
    share the count)."""
    if session.config.option.collectonly:
        return
    jobs = {}
    for item in session.items:
        module, names = getattr(item, "module", None), getattr(item, "fixturenames", ())
        if "small_quiet_run" in names:
            jobs.setdefault("small_quiet_run", _small_quiet_run)
        if "background" in names and hasattr(module, "BACKGROUND_JOB"):  # a test that needs its module's job
            jobs.setdefault(module.__name__, module.BACKGROUND_JOB)
    if not jobs:
        return
    from background import Background

    out = Path(tempfile.mkdtemp(prefix="torchblur-background-"))
    # each job in the foreground, where a test needs it: asked for, or in a pytest-xdist worker (README: -n 2), where the
    # other worker keeps the second core busy and a worker's jobs are those of the modules it is sent
    inline = os.environ.get("TORCHBLUR_TEST_BACKGROUND") == "0" or XDIST_WORKER
    state = {"threads": None if inline else torch.get_num_threads(), "omp": os.environ.get("OMP_NUM_THREADS"), "out": out,
             "module": None}
    if not inline:
        torch.set_num_threads(1)
        os.environ["OMP_NUM_THREADS"] = "1"
    state["background"] = Background(out, jobs, inline=inline)  # in the order the tests need them
    session.config.stash[_BACKGROUND] = state


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item):
    state = item.config.stash.get(_BACKGROUND, None)
    if state is None or state["threads"] is None:
        return
    module = getattr(item, "module", None)
    if module is not state["module"]:
        state["module"] = module
        if state["background"].done():
            _restore_threads(state)


def _restore_threads(state):
    torch.set_num_threads(state["threads"])
    if state["omp"] is None:
        os.environ.pop("OMP_NUM_THREADS", None)
    else:
        os.environ["OMP_NUM_THREADS"] = state["omp"]
    state["threads"] = None


def pytest_sessionfinish(session):
    state = session.config.stash.get(_BACKGROUND, None)
    if state is not None:
        state["background"].stop()
        shutil.rmtree(state["out"], ignore_errors=True)


@pytest.fixture(scope="session")
def background(pytestconfig):
    """The jobs started in the background (``pytest_collection_finish``): ``background.get(module_name)``
    waits for that module's ``BACKGROUND_JOB`` -> its result."""
    state = pytestconfig.stash.get(_BACKGROUND, None)
    assert state is not None, "no background job was started (the module defines no BACKGROUND_JOB?)"
    return state["background"]


def make_case(dtype=torch.float64, tilted=True, batch=()):
    """A tilted PSF on a 2-D Lissajous motion over more than a period."""
    g = torch.Generator().manual_seed(7)
    center = torch.tensor([20.3, 18.7], dtype=dtype) + torch.rand(batch + (2,), generator=g, dtype=dtype)
    if tilted:
        psf = tb.GaussianPSF.from_axes(center, torch.tensor(2.2, dtype=dtype), torch.tensor(1.4, dtype=dtype),
                                       torch.tensor(0.5, dtype=dtype), amplitude=torch.tensor(3.0, dtype=dtype))
    else:
        psf = tb.GaussianPSF.isotropic(center, torch.tensor(1.8, dtype=dtype), amplitude=torch.tensor(3.0, dtype=dtype))
    amp = torch.tensor([9.0, 5.0], dtype=dtype) + torch.rand(batch + (2,), generator=g, dtype=dtype)
    phase = torch.tensor([0.4, 1.3], dtype=dtype) + torch.rand(batch + (2,), generator=g, dtype=dtype)
    f = 100.0
    traj = tb.Sinusoid(amp, phase, torch.tensor(2 * math.pi * f, dtype=dtype))
    win = tb.ExposureWindow(torch.tensor(0.13 / f, dtype=dtype), torch.tensor(1.4 / f, dtype=dtype))
    return traj, psf, win


# Hypothesis: a bounded, reproducible profile for CI (property tests in tests/test_properties.py).
# HYPOTHESIS_PROFILE=thorough runs more examples locally.
try:
    import os

    from hypothesis import HealthCheck, settings

    settings.register_profile("ci", max_examples=25, derandomize=True, deadline=None, print_blob=True,
                              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    settings.register_profile("thorough", max_examples=200, derandomize=False, deadline=None,
                              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
except ImportError:  # hypothesis is a test extra; without it tests/test_properties.py is skipped
    pass
