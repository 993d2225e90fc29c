"""benchmarks/bench_dm_ladder_starts.py patches the ladder fit's LM and settings for its passes: it
gives them back when a pass fails, so that nothing run after it in the same process fits with them."""
import importlib.util
import math
from pathlib import Path

import pytest
import torch

import torchblur.dm.ladder_fit as lf

pytest.importorskip("hcipy")  # the benchmark imports the HCIPy sensor at load

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_dm_ladder_starts", ROOT / "benchmarks" / "bench_dm_ladder_starts.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_failing_pass_leaves_the_ladder_fit_as_it_was(monkeypatch):
    for name in ("levenberg_marquardt", "SECOND_START", "MAX_ITER"):  # restored after this test whatever the benchmark does
        monkeypatch.setattr(lf, name, getattr(lf, name))
    before = (lf.levenberg_marquardt, lf.SECOND_START, lf.MAX_ITER)
    bench = _bench()
    ladder = type("Ladder", (), {"slope": torch.ones(2, 3, 2)})()
    monkeypatch.setattr(bench, "acquire", lambda patterns: (None, None, None, ladder, [(10.0, 1.0, 1.0, None, None)], torch.ones(2, 4),
                                                            None, None, None))
    seen = []

    def failing(*args):
        seen.append((lf.levenberg_marquardt, lf.SECOND_START, lf.MAX_ITER))
        raise RuntimeError("a fit failed")
    monkeypatch.setattr(bench, "fit", failing)
    with pytest.raises(RuntimeError, match="a fit failed"):
        bench.main(["--patterns", "0,1"])
    assert seen[0][0] is not before[0] and seen[0][1:] == (math.inf, 60)  # the first pass ran with the patched fit
    assert (lf.levenberg_marquardt, lf.SECOND_START, lf.MAX_ITER) == before
