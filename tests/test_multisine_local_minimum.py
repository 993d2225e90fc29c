"""The multisine fit's wider search on real data with a local minimum.

tests/data/multisine_local_minimum.npz holds the image set of one group of
``torchblur identify --config configs/identify_multisine.yaml`` (seed 0; tones 148.7, 191.2 and
233.7 Hz on harmonics 7, 9, 11 of 21.25 Hz; 12 frames, electrons at laser power 1, their noise
std, windows, the calibration's Gaussian PSF and the amplitude guess), as fit_multisine was called
with them. In that run the fit ended in a local minimum at reduced chi2 1.42 (amplitudes 5.14,
4.11, 10.06 px, |H| 19-41 % off, reported as converged), below the old 1.5 that triggered the
wider search; the right fit has reduced chi2 0.96. With few starts the first search lands there
for most seeds, so the wider search (RETRY_CHI2, _wide_starts) must find its way out. (Which
seeds land in the trap depends on round-off: the same call gives LOCAL or RIGHT after other fits
in the same process, so the old rule's failure is not asserted here; measured: seeds 0, 1, 3, 5
of 6 with the old rule, none of 0-9 with the new.)
"""
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from torchblur.fit.multisine import RETRY_CHI2, fit_multisine
from torchblur.render.psf import GaussianPSF
from torchblur.render.window import ExposureWindow

from background import run_python

DATA = Path(__file__).parent / "data" / "multisine_local_minimum.npz"
RIGHT = np.array([6.311, 6.942, 7.889])  # px: the fit at reduced chi2 0.959 (the lowest found, from every start tried)
LOCAL = np.array([5.142, 4.105, 10.064])  # px: the local minimum at reduced chi2 1.416


def _fit(seed: int, **kw):
    d = np.load(DATA)
    t = lambda k: torch.from_numpy(np.asarray(d[k])).to(torch.float64)  # noqa: E731
    psf = GaussianPSF(t("psf_center"), t("psf_cov"), float(d["psf_amp"]))
    return fit_multisine(t("img"), psf, ExposureWindow(t("start"), t("dur")), t("om"), noise_std=t("noise"),
                         amplitude_guess=t("guess"), fit_scale=True, seed=seed, direction=t("direction"), **kw)


SEEDS = [1]


def few_starts(seed: int) -> dict:
    """The fit from ``n_starts=2, n_refine=1`` -> its amplitude (px), reduced chi2 and status."""
    fit = _fit(seed, n_starts=2, n_refine=1)
    return {"amplitude": fit.amplitude.tolist(), "reduced_chi2": float(fit.extras["reduced_chi2"]), "status": int(fit.status)}


def BACKGROUND_JOB(out, started):
    """:func:`few_starts` of each seed, in a fresh process in the background (tests/background.py: ~15 CPU-seconds
    beside the other tests) -> ``{seed: its result}``."""
    code = f"import json, test_multisine_local_minimum as t; print(json.dumps([t.few_starts(s) for s in {SEEDS!r}]))"
    return dict(zip(SEEDS, json.loads(run_python(code, started).stdout.splitlines()[-1])))


@pytest.mark.parametrize("seed", SEEDS)
def test_few_starts_still_find_the_global_minimum(seed, background, request):
    # n_starts=2, n_refine=1: with the old rule (retry above 1.5) seeds 0, 1, 3 and 5 ended at LOCAL; with a wider search of
    # 256 starts seed 1 still did (and 7): 1024 starts and 24 refinements find RIGHT for seeds 0-9 (measured; one kept here: 18 s CPU
    # at load ~20, 64 s before the search ranked its starts by the binned cost, benchmarks/bench_search_starts.py)
    fit = background.get(request.module.__name__)[seed]  # few_starts(seed), computed in the background
    np.testing.assert_allclose(np.asarray(fit["amplitude"]), RIGHT, atol=0.02)
    chi2 = fit["reduced_chi2"]
    assert 0.9 < chi2 < RETRY_CHI2
    assert fit["status"] == 0

