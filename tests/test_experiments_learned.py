"""The learned-model and frequency-response experiments run (--quick) and their claims hold (issue 7)."""
import pytest

from run_experiments import run_scripts

# learned_deblur last: it sets torch.set_flush_denormal(True) for the process
SCRIPTS = ("fig11_frequency_response", "beyond_precision", "learned_deblur")


def BACKGROUND_JOB(out, started):
    """The scripts run with ``--quick`` in the background (tests/background.py) -> their ``Runs``."""
    return run_scripts(out, SCRIPTS, threads=1, started=started)


@pytest.fixture(scope="module")
def runs(background, request):
    """The three scripts run with ``--quick`` (``threads=1``), one after another in one fresh process
    (tests/run_experiments.py: the imports paid once, not once per script), in the background."""
    return background.get(request.module.__name__)


def run_quick(name, runs):
    return runs.metrics(name)


def test_learned_deblur(runs):
    out, m = run_quick("learned_deblur", runs)
    assert (out / "learned_deblur.png").exists() and (out / "loss_curve.png").exists()
    s = m["summary"]
    # two exposures: the phase is learned; one exposure: a branch of the alias, not the truth
    assert s["dual_phase_rmse_vs_truth_deg"] < s["single_phase_rmse_vs_truth_deg"] / 4
    assert s["single_phase_rmse_vs_truth_deg"] > 30
    assert s["single_frac_near_either_branch"] > 0.7
    assert s["single_phase_rmse_vs_nearest_branch_deg"] < s["single_phase_rmse_vs_truth_deg"] / 4
    # the alias is really taken (not just noise): a sizeable share of the distinguishable cases
    assert s["single_frac_near_alias_where_apart"] > 0.1
    assert m["variants"]["dual"]["fitter"]["phase_rmse_vs_truth_deg"] < 1.0


def test_fig11_frequency_response(runs):
    out, m = run_quick("fig11_frequency_response", runs)
    assert (out / "fig11_frequency_response.png").exists() and (out / "fig11_breaking_point.png").exists()
    s = m["summary"]
    assert s["paper_branch_crossings_hz"], "the true phase crosses the branch line (-90 deg) in 1-500 Hz"
    assert s["paper_resolver_branch_errors"] == 0
    assert s["paper_nearest_neighbour_branch_errors"] >= 1
    paper = m[f"paper_single_exposure_{m['config']['paper']['spacing']}"]
    # plain continuity goes wrong only after the crossing
    assert min(paper["nearest_neighbour_error_freq_hz"]) > min(s["paper_branch_crossings_hz"])
    assert s["paper_max_abs_mag_err_pct"] < 1.0 and s["paper_max_abs_phase_err_deg_resolver"] < 1.0
    # the dual design eventually breaks at high frequency (limited input range), not at low
    f_break = s["dual_first_freq_over_1deg_hz"] or s["dual_first_freq_over_1pct_hz"]
    assert f_break is not None and f_break > 500


def test_beyond_precision(runs):
    out, m = run_quick("beyond_precision", runs)
    for name in ("beyond_precision.png", "beyond_psf_error.png", "beyond_bandwidth.png"):
        assert (out / name).exists()
    d = m["dual_exposure"]
    assert d["finite"] and 0 < d["crlb_phase_deg_worst"] < 5
    single = m["single_exposure"]
    # branch crossings and whole periods: (near-)singular Fisher information on the grid
    assert single["n_near_singular_designs"] > 0
    assert single["best_design_at_true_phase"]["crlb_phase_deg"] > 0
    # the fitter reaches the bound (efficiency near 1, with Monte-Carlo scatter)
    assert 0.5 < m["monte_carlo_dual"]["efficiency_phase"] < 2.0
    pe = m["psf_error"]
    assert pe["bias_grows_with_error"]
    zero = pe["sigma_error_pct"].index(0.0)
    assert pe["max_abs_bias_M_px"][zero] < 1e-4
    assert max(pe["max_abs_bias_M_pct"]) > 1.0
