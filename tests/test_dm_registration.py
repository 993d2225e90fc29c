"""The mirror's registration fitted to the measured D0 (torchblur.dm.registration, issue 23 part C)."""
import json
import math

import numpy as np
import pytest

from torchblur.dm.actuator_fit import fit_actuators
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.plans import sparse_plan
from torchblur.dm.registration import (EDGE_TEST_P, Registration, diffraction_quadrature, fit_registration, fully_lit, interior,
                                       read_registration_json, register_and_refit, registration_model, support_check,
                                       write_registration_json)
from torchblur.dm.shack_hartmann import ShackHartmann, lit_rows, mean_slopes
from torchblur.errors import ConfigError, ParameterError, ShapeError

MISREG = Registration(shift_x=0.25, shift_y=-0.25, rotation_deg=1.5, magnification=1.03, coupling=0.17)


def _small(oversample=8):
    mirror = DeformableMirror.build(4, coupling=0.15)  # 12 actuators
    wfs = ShackHartmann(n_across=5, pupil_diameter=4.0, oversample=oversample)  # 21 valid subapertures, partly lit edges
    return mirror, wfs


def test_model_is_mean_slopes_at_the_registration_and_its_derivatives():
    mirror, wfs = _small()
    G_ref = wfs.geometry_matrix(mirror, registration=MISREG)
    # the reference itself: mean_slopes with the registration is mean_slopes at the moved actuators and the wider influence
    w = MISREG.magnification * 1 / math.sqrt(-2 * math.log(MISREG.coupling))
    moved = mean_slopes(wfs.centres, wfs.side, 2.0, MISREG.actuators(mirror.actuator_xy), math.exp(-1 / (2 * w * w)), 8)
    np.testing.assert_allclose(G_ref, wfs.slope_px * moved, rtol=0, atol=1e-15)
    a = math.radians(1.5)
    np.testing.assert_allclose(MISREG.actuators([[1.0, 0.0]]), [[1.03 * math.cos(a) + 0.25, 1.03 * math.sin(a) - 0.25]])
    rows = (lit_rows(wfs.centres, wfs.side, 2.0, 8), lit_rows(wfs.centres[:, ::-1], wfs.side, 2.0, 8))
    theta = np.array([0.25, -0.25, a, 1.03, 1 / math.sqrt(-2 * math.log(0.17))])
    G, dG = registration_model(theta, rows, mirror.actuator_xy, wfs.slope_px)
    np.testing.assert_allclose(G, G_ref, rtol=0, atol=1e-13 * np.abs(G_ref).max())
    for k in range(5):
        e = np.zeros(5)
        e[k] = 1e-6
        num = (registration_model(theta + e, rows, mirror.actuator_xy, 1.0)[0]
               - registration_model(theta - e, rows, mirror.actuator_xy, 1.0)[0]) / 2e-6
        np.testing.assert_allclose(dG[k], num, rtol=0, atol=1e-7 * np.abs(dG[k]).max())
    # with the sensor weighting beta: (1 - beta) G_mean + beta G_diffraction, and its derivatives
    quad = diffraction_quadrature(wfs.centres, wfs.side, 2.0)
    th6 = np.append(theta, 0.7)
    G6, dG6 = registration_model(th6, rows, mirror.actuator_xy, 1.0, quad)
    Gd = registration_model(np.append(theta, 1.0), rows, mirror.actuator_xy, 1.0, quad)[0]
    np.testing.assert_allclose(G6, 0.3 * G_ref + 0.7 * Gd, rtol=0, atol=1e-13 * np.abs(G_ref).max())
    for k in range(6):
        e = np.zeros(6)
        e[k] = 1e-6
        num = (registration_model(th6 + e, rows, mirror.actuator_xy, 1.0, quad)[0]
               - registration_model(th6 - e, rows, mirror.actuator_xy, 1.0, quad)[0]) / 2e-6
        np.testing.assert_allclose(dG6[k], num, rtol=0, atol=1e-7 * np.abs(dG6[k]).max())


def test_diffraction_weighting_is_the_best_fit_shift_of_a_square_lenslets_spot():
    """The weight K(a) B(b) of the module docstring: the least-squares shift of the diffraction
    spot of a square lenslet (an FFT of its pupil, zero padded: the whole focal plane) under a
    small phase is the K B-weighted mean of its x slope, not the plain mean."""
    n, pad = 32, 512
    u = (np.arange(n) + 0.5) / n - 0.5  # pupil samples over the side, [-1/2, 1/2]
    y, x = np.meshgrid(u, u, indexing="ij")

    def image(phase):
        e = np.zeros((pad, pad), complex)
        e[:n, :n] = np.exp(1j * phase)
        return np.abs(np.fft.fft2(e)) ** 2

    eps = 1e-3
    tilt = (image(eps * x) - image(-eps * x)) / (2 * eps)  # the image's change per unit mean x slope

    def shift(phase):  # best-fit shift, per unit of the tilt's
        dI = (image(eps * phase) - image(-eps * phase)) / (2 * eps)
        return float((dI * tilt).sum() / (tilt * tilt).sum())

    K, B = 5 / 64 - 3 * x**2 / 8 + x**4 / 4, 3 / 4 - y**2
    for phase, slope in ((x**3, 3 * x**2), (x * y**2, y**2), (x**3 + x**2 * y, 3 * x**2 + 2 * x * y)):
        weighted, plain = float((K * B * slope).sum() / (K * B).sum()), float(slope.mean())
        assert abs(shift(phase) - weighted) < 1e-2 * abs(plain) and abs(weighted - plain) > 0.05 * abs(plain)


def _noisy_D0(G, gain, rng, rel=2e-3):
    std = np.full_like(G, rel * np.abs(G).max())
    return G * gain + std * rng.standard_normal(G.shape), std


def test_fit_recovers_a_misregistration_with_honest_stds():
    mirror, wfs = _small()
    G_true = wfs.geometry_matrix(mirror, registration=MISREG)
    z, gz = [], []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        gain = 1 + 0.05 * rng.standard_normal(12)
        gain[3], gain[7] = 0.0, 0.3 * gain[7]  # a dead and a weak actuator do not drag the registration
        D0, std = _noisy_D0(G_true, gain, rng)
        fit = fit_registration(D0, std, wfs, mirror.actuator_xy, coupling=0.15)
        r = fit.registration
        assert fit.ok and fit.dof == D0.size - 12 - 6 and 0.6 < fit.reduced_chi2 < 1.4 and fit.fitted_on == "every subaperture"
        err = np.array([r.shift_x - 0.25, r.shift_y + 0.25, r.rotation_deg - 1.5, r.magnification - 1.03, r.coupling - 0.17,
                        fit.diffraction_weight])  # a mean-slope sensor: weighting 0
        assert np.all(np.abs(err[:4]) < [0.02, 0.02, 0.1, 0.003])
        z.append(err / np.array([fit.std[k] for k in ("shift_x", "shift_y", "rotation_deg", "magnification", "coupling",
                                                      "diffraction_weight")]))
        live = gain > 0
        gz.append((fit.gain - gain)[live] / np.sqrt(std[0, 0] ** 2 / (fit.G[:, live] ** 2).sum(0) + fit.gain_var_registration[live]))
    rms = np.sqrt(np.mean(np.square(z), 0))
    assert np.all((rms > 0.6) & (rms < 1.45)), rms  # 12 seeds: rms of 12 unit normals within these bounds at p > 0.99
    assert 0.75 < np.sqrt(np.mean(np.square(gz))) < 1.3


def test_refit_on_the_fitted_geometry_gives_the_true_gains():
    """D(jw) of a misregistered mirror with known noise: the actuators fitted on the nominal G
    carry the geometry's error in dc_gain; refitted on the fitted registration they do not."""
    mirror = DeformableMirror.build(4, coupling=0.15, mode_hz=800.0, mode_spread=0.05, gain_spread=0.05, dead=[3], seed=1)
    wfs = ShackHartmann(n_across=5, pupil_diameter=4.0, oversample=8)
    f = np.geomspace(50.0, 2000.0, 10)
    G_true = wfs.geometry_matrix(mirror, registration=MISREG)
    rng = np.random.default_rng(3)
    D_true = G_true[:, :, None] * mirror.response(f)[None]
    s = 1e-3 * np.abs(G_true).max()
    D = D_true + s * (rng.standard_normal(D_true.shape) + 1j * rng.standard_normal(D_true.shape))
    cov = np.broadcast_to(s * s * np.eye(2), D.shape + (2, 2)).copy()
    table0 = fit_actuators(f, D, cov, wfs.geometry_matrix(mirror), actuator_xy=mirror.actuator_xy)
    table, fit, info = register_and_refit(f, D, cov, table0, wfs, mirror.actuator_xy, 0.15, support=np.ones(D.shape[:2], bool))
    live = ~mirror.dead
    z0 = (table0.dc_gain - mirror.gain)[live] / table0.dc_gain_std[live]
    z = (table.dc_gain - mirror.gain)[live] / table.dc_gain_std[live]
    assert np.sqrt(np.mean(z0**2)) > 10  # the nominal geometry is wrong by far more than the noise
    assert np.sqrt(np.mean(z**2)) < 2.0 and np.abs(table.dc_gain - mirror.gain)[live].max() < 0.01
    assert table.status[3] == "dead" and info["n_missing"] == 0
    assert abs(fit.registration.shift_x - 0.25) < 0.02 and abs(fit.registration.rotation_deg - 1.5) < 0.1
    np.testing.assert_allclose(table.mode_hz[live], mirror.mode_hz[live], rtol=5e-3)


def test_plan_support_rechecked_against_the_fitted_geometry():
    mirror, wfs = _small()
    G_nom = wfs.geometry_matrix(mirror)
    plan = sparse_plan(G_nom, 0.01)
    assert support_check(plan.support, G_nom, 0.01)["n_missing"] == 0
    far = wfs.geometry_matrix(mirror, registration=Registration(shift_x=0.5, rotation_deg=5.0))
    info = support_check(plan.support, far, 0.01)
    M = wfs.n_valid
    assert info["n_missing"] > 0 and info["largest_missing_over_max"] > 0.01
    for m, j in info["missing"]:
        assert not plan.support[m, j] and math.hypot(far[m, j], far[M + m, j]) > 0.01 * np.hypot(far[:M], far[M:]).max()
    # a pair on the threshold within 3 stds of the registration's uncertainty is not flagged
    assert support_check(plan.support, far, 0.01, G_std=np.abs(far))["n_missing"] == 0


def test_registration_json_reads_back_and_bad_input(tmp_path):
    mirror, wfs = _small()
    rng = np.random.default_rng(0)
    D0, std = _noisy_D0(wfs.geometry_matrix(mirror, registration=MISREG), np.ones(12), rng)
    fit = fit_registration(D0, std, wfs, mirror.actuator_xy, coupling=0.15)
    write_registration_json(tmp_path / "registration.json", fit, {"missing": [], "n_missing": 0})
    doc = read_registration_json(tmp_path / "registration.json")
    assert doc["registration"] == fit.registration and doc["units"]["shift_x"] == "actuator pitch" and doc["units"]["rotation_deg"] == "deg"
    assert doc["std"]["magnification"] == fit.std["magnification"] and "fitted registration" in doc["dc_gain_reference"]
    assert doc["edge_test"] == fit.edge_test  # None: the small sensor has no interior subaperture
    assert doc["sensor"]["diffraction_weight"] == fit.diffraction_weight and doc["sensor"]["fitted_on"] == fit.fitted_on
    assert doc["std"]["diffraction_weight"] == fit.std["diffraction_weight"]
    raw = json.loads((tmp_path / "registration.json").read_text())
    raw["schema_version"] = 99
    (tmp_path / "bad.json").write_text(json.dumps(raw))
    with pytest.raises(ParameterError, match="schema"):
        read_registration_json(tmp_path / "bad.json")
    # too few entries: not fitted, flagged, never raises; the start's geometry
    few = np.full_like(std, np.nan)
    few[:3, :2] = std[:3, :2]
    bad = fit_registration(D0, few, wfs, mirror.actuator_xy, coupling=0.15)
    assert not bad.ok and "fewer than the unknowns" in bad.message and np.allclose(bad.G, wfs.geometry_matrix(mirror))
    with pytest.raises(ShapeError, match="D0"):
        fit_registration(D0[:, :5], std[:, :5], wfs, mirror.actuator_xy, coupling=0.15)
    with pytest.raises(ParameterError, match="magnification"):
        Registration(magnification=0.0)


def test_simulated_mirror_takes_the_registration_from_the_config():
    from torchblur.rig.factory import build_dm
    from torchblur.config import load_config

    base = ["dm.n_across=3", "wfs.n_across=4", "wfs.oversample=8", "excitation.target_px=3.0"]
    keys = ["dm.registration.shift_x=0.25", "dm.registration.rotation_deg=1.5", "dm.registration.magnification=1.03"]
    mirror, wfs, rig = build_dm(load_config(None, base + keys, force=True))
    assert rig.registration == Registration(shift_x=0.25, rotation_deg=1.5, magnification=1.03)
    np.testing.assert_array_equal(rig.geometry, wfs.geometry_matrix(mirror, registration=rig.registration))
    assert not np.allclose(rig.geometry, wfs.geometry_matrix(mirror))
    for bad, key in (("dm.registration.magnification=2.0", "dm.registration.magnification"),
                     ("dm.registration.coupling=1.5", "dm.registration.coupling"), ("dm.registration.tilt=1", "dm.registration.tilt")):
        with pytest.raises(ConfigError, match=key):
            load_config(None, base + [bad], force=True)


def test_a_mirror_the_model_does_not_describe_is_flagged_by_the_model_rule():
    """Influence functions the model's Gaussian does not describe (here each subaperture's
    slopes distorted by up to 20 %): the registration's reduced chi2 fails the one model rule,
    its report line says its stds do not hold, and the DM verdict is not trustworthy; a mirror
    the model does describe passes and leaves the verdict alone."""
    from dataclasses import replace as dc_replace

    from torchblur.identify.verdict import DMVerdict, registration_guard

    mirror, wfs = _small()
    rng = np.random.default_rng(1)
    G = wfs.geometry_matrix(mirror, registration=MISREG)
    M = G.shape[0] // 2
    distort = np.tile(1 + 0.2 * np.cos(np.arange(M)), 2)[:, None]
    good = fit_registration(*_noisy_D0(G, np.ones(12), rng), wfs, mirror.actuator_xy, coupling=0.15)
    bad = fit_registration(*_noisy_D0(G * distort, np.ones(12), rng), wfs, mirror.actuator_xy, coupling=0.15)
    assert good.ok and bad.ok and good.reduced_chi2 < 2 < bad.reduced_chi2
    assert "fails the model rule" in bad.line() and "fails the model rule" not in good.line()
    v = DMVerdict(line="verdict: trustworthy", trustworthy=True, exit_code=0, actuators=12, flagged=(), poor_fit=(), failed=(),
                  ok=tuple(range(12)), weak=(), dead=(), failed_spot_fits=0, spot_problems=0, max_reduced_chi2=None)
    assert registration_guard(v, good) is v
    flagged = registration_guard(v, bad)
    assert not flagged.trustworthy and flagged.exit_code == 4 and "does not explain D0" in flagged.line
    assert registration_guard(v, dc_replace(bad, ok=False)) is v  # not fitted: the nominal geometry, said by its own line


def test_partly_lit_subapertures_the_model_does_not_describe_are_left_out():
    """Partly lit subapertures whose spots the model does not describe (slopes distorted by up to
    20 % there, as a diffraction spot cut by the pupil's edge is): the fit on every subaperture
    fails the model rule, the fit on the fully lit ones passes and is kept, and the registration
    is right."""
    mirror, wfs = _small()
    rng = np.random.default_rng(2)
    G = wfs.geometry_matrix(mirror, registration=MISREG)
    lit = fully_lit(wfs)
    M = G.shape[0] // 2
    distort = np.tile(np.where(lit, 1.0, 1 + 0.2 * np.cos(np.arange(M))), 2)[:, None]
    fit = fit_registration(*_noisy_D0(G * distort, np.ones(12), rng), wfs, mirror.actuator_xy, coupling=0.15)
    r = fit.registration
    assert fit.ok and fit.fitted_on == "the fully lit subapertures" and 0 < lit.sum() < M
    assert fit.n_entries == 2 * int(lit.sum()) * 12 and fit.reduced_chi2 < 1.5 and "fails the model rule" not in fit.line()
    assert abs(r.shift_x - 0.25) < 0.02 and abs(r.shift_y + 0.25) < 0.02 and abs(r.rotation_deg - 1.5) < 0.1
    assert abs(r.magnification - 1.03) < 0.003 and fit.G.shape == G.shape


def test_edge_subapertures_that_disagree_widen_the_stds(tmp_path):
    """Subapertures at the pupil's edge that see the mirror otherwise than the interior ones (here
    0.6 % more magnified, as one-sided lenslet crosstalk does on HCIPy's D0) bias the fit while its
    reduced chi2 passes the model rule: the edge test (the interior refit's difference) flags it,
    and the covariance with the difference covers the magnification's error, which the noise's
    std alone does not."""
    wfs = ShackHartmann(n_across=6, pupil_diameter=4.8, oversample=4)  # 32 valid, 4 interior
    mirror = DeformableMirror.build(5, coupling=0.15)  # 21 actuators
    edge = Registration(shift_x=0.25, shift_y=-0.25, rotation_deg=1.5, magnification=1.036, coupling=0.17)
    inner = np.tile(interior(wfs), 2)[:, None]
    G = np.where(inner, wfs.geometry_matrix(mirror, registration=MISREG), wfs.geometry_matrix(mirror, registration=edge))
    D0, std = _noisy_D0(G, np.ones(21), np.random.default_rng(0), rel=1e-3)
    fit = fit_registration(D0, std, wfs, mirror.actuator_xy, coupling=0.15)
    e = fit.edge_test
    assert fit.ok and fit.reduced_chi2 < 2 and 0 < int(inner.sum()) == 2 * e["n_interior"] and e["widened"] and e["p"] < EDGE_TEST_P
    err = fit.registration.magnification - 1.03
    noise_only = math.sqrt(fit.cov[3, 3] - e["difference"]["magnification"] ** 2)
    assert abs(err) / noise_only > 5 and abs(err) / fit.std["magnification"] < 2
    assert "edge subapertures disagree" in fit.line() and np.all(fit.gain_var_registration > 0)
    write_registration_json(tmp_path / "registration.json", fit)
    assert read_registration_json(tmp_path / "registration.json")["edge_test"] == fit.edge_test
