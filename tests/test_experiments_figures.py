"""The paper-figure experiment scripts (experiments/fig*.py) run with --quick and their
metrics back each figure's claim (Tani, Mishra, Wen, CDC 2012, Figs. 1-7 and 10)."""
from __future__ import annotations

import math

import pytest

from run_experiments import run_scripts

pytest.importorskip("matplotlib")
pytest.importorskip("omegaconf")

SCRIPTS = ("fig1_peanut", "fig2_cost_vs_phase", "fig4_saturation", "fig5_norms", "fig6_landscape", "fig7_dual_exposure",
           "fig10_psf")


def BACKGROUND_JOB(out, started):
    """The scripts run with ``--quick`` in the background (tests/background.py) -> their ``Runs``."""
    return run_scripts(out, SCRIPTS, threads=1, started=started)


@pytest.fixture(scope="module")
def runs(background, request):
    """Every script of this module run with ``--quick``, one after another in one fresh process
    (tests/run_experiments.py: the imports paid once, not once per script), in the background."""
    return background.get(request.module.__name__)


def run_script(name: str, runs) -> dict:
    """``experiments/<name>.py --quick --out OUT/<name>`` (run by the ``runs`` fixture): it succeeded and drew its
    figure; its metrics."""
    out, metrics = runs.metrics(name)
    assert (out / f"{name}.png").is_file()
    return metrics


def wrapped(x: float) -> float:
    return math.remainder(x, 2 * math.pi)


def test_fig1_peanut(runs):
    m = run_script("fig1_peanut", runs)
    # A half-period exposure of a sine: two bright ends, dimmer middle (the peanut).
    assert m["n_profile_peaks"] == 2
    assert m["ends_to_middle_ratio"] > 1.3
    lo, hi = m["motion_range_px"]
    left, right = m["profile_peaks_px"]
    assert lo < left < 0 < right < hi
    assert 0.7 < (right - left) / (hi - lo) <= 1.0
    assert m["total_light_e"] == pytest.approx(m["total_light_expected_e"], rel=1e-6)


def test_fig2_true_phase_fixed_alias_moves(runs):
    m = run_script("fig2_cost_vs_phase", runs)
    assert len(m["per_exposure"]) >= 3
    for e in m["per_exposure"]:
        assert len(e["minima_rad"]) == 2
        assert e["true_error_rad"] < 0.05
        assert e["alias_error_rad"] < 0.05  # the alias formula (Proposition 3, corrected sign)
    assert m["true_argmin_spread_rad"] < 0.05  # does not move with the exposure
    assert m["alias_argmin_spread_rad"] > 1.0  # moves with the exposure
    for found, formula in zip(m["alias_argmins_rad"], m["alias_formula_rad"]):
        assert abs(wrapped(found - formula)) < 0.05


def test_fig4_saturation(runs):
    m = run_script("fig4_saturation", runs)
    assert m["saturated_in_data"] is True
    assert abs(m["plateau_adu"] - m["camera_saturation_adu"]) <= 1.0  # quantised to whole ADU
    assert abs(m["slope_rel_error"]) < 0.02
    assert m["linear_limit_s"] == pytest.approx(m["linear_limit_true_s"], rel=0.03)
    assert m["offset_adu"] == pytest.approx(m["dark_level_adu"], abs=20)


def test_fig5_norms(runs):
    m = run_script("fig5_norms", runs)
    for nm in ("l1", "l2", "linf"):
        clean = m["noise_free"][nm]
        assert abs(clean["error_rad"]) < 0.01          # every norm: minimum at the truth
        assert abs(clean["alias_error_rad"]) < 0.01    # ... and at its alias
        assert clean["curvature_per_rad2"] > 0
        assert m["noisy"][nm]["curvature_per_rad2"] > 0
    assert abs(m["noisy"]["l2"]["error_rad"]) < 0.05
    # The 2-norm (maximum likelihood under Gaussian noise) is the least noise-sensitive.
    assert m["noisy"]["l2"]["argmin_std_rad"] < m["noisy"]["linf"]["argmin_std_rad"]


def test_fig6_landscape_two_phase_minima_one_amplitude(runs):
    m = run_script("fig6_landscape", runs)
    da, dp = m["grid"]["amplitude_step_px"], m["grid"]["phase_step_rad"]
    for nm in ("l2", "linf"):
        minima = m[nm]["minima"]
        assert sorted(x["branch"] for x in minima) == ["alias", "true"]
        for x in minima:
            assert abs(x["amplitude_error_px"]) <= da
            assert x["phase_error_rad"] <= dp
            assert x["cost_relative"] < 1e-3
        assert len(m[nm]["amplitude_profile_minima_px"]) == 1  # M has no alias
        assert abs(m[nm]["amplitude_profile_minima_px"][0] - m["true_amplitude_px"]) <= da
        assert len(m[nm]["phase_profile_minima_rad"]) == 2


def test_fig7_dual_exposure_removes_alias(runs):
    m = run_script("fig7_dual_exposure", runs)
    assert m["alias_separation"] == pytest.approx(1.0, abs=1e-6)  # centres a quarter period apart
    for mins, alias in zip(m["single_minima_rad"], m["single_aliases_formula_rad"]):
        assert min(abs(wrapped(x - alias)) for x in mins) < 0.05  # each single exposure has its alias
    assert m["joint_n_local_minima"] == 1                      # the joint cost: one minimum ...
    assert m["joint_argmin_error_rad"] < 0.05                  # ... at the true phase
    assert all(v > 0.1 for v in m["joint_cost_at_aliases_over_max"])
    land = m["landscape"]
    assert land["n_local_minima"] == 1
    best = land["minima"][0]
    assert abs(wrapped(best["phase_rad"] - m["true_phase_rad"])) <= land["phase_step_rad"]
    assert abs(best["amplitude_px"] - m["config"]["amplitude_px"]) <= land["amplitude_step_px"]


def test_fig10_psf_identification(runs):
    m = run_script("fig10_psf", runs)
    assert m["converged"] is True
    assert m["cov_max_entry_error_rel"] < 0.05
    true, fit = m["cov_true_px2"], m["cov_fit_px2"]
    for i in range(2):
        for j in range(2):
            assert fit[i][j] == pytest.approx(true[i][j], rel=0.05)
    assert m["relative_residual"] < 1e-2
    assert 0.5 < m["chi2_per_dof"] < 2.0
