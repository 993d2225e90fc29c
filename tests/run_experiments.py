"""Run experiment scripts one after another in ONE fresh process, each as
``python experiments/NAME.py --quick --out OUT/NAME`` would run it (its own ``__main__``
namespace and ``sys.argv``), so their imports (torch, matplotlib, torchblur: ~2 s each time)
are paid once. Usage: ``python tests/run_experiments.py OUT NAME [NAME ...]``; prints one line per
script, ``run_experiments: {"name": NAME, "ok": bool, "error": traceback or null}`` (JSON after the
prefix); exit status 0."""
from __future__ import annotations

import json
import runpy
import sys
import traceback
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
    except BaseException:  # noqa: BLE001 - reported to the test that checks this script
        return {"name": name, "ok": False, "error": traceback.format_exc()}
    finally:
        sys.argv = argv


def main(args: list[str]) -> None:
    sys.path.insert(0, str(EXPERIMENTS))  # the scripts import their `common` module, as run from there
    out = Path(args[0])
    for name in args[1:]:
        print(PREFIX + json.dumps(run_one(name, out)), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
