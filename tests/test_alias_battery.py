"""Issue 24 part A: no confident wrong answer from one exposure per point (the alias,
PHYSICS.md Proposition 3) nor against a known truth. Every case either gives the right branch
(the phase within 5 of its stds of the truth) or flags the point ``alias`` / refuses the run;
the truth guard makes any run with a point (or model) beyond 5 std of a known truth
untrustworthy. The phases come from python-control-free numpy plants and, for the image cases,
from torchblur's renderer fitted by fit_sinusoid (the continuity rule never sees the truth)."""
import math

import numpy as np
import pytest
import torch

import torchblur as tb
from torchblur.design.windows import (ANCHOR_STD_RAD, DesignWarning, check_design, continuity_branches, crossing_phase,
                                      dual_exposure_windows, resolve_branches)
from torchblur.errors import ConfigError, InputTypeError, ParameterError, ShapeError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.render.camera import camera_noise_std
from torchblur.identify.assemble import resolve_single_exposure
from torchblur.config import load_config
from torchblur.identify.verdict import EXIT_FLAGGED, TRUTH_BOUND, truth_disagreement, verdict
from torchblur.sysid.alias_resolution import model_branches
from torchblur.sysid.flags import ALIAS, POINT_FLAGS, UNTRUSTED, flag_names, parse_flags
from torchblur.sysid.frequency_response import FrequencyResponse

F64 = torch.float64
SD = math.radians(0.15)  # a point's phase std (rad), as the default run's


def _plant(kind):
    """``H(f)`` (complex numpy) of the battery's plants."""
    cfg = load_config()
    if kind == "default":  # 420 Hz closed-loop mirror, 30 us delay
        num, den, tau = np.array(cfg.plant.num, float), np.array(cfg.plant.den, float), cfg.plant.delay_s
    elif kind == "sharp":  # a lightly damped 300 Hz resonance, 40 us delay
        wn = 2 * np.pi * 300
        num, den, tau = np.array([wn**2]), np.array([1.0, 2 * 0.05 * wn, wn**2]), 40e-6
    else:  # "lowpass": one pole at 100 Hz, 20 us delay: no resonance
        wc = 2 * np.pi * 100
        num, den, tau = np.array([wc]), np.array([1.0, wc]), 20e-6
    return lambda f: np.polyval(num, 2j * np.pi * f) / np.polyval(den, 2j * np.pi * f) * np.exp(-2j * np.pi * f * tau)


def _single_exposure(freqs, H, b, *, frac=0.3, seed=0):
    """The two candidates of a noisy single-exposure sweep, in the arbitrary order a per-point
    fit returns them: ``(omega, cand_a, cand_b, std, |H|, true phase)``."""
    om = 2 * np.pi * freqs
    phi = np.angle(H(freqs))
    win = dual_exposure_windows(torch.tensor(om), fractions=(frac,), trigger_phase=b)[..., 0]
    alias = tb.alias_phase(torch.tensor(phi), torch.tensor(om), win).numpy()
    rng = np.random.default_rng(seed)
    noise = rng.normal(0, SD, om.shape)
    ph, al = phi + noise, alias - noise  # the alias of the noisy estimate
    swap = rng.random(om.shape) > 0.5
    return om, np.where(swap, al, ph), np.where(swap, ph, al), np.full(om.shape, SD), np.abs(H(freqs)), phi


def _right_or_flagged(r, phi, sd):
    err = np.abs(np.angle(np.exp(1j * (r.phase - phi))))
    wrong = err > TRUTH_BOUND * sd
    return wrong, bool((wrong & r.decided).any())


CASES = [("default", 30, math.pi / 2), ("default", 30, 2.2), ("default", 30, 3.0), ("default", 30, 5.5),
         ("default", 10, math.pi / 2), ("default", 10, 2.2), ("default", 6, 2.2), ("default", 60, 2.2),
         ("sharp", 40, math.pi / 2), ("sharp", 40, 2.2), ("sharp", 15, 4.6),
         ("lowpass", 20, math.pi / 2), ("lowpass", 20, 2.2)]


@pytest.mark.parametrize("plant, n, b", CASES)
def test_continuity_is_right_or_flags_the_point(plant, n, b):
    """Single exposure at several trigger phases and plants, with and without resonance
    crossings, dense and sparse: no point decided on the wrong branch."""
    freqs = np.logspace(0, 3, n)
    om, a, c, sd, mag, phi = _single_exposure(freqs, _plant(plant), b, seed=n)
    r = continuity_branches(om, a, c, sd, magnitude=mag)
    wrong, confident_wrong = _right_or_flagged(r, phi, sd)
    assert not confident_wrong, f"decided wrong at {freqs[wrong & r.decided]} Hz"
    assert r.decided[:3].all()  # anchored: the low frequencies are decided (these trigger phases cross far from 0)
    if plant == "lowpass":  # no resonance: decided until the phase nears the crossing (-54 or -90 deg)
        assert r.decided[np.degrees(phi) > -30].all()


def test_the_issue_sweeps_were_wrong_and_are_now_flagged():
    """The issue's runs: sweep.n=6 (1 kHz 57 deg off) and trigger 2.2 (177 deg off): the points
    plain nearest-branch continuity gets wrong are flagged by the rule."""
    H = _plant("default")
    for n, b in ((6, math.pi / 2), (30, 2.2)):
        freqs = np.logspace(0, 3, n)
        om, a, c, sd, mag, phi = _single_exposure(freqs, H, b, seed=1)
        r = continuity_branches(om, a, c, sd, magnitude=mag)
        assert not _right_or_flagged(r, phi, sd)[1]
        assert not r.decided[-1]  # 1 kHz, past the resonance, is never called certain


def test_a_gap_in_the_sweep_across_the_resonance_is_flagged():
    """Dense to 200 Hz, then 800 Hz and 1 kHz: the resonance (420 Hz) falls in the gap."""
    freqs = np.concatenate([np.logspace(0, np.log10(200), 12), [800.0, 1000.0]])
    om, a, c, sd, mag, phi = _single_exposure(freqs, _plant("default"), 2.2, seed=3)
    r = continuity_branches(om, a, c, sd, magnitude=mag)
    assert not _right_or_flagged(r, phi, sd)[1]
    assert not r.decided[12] and r.decided[:12].all()


def test_a_crossing_at_the_low_frequency_phase_flags_everything():
    """A trigger phase that puts the branches' crossing near 0 deg, the phase at the lowest
    frequency: the rule cannot anchor the sweep; every point is flagged, and the design check
    says so before the run."""
    b = 0.5  # c = b + 0.3 pi: crossing (pi - 2c) / 2 = 7.6 deg
    freqs = np.logspace(0, 3, 20)
    om, a, c, sd, mag, phi = _single_exposure(freqs, _plant("default"), b, seed=4)
    r = continuity_branches(om, a, c, sd, magnitude=mag)
    assert not r.decided.any()
    win = dual_exposure_windows(torch.tensor(om), fractions=(0.3,), trigger_phase=b)
    x = float(torch.rad2deg(crossing_phase(torch.tensor(om[:1]), win[:1, 0]))[0])
    assert abs(x - math.degrees(math.pi / 2 - b - 0.3 * math.pi)) < 1e-9
    with pytest.warns(DesignWarning, match="cannot anchor"):
        msgs = check_design(torch.tensor(om), win)
    assert len(msgs) == 1 and f"crossing at {x:.0f} deg" in msgs[0]


def test_the_design_check_of_one_exposure_names_the_crossing_and_two_exposures_pass():
    om = torch.tensor(2 * np.pi * np.logspace(0, 3, 8))
    one = dual_exposure_windows(om, fractions=(0.3,), trigger_phase=math.pi / 2)
    msgs = check_design(om, one, warn=False)
    assert len(msgs) == 1 and "crossing at -54 deg" in msgs[0] and "never trustworthy" in msgs[0] and "anchor" not in msgs[0]
    assert check_design(om, dual_exposure_windows(om, fractions=(0.3, 0.8)), warn=False) == []


def test_hypotheses_past_the_limit_leave_every_later_point_undecided():
    freqs = np.logspace(0, 3, 30)
    om, a, c, sd, mag, phi = _single_exposure(freqs, _plant("default"), 0.5, seed=5)
    r1 = continuity_branches(om, a, c, sd, magnitude=mag, max_hypotheses=1)
    assert not r1.decided[1:].any()
    # resolve_branches (the old entry point) is this rule's primary choice
    rb = resolve_branches(torch.tensor(om), torch.tensor(a), torch.tensor(c)).numpy()
    r0 = continuity_branches(om, a, c, max_hypotheses=1)
    np.testing.assert_allclose(rb, r0.phase, rtol=0, atol=1e-12)


def test_continuity_refuses_bad_input():
    om = np.array([1.0, 2.0, 2.0])
    with pytest.raises(ParameterError, match="omega"):
        continuity_branches(om, np.zeros(3), np.zeros(3))
    with pytest.raises(ParameterError, match="alias"):
        continuity_branches(np.array([1.0, 2.0]), np.zeros(2), np.zeros(3))


def _frf(freqs, H, b, *, seed=0, frac=0.3):
    """A SISO response as the per-point fits leave it (either branch), its alias phase and the truth."""
    om, a, c, sd, mag, phi = _single_exposure(freqs, H, b, seed=seed, frac=frac)
    cov = np.zeros((len(om), 2, 2))
    cov[:, 0, 0] = (1e-3 * mag) ** 2
    cov[:, 1, 1] = sd**2
    cov[:, 0, 1] = cov[:, 1, 0] = 0.3 * 1e-3 * mag * sd
    return FrequencyResponse(om, mag * np.exp(1j * a), cov=cov), c, H(freqs)


def test_resolve_single_exposure_on_a_response_and_the_verdict():
    """The sine plan's step on a FrequencyResponse: the alias taken where the rule says so (its
    covariance's magnitude-phase term changes sign); past the resonance, where continuity alone
    decides nothing, the model of the decided points and the undecided points' magnitudes decides
    (model_branches); with the truth, no point beyond 5 std is left unflagged. A sweep the rule
    cannot anchor stays flagged alias: the verdict untrustworthy and naming them."""
    freqs = np.logspace(0, 3, 30)
    frf, alias, truth = _frf(freqs, _plant("default"), 2.2, seed=7)
    before = verdict(frf)
    assert before.trustworthy  # without the step (and the truth) the issue's run looked fine
    out = resolve_single_exposure(frf, alias[None, None], np.ones(30, dtype=bool))
    took = np.abs(np.angle(out.response[0, 0] * np.conj(frf.response[0, 0]))) > 1e-12
    assert took.any()
    np.testing.assert_array_equal(np.sign(out.cov[0, 0, took, 0, 1]), -np.sign(frf.cov[0, 0, took, 0, 1]))
    flagged = (out.flags[0, 0] & ALIAS) != 0
    _, _, z = out.errors_against(truth)
    assert not (z[0, 0] > TRUTH_BOUND)[~flagged].any()
    alone = continuity_branches(frf.omega, frf.phase[0, 0], alias, frf.phase_std[0, 0], magnitude=frf.magnitude[0, 0])
    assert (~alone.decided[freqs > 400]).all() and int(flagged.sum()) < int((~alone.decided).sum())
    assert verdict(out, truth=truth).trustworthy == (not flagged.any())
    # points whose exposures resolved the alias are left alone
    same = resolve_single_exposure(frf, alias[None, None], np.zeros(30, dtype=bool))
    assert same is frf
    frf, alias, truth = _frf(freqs, _plant("default"), 0.5, seed=7)  # the crossing at 8 deg: no anchor
    out = resolve_single_exposure(frf, alias[None, None], np.ones(30, dtype=bool))
    flagged = (out.flags[0, 0] & ALIAS) != 0
    v = verdict(out)
    assert flagged.all() and not v.trustworthy and v.exit_code == EXIT_FLAGGED and v.alias == 30
    assert f"{v.alias} alias (" in v.line and "one exposure" in v.line


def test_the_model_step_decides_past_the_crossing_and_never_wrongly():
    """model_branches on the continuity rule's output (the default plant and a sharp 300 Hz
    resonance): every point it decides is on the right branch (within 5 of its stds of the
    truth), and past the resonance it decides what continuity could not. Bad input is refused by
    name. (benchmarks/bench_alias.py --sweep runs it over 8 trigger phases x 3 seeds of the
    default run.)"""
    decided_after = 0
    for plant, n, b in (("default", 30, math.pi / 2), ("sharp", 40, 2.2)):
        freqs = np.logspace(0, 3, n)
        frf, alias, truth = _frf(freqs, _plant(plant), b, seed=n + 1)
        r = continuity_branches(frf.omega, frf.phase[0, 0], alias, frf.phase_std[0, 0], magnitude=frf.magnitude[0, 0])
        cov = np.array(frf.cov[0, 0])
        cov[r.took_alias, 0, 1] *= -1
        cov[r.took_alias, 1, 0] *= -1
        cont = frf.replace(response=(frf.magnitude[0, 0] * np.exp(1j * r.phase))[None, None], cov=cov[None, None])
        other = np.where(r.took_alias, frf.phase[0, 0], alias)
        out, und = model_branches(cont, other, ~r.decided)
        assert not (und & r.decided).any()
        _, _, z = out.errors_against(truth)
        assert not (z[0, 0] > TRUTH_BOUND)[~und].any(), (plant, b, freqs[(z[0, 0] > TRUTH_BOUND) & ~und])
        decided_after += int((~und & ~r.decided & (freqs > (420 if plant == "default" else 300))).sum())
    assert decided_after >= 4
    with pytest.raises(ShapeError, match="other_phase, undecided"):
        model_branches(cont, other[:3], ~r.decided)
    with pytest.raises(InputTypeError, match="frf"):
        model_branches(frf.response, other, ~r.decided)


def test_the_two_axes_of_a_spot_follow_the_axis_that_moves():
    """A spot's x and y come from one fit: time reversal flips both, so the moving axis decides
    and the other follows, flags included."""
    freqs = np.logspace(0, 3, 20)
    H = _plant("default")
    frf1, alias, _ = _frf(freqs, H, 2.2, seed=8)
    small = 1e-3 * frf1.response[0, 0] * np.exp(0.4j)  # a cross axis with little motion
    resp = np.stack([frf1.response[0, 0], small])[:, None]
    cov = np.stack([frf1.cov[0, 0], frf1.cov[0, 0] * 1e-6])[:, None]
    frf = FrequencyResponse(frf1.omega, resp, cov=cov, input_labels=["x"], output_labels=["x", "y"])
    alias2 = np.stack([alias, np.angle(small) + 0.1])[:, None]
    out = resolve_single_exposure(frf, alias2, np.ones((2, 1, 20), dtype=bool), axis_of=np.array([0, 0]))
    took = [np.abs(np.angle(out.response[o, 0] * np.conj(frf.response[o, 0]))) > 1e-12 for o in range(2)]
    np.testing.assert_array_equal(took[0], took[1])
    np.testing.assert_array_equal(out.flags[0, 0], out.flags[1, 0])


@pytest.mark.parametrize("b", [math.pi / 2, 2.2])
def test_single_exposure_images_fitted_then_resolved(b):
    """Rendered single-exposure images of the default plant at 8 frequencies, fitted by
    fit_sinusoid (which returns either branch), resolved by continuity: every point right
    within 5 of its stds, or flagged alias."""
    freqs = np.array([5.0, 20.0, 60.0, 120.0, 200.0, 300.0, 420.0, 700.0])
    H = _plant("default")
    h = H(freqs)
    om = torch.tensor(2 * np.pi * freqs, dtype=F64)
    M = torch.tensor(6.0 * np.abs(h) / np.abs(h).max() + 2.0, dtype=F64)
    A = M / torch.tensor(np.abs(h))
    win = dual_exposure_windows(om, fractions=(0.3,), trigger_phase=b)
    g = torch.Generator().manual_seed(11)
    cen = torch.tensor([16.0, 12.0], dtype=F64).expand(8, 2)
    psf = tb.GaussianPSF.isotropic(cen, torch.full((8,), 1.8, dtype=F64))
    traj = tb.Sinusoid(torch.stack([M, torch.zeros_like(M)], -1)[:, None], torch.tensor(np.angle(h), dtype=F64)[:, None, None]
                       .expand(8, 1, 2), om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=24, width=32)
    sigma = 0.01 * clean.amax((-1, -2, -3))
    imgs = clean + sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64)
    fit = fit_sinusoid(imgs, psf, win, om, noise_std=sigma, axes="x")
    mag, ph = (fit.amplitude / A).numpy(), fit.phase.numpy()
    cov = np.zeros((8, 2, 2))
    cov[:, 0, 0] = (fit.amplitude_std / A).numpy() ** 2
    cov[:, 1, 1] = fit.phase_std.numpy() ** 2
    frf = FrequencyResponse(om.numpy(), mag * np.exp(1j * ph), cov=cov)
    out = resolve_single_exposure(frf, fit.alias_phase.numpy()[None, None], np.ones(8, dtype=bool))
    _, _, z = out.errors_against(h)
    flagged = (out.flags[0, 0] & ALIAS) != 0
    assert not (z[0, 0] > TRUTH_BOUND)[~flagged].any(), (z, flagged)
    assert not flagged[:3].any()  # below the resonance the branch is decided
    assert verdict(out, truth=h).trustworthy == (not flagged.any())


@pytest.mark.parametrize("repeats", [1, 2])
def test_a_spot_near_the_crossing_is_not_left_on_it(repeats):
    """One exposure (and its repeats, as the spots config takes it): a spot moving on both axes
    with phases a few degrees from the branches' crossing. Gauss-Newton started there used to
    stay on the crossing (the image's phase derivative vanishes by symmetry), with a phase std
    of ~1e15 deg and a magnitude 13 std off (the spots config's one-exposure run, 489 Hz). Now
    every item leaves it or is flagged (not converged, in the flat valley there): a finite phase
    std and phase and magnitude within 5 std of the truth or of its alias (the branch is
    continuity's job)."""
    f, n = 500.0, 6
    om = 2 * math.pi * f
    win = tb.ExposureWindow(torch.full((n, repeats), 0.1 / f, dtype=F64), torch.full((n, repeats), 0.3 / f, dtype=F64))
    chi = float(tb.alias_phase(torch.tensor(0.0, dtype=F64), om, win[0, 0])) / 2
    off = np.radians([-4.0, -2.0, 6.0, -3.0, 3.0, 5.0])
    phase = torch.tensor(np.stack([chi + off, chi + 0.8 * off], -1))
    amp = torch.tensor([3.0, 1.5], dtype=F64).expand(n, 2)
    psf = tb.GaussianPSF.isotropic(torch.tensor([16.0, 16.0], dtype=F64).expand(n, 2), torch.full((n,), 1.5, dtype=F64))
    psf = tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * 2e6)
    clean = tb.render_blur(tb.Sinusoid(amp[:, None], phase[:, None], om), tb.GaussianPSF(psf.center[:, None], psf.cov[:, None],
                           psf.amplitude[:, None]), win, height=32, width=32)
    g = torch.Generator().manual_seed(0)
    imgs = torch.poisson(clean, generator=g) + 3.0 * torch.randn(clean.shape, generator=g, dtype=F64)
    fit = fit_sinusoid(imgs, psf, win, torch.full((n,), om, dtype=F64), axes="xy", noise_std=camera_noise_std(clean, 3.0))
    ok = fit.status == 0  # a fit left in the flat valley at the crossing says so (not converged)
    assert int(ok.sum()) >= 5, fit.status
    assert (fit.phase_std[ok] < 0.5).all(), fit.phase_std
    z_amp = ((fit.amplitude - amp) / fit.amplitude_std).abs()[ok]
    err = torch.stack([(fit.phase - phase + math.pi) % (2 * math.pi) - math.pi,
                       (fit.alias_phase - phase + math.pi) % (2 * math.pi) - math.pi]).abs()[:, ok] / fit.phase_std[ok]
    assert (z_amp < TRUTH_BOUND).all(), z_amp
    assert (err.amin(0) < TRUTH_BOUND).all(), err


def test_a_mislabelled_exposure_shows_in_the_fit():
    """An exposure recorded as 30 % of the period that lasted 36 %: the fit's reduced chi2 goes
    above the poor-fit bound (the point is flagged poor_fit) or its answer is still right."""
    om = torch.tensor([2 * math.pi * 150.0], dtype=F64)
    true_win = dual_exposure_windows(om, fractions=(0.36, 0.8), trigger_phase=1.0)
    told_win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=1.0)
    psf = tb.GaussianPSF.isotropic(torch.tensor([[16.0, 12.0]], dtype=F64), torch.tensor([1.8], dtype=F64))
    traj = tb.Sinusoid(torch.tensor([[[7.0, 0.0]]], dtype=F64), torch.tensor([[[-0.7, -0.7]]], dtype=F64), om[:, None])
    clean = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), true_win, height=24, width=32)
    sigma = 0.01 * clean.amax((-1, -2, -3))
    imgs = clean + sigma[:, None, None, None] * torch.randn(clean.shape, generator=torch.Generator().manual_seed(2), dtype=F64)
    fit = fit_sinusoid(imgs, psf, told_win, om, noise_std=sigma, axes="x")
    right = abs(float(tb.wrap_phase(fit.phase[0] + 0.7))) < TRUTH_BOUND * float(fit.phase_std[0]) and \
        abs(float(fit.amplitude[0]) - 7.0) < TRUTH_BOUND * float(fit.amplitude_std[0])
    assert right or float(fit.reduced_chi2.reshape(-1)[0]) > 1.5


def test_the_truth_guard_names_the_points_and_the_model():
    """The guard cannot be argued with: no flag set, yet a point beyond 5 std of the known truth
    (or a model that far from it) makes the run untrustworthy, and the line names where."""
    freqs = np.logspace(0, 3, 12)
    H = _plant("default")
    frf, _, truth = _frf(freqs, H, 2.2, seed=9)
    good = frf.replace(response=np.abs(truth) * np.exp(1j * np.angle(truth)) * (1 + 0.5e-3))
    v = verdict(good, truth=truth)
    assert v.trustworthy and v.beyond_truth == 0 and v.model_beyond_truth == 0
    bad = good.replace(response=np.where(np.arange(12) == 10, good.response * np.exp(1j * 0.2), good.response))
    v = verdict(bad, truth=truth)
    assert not v.trustworthy and v.exit_code == EXIT_FLAGGED and v.beyond_truth == 1 and v.flagged == 0
    assert f"beyond 5 std of the known truth ({freqs[10]:.4g} Hz)" in v.line
    # a model 1 % off everywhere: beyond 5 point stds (0.1 %) at every point
    model = type("M", (), {"frequency_response": staticmethod(lambda w: 1.01 * H(np.asarray(w) / (2 * np.pi)))})()
    v = verdict(good, truth=truth, model=model)
    assert not v.trustworthy and v.model_beyond_truth == 12 and "the model beyond 5 std of the known truth" in v.line
    p, m = truth_disagreement(good, None)
    assert p is None and m is None and verdict(bad).trustworthy  # without a truth the guard says nothing


def test_the_alias_flag_is_written_and_read_back(tmp_path):
    assert POINT_FLAGS[ALIAS] == "alias" and UNTRUSTED & ALIAS and parse_flags(flag_names(ALIAS | 1)) == ALIAS | 1
    freqs = np.logspace(0, 3, 5)
    frf, _, _ = _frf(freqs, _plant("default"), 2.2)
    frf = frf.replace(flags=np.array([[[0, ALIAS, 0, ALIAS | 1, 0]]]))
    frf.to_csv(tmp_path / "frf.csv")
    frf.to_json(tmp_path / "frf.json")
    frf.to_mat(tmp_path / "frf.mat")
    assert "alias" in (tmp_path / "frf.csv").read_text().splitlines()[2]
    for back in (FrequencyResponse.from_csv(tmp_path / "frf.csv"), FrequencyResponse.from_json(tmp_path / "frf.json")):
        np.testing.assert_array_equal(back.flags, frf.flags)
    from scipy.io import loadmat

    np.testing.assert_array_equal(np.asarray(loadmat(tmp_path / "frf.mat")["flags"]).reshape(-1), frf.flags.reshape(-1))


@pytest.mark.parametrize("exposures", ["[0.3]", "[0.3,1.3]"])
def test_the_dm_route_refuses_exposures_that_leave_the_alias(exposures):
    with pytest.raises(ConfigError, match=r"sweep\.exposures: .* do not resolve the alias"):
        load_config("configs/identify_dm.yaml", [f"sweep.exposures={exposures}"])


def test_anchor_std_is_the_documented_ten_degrees():
    assert ANCHOR_STD_RAD == pytest.approx(math.radians(10.0))


def test_the_dm_truth_guard_names_the_actuators():
    """A simulated DM run: an actuator beyond 5 std of the mirror's truth, or a live one reported
    dead, makes the run untrustworthy whatever its flags; without a truth nothing changes."""
    from types import SimpleNamespace

    from torchblur.identify.verdict import DMVerdict, truth_disagreement_dm, truth_guard

    mirror = SimpleNamespace(dead=np.array([False, True, False, False]), gain=np.array([1.0, 0.0, 1.0, 1.0]),
                             mode_hz=np.full(4, 2000.0), damping=np.full(4, 0.1))
    act = SimpleNamespace(status=("ok", "dead", "ok", "dead"), dc_gain=np.array([1.001, np.nan, 1.1, np.nan]),
                          dc_gain_std=np.full(4, 0.002), mode_hz=np.array([2001.0, np.nan, 2000.0, np.nan]), mode_hz_std=np.full(4, 1.0), damping=np.full(4, 0.1),
                          damping_std=np.full(4, 0.01))
    assert truth_disagreement_dm(act, mirror) == (2, 3)
    v = DMVerdict(line="verdict: trustworthy: all 4 actuators within tolerance", trustworthy=True, exit_code=0, actuators=4, flagged=0,
                  poor_fit=(), failed=(), ok=(0, 2, 3), weak=(), dead=(1,), failed_spot_fits=0, spot_problems=10, max_reduced_chi2=1.0)
    g = truth_guard(v, SimpleNamespace(mirror=mirror, actuators=act))
    assert not g.trustworthy and g.exit_code == EXIT_FLAGGED and g.beyond_truth == (2, 3) and "(2, 3)" in g.line
    assert truth_guard(v, SimpleNamespace(mirror=None)) is v
