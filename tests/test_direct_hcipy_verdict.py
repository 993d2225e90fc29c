"""Issue 30's case, reduced: a user rig whose frames are HCIPy diffraction spots (an independent
optics engine: a circular aperture with astigmatism and coma), a plant with modes at 600 Hz
(damping 0.08) and 2 kHz and a 25 us delay, configs/identify_direct.yaml at 5 points, through
``torchblur.identify(cfg, rig)``. The direct model (fitted with a Gaussian PSF, which these
spots are not) must end flagged by name, or be within its stds of the truth; model.json then
holds the model that passed. (Full size: 12 points, 64x64 frames: the direct delay 20.5 +- 0.7
us, the two-step 24.2 +- 0.8 us, truth 25: flagged, exit 4.)"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

pytest.importorskip("hcipy")
# A whole identification with HCIPy frames: 92 s on the shared 2-core machine (the small default
# run there: 31 s), beyond the suite's budget; run it with TORCHBLUR_SLOW=1 (benchmarks/
# bench_direct_hcipy.py prints the full-size case).
pytestmark = pytest.mark.skipif(not os.environ.get("TORCHBLUR_SLOW"), reason="a whole HCIPy identification (~90 s); TORCHBLUR_SLOW=1")

import hcipy_frames as hf  # noqa: E402
import hcipy_rig as hr  # noqa: E402

import torchblur as tb  # noqa: E402
from torchblur.identify.config import load_config  # noqa: E402
from torchblur.identify.verdict import EXIT_FLAGGED, verdict  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "identify_direct.yaml"
TRUE_MODES_HZ, TRUE_DELAY_S = (600.0, 2000.0), 25e-6


def _within(model_params: dict, sigma: float = 3.0) -> bool:
    """Whether the delay and both modes' frequencies are within ``sigma`` stds of the truth."""
    ok = abs(model_params["delay_s"][0] - TRUE_DELAY_S) <= sigma * model_params["delay_s"][1]
    for f, (v, s) in zip(TRUE_MODES_HZ, model_params["modes"]):
        ok = ok and abs(v - f) <= sigma * s
    return ok


def test_direct_model_on_diffraction_spots_is_flagged_or_right(tmp_path):
    from torchblur.identify.cli import _write_models

    num, den, tau = hr.issue30_plant()
    cfg = load_config(str(CONFIG), [f"plant.num={num}", f"plant.den={den}", f"plant.delay_s={tau}", "sweep.n=5",
                                    "sweep.f_min_hz=100", "camera.height=40", "camera.width=40"])
    rig = hr.hcipy_rig(cfg, optics=hf.SpotOptics(pupil_px=32))
    res = tb.identify(cfg, rig, progress=False)
    d, m = res.direct_model, res.model
    assert d is not None and m is not None
    two = {"delay_s": m.parameter("delay_s"), "modes": [(x["freq_hz"], x["freq_hz_std"]) for x in m.modal_parameters()]}
    assert _within(two)  # the two-step model, fitted with the measured kernel, is right within its stds
    k = list(d.param_names).index("delay_s")
    direct = {"delay_s": (float(d.params[k]), float(d.std[k])),
              "modes": [(x["freq_hz"], x["freq_hz_std"]) for x in d.modal_parameters()]}
    v = verdict(res.frf, cfg, model=m, direct=d)
    if not _within(direct):  # a direct model off beyond its stds is flagged by name
        assert v.exit_code == EXIT_FLAGGED and not v.trustworthy
        assert "the direct model fails" in v.line and "model.json holds the two-step model" in v.line
    _write_models(cfg, res, tmp_path, v.models)
    doc = json.loads((tmp_path / "model.json").read_text())
    assert doc["model_passed"] is True
    held = "direct" if doc["schema"] == "torchblur.direct_model_fit" else "two-step"
    assert held == ("direct" if _within(direct) and v.trustworthy else "two-step")
    assert math.isfinite(doc["judgement"][0]["reduced_chi2"])
