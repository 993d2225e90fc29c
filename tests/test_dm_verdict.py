"""The DM run's verdict (torchblur/identify/verdict.py): hand-built actuator tables (trustworthy, poor
fit, failed, dead and weak named but not flagged, failed spot fits under and over the rule), and
the CLI's exit status and last line on the small DM config (a synthetic run: seconds)."""
import dataclasses
import json

import numpy as np
import pytest

from torchblur.dm.actuator_fit import ActuatorTable, fit_actuators, second_order
from torchblur.identify.verdict import LOST_FRACTION, DMVerdict, dm_verdict, failed_actuators, lost_fraction
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.identify.verdict import EXIT_FLAGGED

FREQ = np.array([100.0, 300.0, 600.0, 900.0, 1500.0])
N, S = 5, 8  # actuators, slopes
PROBLEMS = 16 * FREQ.size * (S // 2)


def _table(status=("ok", "ok", "ok", "weak", "dead"), **changes) -> tuple[ActuatorTable, np.ndarray]:
    """A hand-built table of N actuators (mode 600 Hz, damping 0.1, no delay; actuator 3 at gain
    0.3, 4 dead) and its D ``[S, N, F]`` = G H (no failed fit: every entry finite)."""
    rng = np.random.default_rng(0)
    G = rng.normal(size=(S, N))
    gain = np.array([1.0, 1.0, 1.0, 0.3, 0.0])
    dyn = np.array([1.0, 1.0, 1.0, 1.0, np.nan])  # a dead actuator's dynamics are NaN
    H = second_order(FREQ, gain, 600.0 * dyn, 0.1 * dyn, 0.0 * dyn)
    H[4] = 0.0
    fields = dict(dc_gain=gain, dc_gain_std=np.full(N, 1e-3), mode_hz=600.0 * dyn, mode_hz_std=0.5 * dyn, damping=0.1 * dyn,
                  damping_std=1e-3 * dyn, delay_s=0.0 * dyn, delay_s_std=1e-6 * dyn, status=tuple(status),
                  poor_fit=np.zeros(N, dtype=bool), reduced_chi2=np.array([1.1, 0.9, 1.2, 1.0, np.nan]), static_column=G * gain,
                  static_column_std=np.full((S, N), 1e-3), shape=H, shape_cov=np.tile(np.eye(2) * 1e-6, (N, FREQ.size, 1, 1)),
                  freq_hz=FREQ)
    fields.update(changes)
    D = G[:, :, None] * H[None]
    D[:, 4] = 1e-4 * rng.normal(size=(S, FREQ.size))  # the dead one's column: noise
    return ActuatorTable(**fields), D


def test_trustworthy_names_dead_and_weak_without_flagging_them():
    table, D = _table()
    v = dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS)
    assert isinstance(v, DMVerdict) and v.trustworthy and v.exit_code == 0 and v.flagged == 0
    assert v.line == (f"verdict: trustworthy: all 5 actuators within tolerance: 3 ok, 1 weak (3), 1 dead (4); "
                      f"model reduced chi2 <= 1.2 (chi2 test p >= 0.001 over the run's actuators); 0 of {PROBLEMS} spot fits failed")
    assert (v.ok, v.weak, v.dead, v.poor_fit, v.failed) == ((0, 1, 2), (3,), (4,), (), ())
    assert v.details == () and v.max_reduced_chi2 == pytest.approx(1.2)
    d = json.loads(json.dumps(v.to_dict()))
    assert d["dead"] == [4] and d["weak"] == [3] and d["line"] == v.line and d["exit_code"] == 0


def test_spot_fits_that_do_not_explain_their_images_make_the_run_untrustworthy():
    """Spots the Gaussian PSF or the noise model does not describe (a real lenslet's spot, another
    camera): every actuator's numbers look fine and their stds are too small. Judged from the
    spot fits' reduced chi2: a stray above fit.poor_fit_chi2 is named, more than 1 % of them fail
    the run."""
    from torchblur.identify.verdict import POOR_SPOT_FRACTION

    table, D = _table()
    rng = np.random.default_rng(0)
    chi2 = 1 + 0.06 * rng.standard_normal(PROBLEMS)  # what a model that explains the images gives
    chi2[:3] = 2.5  # strays: 3 of 320, under 1 %
    v = dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS, spot_reduced_chi2=chi2)
    assert v.trustworthy and v.exit_code == 0 and v.poor_spot_fits == 3 and not v.spot_model_fails
    assert "0 of 320 spot fits failed, 3 above reduced chi2 1.5 (median 0.997)" in v.line
    chi2[: int(2 * POOR_SPOT_FRACTION * PROBLEMS)] = 1.9  # 2 %: the model does not describe the spots
    v = dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS, spot_reduced_chi2=chi2)
    assert not v.trustworthy and v.exit_code == EXIT_FLAGGED and v.spot_model_fails and v.flagged == 0
    assert v.line.startswith("verdict: untrustworthy: the spot model does not explain the images") and "every std is too small" in v.line
    assert dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS).poor_spot_fits == 0  # not given: not judged


def test_poor_fit_is_flagged_with_its_inflation():
    chi2 = np.array([1.1, 3.24, 1.2, 1.0, np.nan])
    table, D = _table(poor_fit=np.array([False, True, False, False, False]), reduced_chi2=chi2)
    v = dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS)
    assert not v.trustworthy and v.exit_code == EXIT_FLAGGED == 4
    assert v.line == f"verdict: 1 of 5 actuators flagged: 1 poor fit (1); status 3 ok, 1 weak (3), 1 dead (4); 0 of {PROBLEMS} spot fits failed"
    assert v.details == ("  flagged actuator 1 (ok): poor fit (reduced chi2 3.24, stds x1.8)",)


def test_live_actuator_with_non_finite_estimates_failed_dead_one_not():
    mode = np.array([600.0, np.nan, 600.0, 600.0, np.nan])  # actuator 1 live with no mode; 4 dead (NaN by design)
    std = np.array([1e-3, 1e-3, np.inf, 1e-3, 1e-3])
    table, D = _table(mode_hz=mode, dc_gain_std=std)
    v = dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS)
    assert v.failed == (1, 2) and v.poor_fit == () and v.exit_code == EXIT_FLAGGED
    assert v.line.startswith("verdict: 2 of 5 actuators flagged: 2 failed (1, 2); status 3 ok, 1 weak (3), 1 dead (4)")
    assert "mode_hz not finite" in v.details[0] and "dc_gain_std not finite" in v.details[1]
    # a dead actuator whose DC gain is not finite (its column had no data at all) is failed too
    table, D = _table(dc_gain=np.array([1.0, 1.0, 1.0, 0.3, np.nan]))
    assert dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS).failed == (4,)


def _lose(D, j, n):
    """``D`` with the first ``n`` entries (slope-major) of column ``j`` NaN."""
    D = D.copy()
    col = D[:, j].reshape(-1)
    col[:n] = np.nan
    D[:, j] = col.reshape(S, FREQ.size)
    return D


def test_failed_spot_fits_under_and_over_the_rule():
    table, D = _table()
    entries = S * FREQ.size  # 40 per column
    under = _lose(D, 2, int(LOST_FRACTION * entries))  # 4 of 40: exactly the fraction, not more
    v = dm_verdict(table, D=under, n_failed_spot_fits=7, n_spot_problems=PROBLEMS)
    assert v.trustworthy and v.exit_code == 0 and v.line.endswith(f"; 7 of {PROBLEMS} spot fits failed")
    assert lost_fraction(under)[2] == pytest.approx(LOST_FRACTION)
    over = _lose(D, 2, int(LOST_FRACTION * entries) + 1)  # 5 of 40
    v = dm_verdict(table, D=over, n_failed_spot_fits=9, n_spot_problems=PROBLEMS)
    assert v.failed == (2,) and v.exit_code == EXIT_FLAGGED
    assert v.line == f"verdict: 1 of 5 actuators flagged: 1 failed (2); status 3 ok, 1 weak (3), 1 dead (4); 9 of {PROBLEMS} spot fits failed"
    assert "12.5 % of its column lost to failed spot fits (more than 10 %)" in v.details[0]
    # a slope lost at every frequency leaves D0 without that entry: failed, whatever the fraction
    hole = np.array(table.static_column)
    hole[6, 1] = np.nan
    t2 = dataclasses.replace(table, static_column=hole)
    assert "no static column entry at 1 slope(s)" in failed_actuators(t2, D)[1]


def test_lost_fraction_counts_only_the_support():
    _, D = _table()
    D = D.copy()
    D[:4, 0] = 0.0  # a sparse plan: actuator 0 seen by slopes 4..7 only (exact zeros off its support)
    D[4, 0, :2] = np.nan
    np.testing.assert_allclose(lost_fraction(D), [2 / 20, 0, 0, 0, 0])
    D[:, 1] = 0.0  # a column with no support at all
    assert lost_fraction(D)[1] == 0.0


def test_many_flagged_are_listed_with_more():
    n = 9
    rng = np.random.default_rng(1)
    G = rng.normal(size=(S, n))
    H = second_order(FREQ, np.ones(n), np.full(n, 600.0), np.full(n, 0.1), np.zeros(n))
    one = np.ones(n)
    table = ActuatorTable(dc_gain=one, dc_gain_std=one * 1e-3, mode_hz=one * 600, mode_hz_std=one, damping=one * 0.1,
                          damping_std=one * 1e-3, delay_s=one * 0, delay_s_std=one * 1e-6, status=("ok",) * n,
                          poor_fit=np.ones(n, dtype=bool), reduced_chi2=one * 5.0, static_column=G, static_column_std=G * 0 + 1e-3,
                          shape=H, shape_cov=np.tile(np.eye(2), (n, FREQ.size, 1, 1)), freq_hz=FREQ)
    v = dm_verdict(table, D=G[:, :, None] * H[None], n_failed_spot_fits=0, n_spot_problems=1)
    assert "9 of 9 actuators flagged: 9 poor fit (0, 1, 2, 3, 4, 5, ... 3 more); status 9 ok" in v.line and len(v.details) == 9



def test_every_plan_has_one_verdict_type_and_a_dm_guard_is_one_more_function(monkeypatch):
    """One Verdict type for every plan; a DM rule after the actuators' is a guard in DM_GUARDS:
    final_verdict applies each in order, and a failing one appends its reason, its report line
    and exit 4 through Verdict.untrusted."""
    from types import SimpleNamespace

    from torchblur.identify import verdict as verdict_module
    from torchblur.identify.verdict import ResponseVerdict, Verdict, final_verdict

    table, D = _table()
    res = SimpleNamespace(plan=_every_pair_plan("hadamard"), freq_hz=FREQ, G=np.zeros((S, N)), actuators=table, D=D, n_failed=0,
                          spot_reduced_chi2=None, mirror=None, support_check=None, registration=None)
    v = final_verdict(res, 1.5)
    assert isinstance(v, DMVerdict) and isinstance(v, Verdict) and not issubclass(ResponseVerdict, DMVerdict)
    assert v.trustworthy and v.line == dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=PROBLEMS).line
    guard = lambda v, res: v.untrusted("a new rule fails", "  new rule: why")  # noqa: E731
    monkeypatch.setattr(verdict_module, "DM_GUARDS", (*verdict_module.DM_GUARDS, guard))
    g = final_verdict(res, 1.5)
    assert v.line.startswith("verdict: trustworthy: ")  # its head now says the guard's decision
    assert g.line == "verdict: not trustworthy: " + v.line[len("verdict: trustworthy: "):] + "; a new rule fails"
    assert not g.trustworthy and g.exit_code == EXIT_FLAGGED
    assert g.details == ("  new rule: why",) and json.loads(json.dumps(g.to_dict()))["details"] == ["  new rule: why"]

def _every_pair_plan(kind):
    """A plan of 16 patterns of ``kind`` in which every pattern drives every spot (PROBLEMS spot problems)."""
    from torchblur.dm.plans import Plan
    return Plan(kind, np.ones((16, N)), np.ones((S, N), dtype=bool))


def test_a_ladder_run_on_a_hadamard_plan_is_not_trustworthy_and_names_the_fits_that_left_the_ladder():
    """The ladder guard: a run fitted with the shifted still keeps its verdict; one fitted with the
    ladder on a Hadamard plan is not trustworthy (its actuator stds do not hold on HCIPy's diffraction
    spots: benchmarks/bench_dm_hcipy.py), on a sparse or one-at-a-time plan it keeps its verdict; either
    line names the spot fits whose motion left the ladder's levels (left out of D), with a reason of its
    own above POOR_SPOT_FRACTION."""
    from types import SimpleNamespace

    from torchblur.identify.verdict import POOR_SPOT_FRACTION, final_verdict

    table, D = _table()
    base = dict(freq_hz=FREQ, G=np.zeros((S, N)), actuators=table, D=D, n_failed=0,
                spot_reduced_chi2=None, mirror=None, support_check=None, registration=None)
    had, sparse = _every_pair_plan("hadamard"), _every_pair_plan("sparse")
    v0 = final_verdict(SimpleNamespace(**base, plan=had), 1.5)
    assert v0.trustworthy and final_verdict(SimpleNamespace(**base, plan=had, spot_model="shifted", n_out_of_ladder=0), 1.5) == v0
    lad = final_verdict(SimpleNamespace(**base, plan=had, spot_model="ladder", n_out_of_ladder=0), 1.5)
    assert not lad.trustworthy and lad.exit_code == EXIT_FLAGGED and "on a Hadamard plan pulls each actuator's response" in lad.line
    # every earlier rule held, so the line began "verdict: trustworthy"; its first words now say what the guard decided
    assert v0.line.startswith("verdict: trustworthy: all") and lad.line.startswith("verdict: not trustworthy: all")
    for kind in ("sparse", "one_at_a_time"):
        plan = _every_pair_plan(kind)
        assert final_verdict(SimpleNamespace(**base, plan=plan, spot_model="ladder", n_out_of_ladder=0), 1.5) == v0
    # the run's early warning (identify.dm_plan, once the plan and the spot model are known) fires exactly where the guard stops it
    from torchblur.identify.verdict import LADDER_ON_HADAMARD, ladder_on_hadamard
    for model in ("shifted", "ladder"):
        for kind in ("hadamard", "sparse", "one_at_a_time"):
            v = final_verdict(SimpleNamespace(**base, plan=_every_pair_plan(kind), spot_model=model, n_out_of_ladder=0), 1.5)
            assert ladder_on_hadamard(model, kind) == (LADDER_ON_HADAMARD in v.line) == (not v.trustworthy)
    few = final_verdict(SimpleNamespace(**base, plan=sparse, spot_model="ladder", n_out_of_ladder=1), 1.5)
    assert few.line == v0.line + "; 1 spot fits' motion left the ladder's levels (left out of D; raise dm_plan.ladder_reach)"
    assert few.trustworthy and few.exit_code == v0.exit_code
    n_many = int(POOR_SPOT_FRACTION * v0.spot_problems) + 1
    for plan in (had, sparse):
        many = final_verdict(SimpleNamespace(**base, plan=plan, spot_model="ladder", n_out_of_ladder=n_many), 1.5)
        assert f"{n_many} spot fits' motion left the ladder's levels" in many.line and not many.trustworthy
        assert many.exit_code == EXIT_FLAGGED


def test_bad_arguments_are_named():
    table, D = _table()
    with pytest.raises(ShapeError, match="D: expected"):
        dm_verdict(table, D=D[:, :3], n_failed_spot_fits=0, n_spot_problems=1)
    with pytest.raises(ParameterError, match="n_failed_spot_fits"):
        dm_verdict(table, D=D, n_failed_spot_fits=5, n_spot_problems=4)
    with pytest.raises(ParameterError, match="n_spot_problems"):
        dm_verdict(table, D=D, n_failed_spot_fits=0, n_spot_problems=-1)
    with pytest.raises(InputTypeError, match="n_failed_spot_fits"):
        dm_verdict(table, D=D, n_failed_spot_fits=1.5, n_spot_problems=4)
    with pytest.raises(InputTypeError, match="table"):
        dm_verdict({"status": ()}, D=D, n_failed_spot_fits=0, n_spot_problems=1)


# ------------------------------------------------------------------------------ the CLI
@pytest.fixture(scope="module")
def small_result():
    """A DMResult of the small DM config (tests/test_dm_run.py's SMALL) without the sweep: D is
    the simulated rig's truth plus seeded noise, fitted by fit_actuators (as the DM plan does)."""
    from test_dm_run import SMALL

    from torchblur.identify.dm_plan import DMResult
    from torchblur.rig.factory import build_dm
    from torchblur.dm.plans import choose_plan
    from torchblur.config import load_config

    cfg = load_config(None, SMALL)
    mirror, wfs, rig = build_dm(cfg)
    G = wfs.geometry_matrix(mirror)
    freqs = np.asarray(cfg.frequencies_hz())
    plan, R, info = choose_plan("hadamard", G, budget_frames=None, n_freq=freqs.size, n_exposures=2, n_repeats=1)
    rng = np.random.default_rng(3)
    sd = 2e-3 * np.abs(G).max()
    D = rig.truth_D(freqs) + sd * (rng.normal(size=G.shape + (freqs.size,)) + 1j * rng.normal(size=G.shape + (freqs.size,)))
    D_cov = np.broadcast_to(np.eye(2) * sd**2, D.shape + (2, 2)).copy()
    table = fit_actuators(freqs, D, D_cov, G, actuator_xy=mirror.actuator_xy)
    P = plan.n_patterns
    res = DMResult(freq_hz=freqs, plan=plan, n_repeats=R, plan_info=info, amplitude=np.ones(freqs.size), power=np.ones(freqs.size),
                   Y=np.zeros((P, G.shape[0], freqs.size), complex), Y_cov=np.zeros((P, G.shape[0], freqs.size, 2, 2)), D=D,
                   D_cov=D_cov, actuators=table, G=G, actuator_xy=mirror.actuator_xy, n_frames=P * freqs.size * 2, n_failed=0,
                   timing_s={"calibration": 0.0, "acquisition": 0.0, "fit_wait": 0.0, "estimation": 0.0})
    return SMALL, res


def _run(tmp_path, monkeypatch, res, small, *args):
    from torchblur.cli import commands
    from torchblur.cli import main

    monkeypatch.setattr(commands, "identify", lambda cfg, rig=None, **kw: res)
    out = tmp_path / "run"
    return main(["identify", "--out", str(out), "--quiet", *args, *small, "report.figures=false"]), out  # no figure checked here


def test_cli_trustworthy_exits_0_with_the_verdict_last(tmp_path, monkeypatch, capsys, small_result):
    small, res = small_result
    assert res.actuators.status[2] == "dead" and not res.actuators.poor_fit.any()
    rc, out = _run(tmp_path, monkeypatch, res, small)
    stdout = capsys.readouterr().out
    last = stdout.strip().splitlines()[-1]
    assert rc == 0 and last.startswith("verdict: trustworthy: all 9 actuators within tolerance: 8 ok, 1 dead (2); model reduced chi2")
    assert last.endswith(f"; 0 of {16 * 8 * 12} spot fits failed")
    assert (out / "report.txt").read_text().strip().splitlines()[-1] == last


def test_cli_flagged_exits_4_and_json_has_the_verdict(tmp_path, monkeypatch, capsys, small_result):
    small, res = small_result
    t = res.actuators
    D = res.D.copy()
    D[:, 5, :3] = np.nan  # failed spot fits took 3 of the 8 frequencies of actuator 5's column
    poor = np.zeros(len(t), dtype=bool)
    poor[7] = True
    bad = dataclasses.replace(res, D=D, n_failed=40, actuators=dataclasses.replace(t, poor_fit=poor))
    rc, out = _run(tmp_path, monkeypatch, bad, small, "--json")
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    line = "verdict: 2 of 9 actuators flagged: 1 poor fit (7), 1 failed (5); status 8 ok, 1 dead (2); 40 of 1536 spot fits failed"
    assert rc == EXIT_FLAGGED and summary["verdict"] == line and summary["trustworthy"] is False
    assert summary["actuator_flags"] == {"poor_fit": [7], "failed": [5]} and summary["failed_spot_fits"] == 40
    assert captured.err.strip().splitlines()[-1] == line  # with --json the human lines (the verdict last) go to stderr
    report = (out / "report.txt").read_text().strip().splitlines()
    assert report[-1] == line and report[-2].startswith("  flagged actuator 7 (ok): poor fit")
    assert "37.5 % of its column lost" in report[-3]
