"""Run experiment scripts one after another in ONE fresh process, each as
``python experiments/NAME.py --quick --out OUT/NAME`` would run it (its own ``__main__``
namespace and ``sys.argv``), so their imports (torch, matplotlib, torchblur: ~2 s each time)
are paid once. Usage: ``python tests/run_experiments.py OUT THREADS NAME [NAME ...]`` (THREADS: torch's CPU
threads, also given as ``threads=THREADS`` to the scripts whose config has that key); prints one line per
script, ``run_experiments: {"name": NAME, "ok": bool, "error": traceback or null}`` (JSON after the
prefix); exit status 0.

The suite runs its batches in the background (tests/background.py), one thread each, beside its other
tests: their ~40 CPU-seconds then cost little wall time on 2 cores."""
from __future__ import annotations

import json
import runpy
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
CONFIGS = EXPERIMENTS.parent / "configs"
PREFIX = "run_experiments: "


def run_one(name: str, out: Path, threads: int) -> dict:
    """``experiments/<name>.py --quick --out <out>/<name> [threads=THREADS]`` in this process -> ``{"name", "ok", "error"}``."""
    from omegaconf import OmegaConf

    script = EXPERIMENTS / f"{name}.py"
    argv = sys.argv
    sys.argv = [str(script), "--quick", "--out", str(out / name)]
    if "threads" in OmegaConf.load(CONFIGS / f"{name}.yaml"):
        sys.argv.append(f"threads={threads}")
    try:
        runpy.run_path(str(script), run_name="__main__")
        return {"name": name, "ok": True, "error": None}
    except SystemExit as exc:  # argparse errors and explicit exits
        ok = exc.code in (None, 0)
        return {"name": name, "ok": ok, "error": None if ok else f"SystemExit({exc.code!r})"}
    except Exception:  # noqa: BLE001 - reported to the test that checks this script
        return {"name": name, "ok": False, "error": traceback.format_exc()}
    finally:
        sys.argv = argv


def run_scripts(out: Path, names, *, threads: int = 1, timeout_s: float = 600, started=None) -> "Runs":
    """The scripts ``names`` run by this file in one fresh process (cwd: the repository) into ``out``,
    with ``threads`` torch threads; ``started(popen)`` is told the process once it runs (tests/background.py)."""
    from background import run

    proc = run([sys.executable, __file__, str(out), str(threads), *names], started or (lambda popen: None),
               env={"MPLBACKEND": "Agg", "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)},
               cwd=EXPERIMENTS.parent, timeout_s=timeout_s)
    assert proc.returncode == 0, proc.stderr[-3000:]
    status = {}
    for line in proc.stdout.splitlines():
        if line.startswith(PREFIX):  # the runner's lines; the scripts print their own too
            doc = json.loads(line[len(PREFIX):])
            status[doc["name"]] = (doc["ok"], doc["error"])
    return Runs(out, status, proc)


@dataclass(frozen=True)
class Runs:
    """What :func:`run_scripts` ran: ``out`` folder, ``status {name: (ok, error)}``, the process."""

    out: Path
    status: dict
    proc: subprocess.CompletedProcess

    def metrics(self, name: str) -> tuple[Path, dict]:
        """Asserts that ``name`` ran and succeeded -> ``(its out folder, its metrics.json, which says quick)``."""
        tail = f"\n{self.proc.stdout[-3000:]}\n{self.proc.stderr[-3000:]}"
        assert name in self.status, f"{name} did not run:{tail}"
        ok, error = self.status[name]
        assert ok, f"{name} failed:\n{error}{tail}"
        out = self.out / name
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["quick"] is True
        return out, metrics


def main(args: list[str]) -> None:
    sys.path.insert(0, str(EXPERIMENTS))  # the scripts import their `common` module, as run from there
    out, threads = Path(args[0]), int(args[1])
    import torch

    torch.set_num_threads(threads)
    for name in args[2:]:
        print(PREFIX + json.dumps(run_one(name, out, threads)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
