"""The `torchblur` command in a fresh process, and the one small default run that tests share."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["sweep.freq_hz=[20,150,300,600]"]  # enough points for the model (with 2 the verdict says it does not explain them)


def run_cli(*argv, cwd=None) -> subprocess.CompletedProcess:
    """``python -m torchblur.cli ARGV`` with this tree's torchblur -> the finished process (text output)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "torchblur.cli", *argv], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=600)
