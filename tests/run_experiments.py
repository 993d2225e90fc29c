"""Run experiment scripts one after another in ONE fresh process, each as
``python experiments/NAME.py --quick --out OUT/NAME`` would run it (its own ``__main__``
namespace and ``sys.argv``), so their imports (torch, matplotlib, torchblur: ~2 s each time)
are paid once. Usage: ``python tests/run_experiments.py OUT NAME [NAME ...]``; prints one line per
script, ``run_experiments: {"name": NAME, "ok": bool, "error": traceback or null}`` (JSON after the
prefix); exit status 0."""
from __future__ import annotations

import json
import os
import runpy
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"
PREFIX = "run_experiments: "


def run_one(name: str, out: Path) -> dict:
    """``experiments/<name>.py --quick --out <out>/<name>`` in this process -> ``{"name", "ok", "error"}``."""
    script = EXPERIMENTS / f"{name}.py"
    argv = sys.argv
    sys.argv = [str(script), "--quick", "--out", str(out / name)]
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


def run_scripts(out: Path, names, *, env: dict | None = None, timeout_s: float = 600) -> "Runs":
    """The scripts ``names`` run by this file in one fresh process (cwd: the repository) into ``out``."""
    proc = subprocess.run([sys.executable, __file__, str(out), *names], cwd=EXPERIMENTS.parent, capture_output=True,
                          text=True, env=dict(os.environ, **(env or {})), timeout=timeout_s)
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
    out = Path(args[0])
    for name in args[1:]:
        print(PREFIX + json.dumps(run_one(name, out)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
