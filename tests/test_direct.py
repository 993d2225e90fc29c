"""Direct identification (torchblur.sysid.direct): a parametric model fitted to every image at once.

Synthetic sweeps are rendered with the fitter's own forward model (point-sampled Gaussian
PSF) so that noise-free data are fitted exactly; the end-to-end run goes through the
simulated rig (pixel integration, transients, camera noise).
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

import torchblur as tb
from torchblur.config import load_config
from torchblur.sysid.alias_resolution import resolve_alias_with_model
from torchblur.sysid.direct import DirectModelFit, fit_direct
from torchblur.errors import ConfigError, InputTypeError, ParameterError, ShapeError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function
from readback import assert_reads_back

F64 = torch.float64
# Truth: a 650 Hz resonance (zeta 0.03) and a second mode at 1.5 kHz (zeta 0.05), 40 us delay.
MODES = ((650.0, 0.03), (1500.0, 0.05))
GAIN, DELAY = 10.0, 40e-6


MODAL_GAINS = (8.0, 2.0)  # the modal truth: 8 x (650 Hz mode) + 2 x (1.5 kHz mode)


def plant(omega, modes=MODES, gain=GAIN, delay=DELAY, kind="tf"):
    """kind "tf": gain x the product of the modes; "modal": sum of the modes, gains MODAL_GAINS (times gain / GAIN)."""
    s = 1j * np.asarray(omega)
    h = gain * np.ones_like(s) if kind == "tf" else np.zeros_like(s)
    for (f, z), g in zip(modes, MODAL_GAINS):
        w = 2 * math.pi * f
        mode = w * w / (s * s + 2 * z * w * s + w * w)
        h = h * mode if kind == "tf" else h + g * gain / GAIN * mode
    return h * np.exp(-s * delay)


def sweep(freqs, *, fracs=(0.3, 0.8), size=32, target=5.0, peak=3000.0, read=5.0, seed=None, kind="tf", b=math.pi / 2,
          direction=(1.0, 0.0)):
    """Images [F, E, H, W] of a sine sweep of ``plant`` along the unit image ``direction``
    (noise: sqrt(read^2 + signal), Gaussian)."""
    om = 2 * math.pi * np.asarray(freqs, dtype=np.float64)
    h = plant(om, kind=kind)
    A = target / np.abs(h)
    F, E = len(freqs), len(fracs)
    start = torch.tensor([[b / w] * E for w in om], dtype=F64)
    dur = torch.tensor([[fr * 2 * math.pi / w for fr in fracs] for w in om], dtype=F64)
    win = tb.ExposureWindow(start, dur)
    c = torch.full((F, 2), (size - 1) / 2, dtype=F64)
    psf = tb.GaussianPSF(c, (4.0 * torch.eye(2, dtype=F64)).expand(F, 2, 2), peak / dur.amax(-1))
    M = torch.tensor(np.abs(h) * A, dtype=F64)
    ph = torch.tensor(np.angle(h), dtype=F64)
    traj = tb.Sinusoid((M[:, None] * torch.tensor(direction, dtype=F64))[:, None], ph[:, None, None].expand(F, 1, 2),
                       torch.tensor(om, dtype=F64)[:, None])
    img = tb.render_blur(traj, tb.GaussianPSF(psf.center[:, None], psf.cov[:, None], psf.amplitude[:, None]), win,
                         height=size, width=size)
    if seed is not None:
        img = img + torch.sqrt(read**2 + img) * torch.randn(img.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)
    noise = torch.sqrt(read**2 + img.clamp_min(0))
    return dict(images=img, psf=psf, window=win, omega=torch.tensor(om, dtype=F64), amplitude=torch.tensor(A, dtype=F64),
                noise=noise)


def two_step(d):
    """The two-step route: per-point fits -> FrequencyResponse -> fixed-order model."""
    fit = fit_sinusoid(d["images"], d["psf"], d["window"], d["omega"], noise_std=d["noise"], fit_scale=True)
    A = d["amplitude"].numpy()
    i_m, i_p = fit.param_names.index("amplitude_x"), fit.param_names.index("phase_x")
    cov = fit.covariance[:, [i_m, i_p]][:, :, [i_m, i_p]].numpy().copy()
    cov[:, 0, :] /= A[:, None]
    cov[:, :, 0] /= A[:, None]
    frf = FrequencyResponse(d["omega"].numpy(), fit.amplitude.numpy() / A * np.exp(1j * fit.phase.numpy()), cov=cov)
    return fit, frf


def start_model(modes, gain, delay, omega, kind="tf"):
    """A TransferFunctionFit of an exactly known plant (noise-free, uniform weights)."""
    frf = FrequencyResponse(omega, plant(omega, modes, gain, delay, kind))
    return fit_transfer_function(frf, n_poles=4, n_zeros=0 if kind == "tf" else 2, delay_s=None, weights="uniform")


def mode_errors(fit):
    m = fit.modal_parameters()
    return [(m[k]["freq_hz"] - f, m[k]["freq_hz_std"], m[k]["zeta"] - z, m[k]["zeta_std"]) for k, (f, z) in enumerate(MODES)]


FREQS = np.geomspace(150.0, 1800.0, 10)


@pytest.mark.parametrize("form", ["tf", "modal"])
def test_noise_free_recovers_the_parameters_from_a_perturbed_start(form):
    d = sweep(FREQS, kind=form)
    off = start_model(((660.0, 0.036), (1460.0, 0.045)), 9.6, 47e-6, d["omega"].numpy(), kind=form)
    r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], off, form=form, noise_std=d["noise"])
    assert r.converged and r.form == form
    assert r.reduced_chi2 < 1e-12
    modes = r.modal_parameters()
    for m, (f, z) in zip(modes, MODES):
        assert m["freq_hz"] == pytest.approx(f, rel=1e-7)
        assert m["zeta"] == pytest.approx(z, rel=1e-6)
    assert r.delay_s == pytest.approx(DELAY, rel=1e-6)
    w = d["omega"].numpy()
    np.testing.assert_allclose(r.frequency_response(w), plant(w, kind=form), rtol=1e-7)
    if form == "modal":
        np.testing.assert_allclose([m["gain"] for m in modes], MODAL_GAINS, rtol=1e-6)
    np.testing.assert_allclose(r.scale, 1.0, rtol=1e-7)
    # the start really was off
    assert abs(r.start_params - r.params).max() > 0


def test_noise_free_along_a_rotated_axis():
    """A motion along an axis rotated 25 deg in the image, fitted along it (``axis=(x, y)``):
    the parameters come back exactly; fitted along x they do not."""
    u = (math.cos(math.radians(25)), math.sin(math.radians(25)))
    d = sweep(FREQS, direction=u)
    off = start_model(((660.0, 0.036), (1460.0, 0.045)), 9.6, 47e-6, d["omega"].numpy())
    r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], off, axis=(2 * u[0], 2 * u[1]), noise_std=d["noise"])
    assert r.converged and r.reduced_chi2 < 1e-12
    for m, (f, z) in zip(r.modal_parameters(), MODES):
        assert m["freq_hz"] == pytest.approx(f, rel=1e-7)
        assert m["zeta"] == pytest.approx(z, rel=1e-6)
    along_x = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], off, noise_std=d["noise"])
    assert along_x.reduced_chi2 > 1.0
    with pytest.raises(ParameterError, match="axis"):
        fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], off, axis=(0.0, 0.0))


def test_noisy_errors_are_within_the_reported_std():
    for seed in range(3):
        d = sweep(FREQS, seed=seed)
        _, frf = two_step(d)
        tf = fit_transfer_function(frf, n_poles=4, n_zeros=0)
        r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], tf, noise_std=d["noise"])
        assert r.converged
        assert 0.8 < r.reduced_chi2 < 1.2
        for ef, sf, ez, sz in mode_errors(r):
            assert abs(ef) < 4 * sf and abs(ez) < 4 * sz
        i = r.param_names.index("delay_s")
        assert abs(r.params[i] - DELAY) < 4 * r.std[i]


def test_covariance_is_the_inverse_fisher_information_of_a_dense_reference():
    """The blockwise (Schur) Fisher information equals J^T W J of the dense Jacobian over all
    pixels and all parameters (model and per-point scales), by autograd through render_blur."""
    freqs = np.array([300.0, 640.0, 700.0, 1400.0])
    d = sweep(freqs, size=24, seed=5)
    tf = start_model(MODES, GAIN, DELAY, d["omega"].numpy())
    r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], tf, noise_std=d["noise"])
    from torchblur.sysid.direct import _response

    struct = r._struct
    P, F = r.params.size, len(freqs)
    s = torch.tensor(1j * d["omega"].numpy())
    settings = tb.RenderSettings(nodes=64)

    def model(theta):
        h = _response(struct, theta[:P], s, r.delay_s)
        M, ph = d["amplitude"] * h.abs(), torch.angle(h)
        traj = tb.Sinusoid(torch.stack([M, torch.zeros_like(M)], -1)[:, None], ph[:, None, None].expand(F, 1, 2),
                           d["omega"][:, None])
        p = d["psf"]
        img = tb.render_blur(traj, tb.GaussianPSF(p.center[:, None], p.cov[:, None], p.amplitude[:, None]), d["window"],
                             height=24, width=24, settings=settings)
        return (img * theta[P:, None, None, None]).reshape(-1)

    theta = torch.cat([torch.tensor(r.params), torch.tensor(r.scale)])
    from torchblur.optim import model_jacobian

    _, J = model_jacobian(lambda t, i: model(t[0])[None], theta[None], torch.zeros(1, dtype=torch.long))
    J = J[0]
    w = (1 / d["noise"] ** 2).reshape(-1)
    fisher = (J * w[:, None]).T @ J
    cov = torch.linalg.inv(fisher)[:P, :P].numpy()
    np.testing.assert_allclose(r.covariance, cov, rtol=2e-3, atol=0)


def _old_point_images(M, phi, om, ud, center, precision, t, wq, H, W):
    """The hand-written node positions and derivatives of fit_direct's render before it called the
    one forward model (render.splat.sine_blur_with_jacobian): kept as a reference."""
    from torchblur.render.splat import gaussian_splat_with_jacobian

    Ap, Bp, Cp = precision
    arg = om[:, None, None] * t + phi[:, None, None]
    sn, cs = torch.sin(arg), torch.cos(arg)
    disp = M[:, None, None] * sn
    d = torch.stack([sn, M[:, None, None] * cs], -1)  # [n, E, S, 2]
    cx = center[:, 0, None, None].expand(t.shape)
    cy = center[:, 1, None, None].expand(t.shape)
    px, py, dpx, dpy = cx + ud[0] * disp, cy + ud[1] * disp, ud[0] * d, ud[1] * d
    return gaussian_splat_with_jacobian(px, py, dpx, dpy, wq, Ap[:, None], Bp[:, None], Cp[:, None], H, W)


@pytest.mark.parametrize("direction", [(1.0, 0.0), (0.6, -0.8)])
def test_point_images_on_the_one_forward_model_equal_the_old_hand_written_ones(direction):
    """fit_direct's images and d/d(M, phi) (sine_blur_with_jacobian) equal the hand-written ones
    they replaced, to round-off."""
    from torchblur.render.blur import quadrature_nodes
    from torchblur.render.splat import window_nodes
    from torchblur.sysid.direct import _point_images

    d = sweep(np.array([300.0, 640.0, 1400.0]), size=24)
    n = 3
    psf = d["psf"]
    win = d["window"]
    M = torch.tensor([4.0, 6.5, 2.0], dtype=F64)
    phi = torch.tensor([0.3, -1.2, 2.8], dtype=F64)
    ud = torch.tensor(direction, dtype=F64)
    tau, w = quadrature_nodes(6, 8, dtype=F64)
    t, wq = window_nodes(win.start, win.duration, tau, w, psf.amplitude[:, None])
    img, dimg = _point_images(M, phi, d["omega"], ud, psf.center, psf.precision(), t, wq, 24, 24)
    ref, dref = _old_point_images(M, phi, d["omega"], ud, psf.center, psf.precision(), t, wq, 24, 24)
    assert img.shape == (n, 2, 24, 24) and dimg.shape == (n, 2, 2, 24, 24)
    np.testing.assert_allclose(img.numpy(), ref.numpy(), rtol=0, atol=1e-12 * float(ref.abs().max()))
    np.testing.assert_allclose(dimg.numpy(), dref.numpy(), rtol=0, atol=1e-12 * float(dref.abs().max()))


def test_single_exposure_direct_does_at_least_as_well_as_the_two_step_route():
    """One exposure window (30% of the period) per point, timed so that the two alias branches
    cross at -90 deg, the phase of the resonance (Proposition 3): the per-point phases near
    the resonance are the least determined. Both routes pick the branches with the model
    (resolve_alias_with_model); the direct fit, started from the best candidates, does at
    least as well and lands within its reported std."""
    freqs = np.unique(np.concatenate([np.geomspace(200.0, 2000.0, 8), np.linspace(620.0, 680.0, 4)]))
    d = sweep(freqs, fracs=(0.3,), size=40, target=6.0, peak=2000.0, seed=0, b=0.7 * math.pi)
    fit, frf = two_step(d)
    res = resolve_alias_with_model(frf, fit.alias_phase, n_poles=4, n_zeros=0)
    assert res.flipped.dtype == bool and res.flipped.shape == (freqs.size,) and res.candidates[0] is res.model
    truth = plant(frf.omega)
    err_deg = np.degrees(np.abs(np.angle(res.frf.response[0, 0] / truth)))
    assert err_deg.max() < 20  # every point on its right branch (the alias is > 20 deg away or the same image)
    r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], res.candidates[:2], noise_std=d["noise"])
    two = res.model.modal_parameters()[0]
    (ef, sf, ez, sz), _ = mode_errors(r)
    assert abs(ef) < 3 * sf and abs(ez) < 3 * sz
    assert abs(ef) <= abs(two["freq_hz"] - 650.0) + 0.1 * sf
    assert abs(ez) <= abs(two["zeta"] - 0.03) + 0.1 * sz


def test_excluded_points_are_counted_and_ignored():
    d = sweep(FREQS, seed=1)
    tf = start_model(MODES, GAIN, DELAY, d["omega"].numpy())
    valid = torch.ones(len(FREQS), dtype=torch.bool)
    valid[2] = False
    bad = d["images"].clone()
    bad[2] = 0.0  # a dark point
    r = fit_direct(bad, d["psf"], d["window"], d["omega"], d["amplitude"], tf, noise_std=d["noise"], valid=valid)
    keep = valid.numpy()
    psf_kept = tb.GaussianPSF(d["psf"].center[valid], d["psf"].cov[valid], d["psf"].amplitude[valid])
    sub = fit_direct(d["images"][valid], psf_kept, d["window"][valid], d["omega"][valid], d["amplitude"][valid], tf,
                     noise_std=d["noise"][valid])
    assert r.n_excluded == 1 and r.used.tolist() == keep.tolist()
    assert np.isnan(r.scale[2])
    assert _assert_round_trip(r).used.tolist() == keep.tolist()  # the excluded point and its NaN scale read back
    np.testing.assert_allclose(r.params, sub.params, rtol=1e-9)
    with pytest.raises(ParameterError, match="valid"):
        fit_direct(bad, d["psf"], d["window"], d["omega"], d["amplitude"], tf, valid=torch.zeros(len(FREQS), dtype=torch.bool))


def test_a_point_the_model_does_not_explain_is_flagged_poor_fit():
    """The per-point rule of fit_sinusoid (reduced chi2 above POOR_FIT_CHI2 = 1.5): on a right
    sweep no point is flagged and each point's reduced chi2 is about 1; a point with a mislabelled
    exposure is flagged, the worst; with the noise estimated nothing is flagged (NaN: unknown)."""
    from torchblur.fit.status import POOR_FIT_CHI2, POOR_FIT_FLAG

    freqs = FREQS[::2]
    d = sweep(freqs, seed=3)
    tf = start_model(MODES, GAIN, DELAY, d["omega"].numpy())
    args = (d["psf"], d["window"], d["omega"], d["amplitude"], tf)
    right = fit_direct(d["images"], *args, noise_std=d["noise"])
    assert right.flags.shape == right.point_reduced_chi2.shape == (len(freqs),)
    assert not right.flags.any() and np.all(np.abs(right.point_reduced_chi2 - 1) < 0.2)
    imgs = d["images"].clone()
    imgs[2, 0] = sweep(freqs, fracs=(0.45, 0.8), seed=3)["images"][2, 0]  # one point's 30 % exposure lasted 45 %
    r = fit_direct(imgs, *args, noise_std=d["noise"])
    assert r.flags[2] & POOR_FIT_FLAG and r.point_reduced_chi2[2] > 5 * POOR_FIT_CHI2
    assert int(np.argmax(r.point_reduced_chi2)) == 2  # the worst (the one model spreads the damage to its neighbours)
    unknown = fit_direct(d["images"], *args, max_iter=3)
    assert np.isnan(unknown.point_reduced_chi2).all() and not unknown.flags.any()

def _assert_round_trip(r: DirectModelFit) -> DirectModelFit:
    """``r`` through model.json's document and back (strict JSON): every field, the covariance
    exactly, the same response, poles and modes; a version-1, a newer or a padded document
    refused by name."""
    doc = json.loads(json.dumps(r.to_dict(), allow_nan=False))
    back = DirectModelFit.from_dict(doc)
    for f in ("params", "covariance", "std", "start_params", "used", "scale"):
        np.testing.assert_array_equal(getattr(back, f), getattr(r, f), err_msg=f)
    assert (back.background is None) == (r.background is None)
    if r.background is not None:
        np.testing.assert_array_equal(back.background, r.background)
    for f in ("form", "param_names", "delay_s", "cost", "dof", "reduced_chi2", "noise_estimated", "converged", "n_iter", "n_excluded",
              "_struct"):
        assert getattr(back, f) == getattr(r, f), f
    w = np.geomspace(50, 5000, 9) * 2 * math.pi
    np.testing.assert_array_equal(back.frequency_response(w), r.frequency_response(w))
    assert back.modal_parameters() == r.modal_parameters() and back.to_dict() == doc
    with pytest.raises(ParameterError, match="schema_version: 1 .*read_outputs"):
        DirectModelFit.from_dict({**doc, "schema_version": 1})
    with pytest.raises(ParameterError, match=r"unsupported version 3 \(written by a newer torchblur"):
        DirectModelFit.from_dict({**doc, "schema_version": 3})
    with pytest.raises(ParameterError, match=r"unknown keys \['extra'\]"):
        DirectModelFit.from_dict({**doc, "extra": 1})
    with pytest.raises(ParameterError, match=r"covariance: expected shape"):
        DirectModelFit.from_dict({**doc, "covariance": doc["covariance"][:-1]})
    return back


def test_result_api_is_consistent():
    control = pytest.importorskip("control")
    d = sweep(FREQS, seed=2, kind="modal")
    tf = start_model(MODES, GAIN, DELAY, d["omega"].numpy(), kind="modal")
    r = fit_direct(d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], tf, noise_std=d["noise"], form="modal")
    w = np.geomspace(100, 3000, 7) * 2 * math.pi
    sys_ = r.to_control()
    h_ct = np.asarray(control.frequency_response(sys_, w).complex).reshape(-1)
    np.testing.assert_allclose(h_ct * np.exp(-1j * w * r.delay_s), r.frequency_response(w), rtol=1e-9)
    doc = json.loads(json.dumps(r.to_dict()))
    assert doc["schema"] == "torchblur.direct_model_fit" and doc["form"] == "modal"
    assert len(doc["params"]) == len(doc["std"]) == len(doc["param_names"]) == r.params.size
    assert len(doc["modes"]) == 2 and doc["n_points_used"] == len(FREQS)
    # modal form: a mode's omega_n std is its parameter's std
    i = min((r.param_names.index(f"mode{k}_omega_n") for k in (1, 2)), key=lambda j: r.params[j])
    assert r.modal_parameters()[0]["omega_n_std"] == pytest.approx(r.std[i], rel=1e-9)
    assert isinstance(r, DirectModelFit) and "modal" in repr(r)
    _assert_round_trip(r)
    # a DirectModelFit as the start: its own form is a fixed point; the tf form (2 zeros, 4 poles)
    # holds the modal model, so it fits at least as well
    args = (d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], r)
    r2 = fit_direct(*args, noise_std=d["noise"], form="modal")
    np.testing.assert_allclose(r2.params, r.params, rtol=1e-6)
    r3 = fit_direct(*args, noise_std=d["noise"], form="tf")
    assert r3.converged and r3.zeros.size == 2 and r3.cost <= r.cost * (1 + 1e-9)


def test_bad_inputs_name_the_argument():
    d = sweep(FREQS[:4])
    tf = start_model(MODES, GAIN, DELAY, d["omega"].numpy())
    args = [d["images"], d["psf"], d["window"], d["omega"], d["amplitude"], tf]

    def call(i, value, exc, name, **kw):
        a = list(args)
        if i is not None:
            a[i] = value
        with pytest.raises(exc) as info:
            fit_direct(*a, **kw)
        assert name in str(info.value)

    nan = d["images"].clone()
    nan[0, 0, 3, 3] = float("nan")
    call(0, nan, ParameterError, "images")
    call(0, d["images"][0], ShapeError, "images")
    call(0, d["images"].numpy(), InputTypeError, "images")
    call(3, d["omega"][:3], ShapeError, "omega")
    call(3, -d["omega"], ParameterError, "omega")
    call(4, d["amplitude"][:2], ShapeError, "input_amplitude")
    call(2, tb.ExposureWindow(torch.ones(3, 2, dtype=F64), 0.1), ShapeError, "window")
    call(5, "model", InputTypeError, "start")
    call(None, None, ParameterError, "form", form="state_space")
    call(None, None, ShapeError, "noise_std", noise_std=torch.ones(2, 2))
    call(None, None, ShapeError, "mask", mask=torch.ones(3, dtype=torch.bool))
    call(None, None, ShapeError, "valid", valid=torch.ones(2, dtype=torch.bool))
    call(None, None, ParameterError, "max_iter", max_iter=0)
    with pytest.raises(ShapeError, match="alias_phase"):
        resolve_alias_with_model(FrequencyResponse(d["omega"].numpy(), plant(d["omega"].numpy())), torch.zeros(2))


@pytest.mark.parametrize("overrides,key", [(["model.direct=maybe"], "model.direct"), (["model.direct_form=ss"], "model.direct_form"),
                                           (["model.direct_max_iter=0"], "model.direct_max_iter")])
def test_config_validates_the_direct_keys(overrides, key):
    with pytest.raises(ConfigError) as info:
        load_config(None, overrides)
    assert str(info.value).startswith(key)
    assert load_config().model.direct is False  # the default keeps the two-step model alone
    assert load_config(None, ["model.direct=true", "model.direct_form=modal"]).model.direct_form == "modal"


def test_cli_identify_with_direct_writes_both_models(tmp_path, capsys):
    from torchblur import cli

    # through the command's main() in this process (the fresh-process path of the command has its own tests in
    # test_cli_output.py; a fresh process here cost ~3 s of imports)
    out = tmp_path / "run"
    argv = ["identify", "--out", str(out), "--quiet", "sweep.freq_hz=[3,100,300,420,450,900]",
            "camera.height=40", "camera.width=40", "model.max_order=3", "seed=1", "model.direct=true", "report.figures=false"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    direct = json.loads((out / "model.json").read_text())
    two = json.loads((out / "model_two_step.json").read_text())
    assert direct["schema"] == "torchblur.direct_model_fit" and direct["converged"]
    assert two["schema"] == "torchblur.transfer_function_fit"
    # each model carries the verdict's judgement (torchblur.sysid.model_check)
    assert [j["name"] for j in direct["judgement"]] == ["direct"] and [j["name"] for j in two["judgement"]] == ["two-step"]
    assert direct["model_passed"] is two["model_passed"] is True
    assert direct["seed"] == 1 and direct["torchblur_version"]
    mode = direct["modes"][0]  # the default plant: 420 Hz, zeta 0.12
    assert abs(mode["freq_hz"] - 420.0) < 5 * mode["freq_hz_std"] + 0.5
    assert abs(mode["zeta"] - 0.12) < 5 * mode["zeta_std"] + 0.002
    report = (out / "report.txt").read_text()
    assert "direct model" in report and "model_two_step.json" in report
    got = assert_reads_back(out)  # model.json: the direct fit's document; model_two_step.json: a TransferFunctionFit
    assert isinstance(got["model.json"], DirectModelFit) and got["model_two_step.json"].n_poles >= 2
    np.testing.assert_array_equal(got["model.json"].covariance, np.array(direct["covariance"], dtype=float))  # with its covariance


def test_direct_is_refused_for_mimo_and_spots_runs():
    """The direct fit handles one axis and one spot: a 2x2 plant or a spot grid is a config error."""
    from pathlib import Path

    from torchblur.config import load_config
    from torchblur.errors import ConfigError

    mimo_cfg = str(Path(__file__).resolve().parents[1] / "configs" / "identify_mimo.yaml")
    for path, over in ((mimo_cfg, ["model.direct=true"]), (None, ["model.direct=true", "spots.rows=2", "spots.cols=2", "excitation.target_px=4"])):
        with pytest.raises(ConfigError, match="^model.direct:"):
            load_config(path, over)


def test_multisine_refuses_mimo_spots_and_direct():
    """A multisine drives one axis and fits one spot, and the direct fit works on sine sweeps."""
    from pathlib import Path

    from torchblur.errors import ConfigError

    mimo_cfg = str(Path(__file__).resolve().parents[1] / "configs" / "identify_mimo.yaml")
    cases = ((mimo_cfg, ["excitation.kind=multisine"], "excitation.kind"),
             (None, ["excitation.kind=multisine", "spots.rows=2", "spots.cols=2", "excitation.target_px=4"], "excitation.kind"),
             (None, ["excitation.kind=multisine", "model.direct=true"], "model.direct"))
    for path, over, key in cases:
        with pytest.raises(ConfigError, match=f"^{key}:"):
            load_config(path, over)


def test_modes_far_outside_the_swept_band_are_named():
    from torchblur.identify.run import modes_outside_band

    modes = [{"freq_hz": 650.0}, {"freq_hz": 1e30}, {"freq_hz": 2.0}, {"freq_hz": 0.5}, {"freq_hz": 2900.0}]
    assert [m["freq_hz"] for m in modes_outside_band(modes, 5.0, 1000.0)] == [1e30, 0.5]
    assert [m["freq_hz"] for m in modes_outside_band(modes, 5.0, 1000.0, factor=2.0)] == [1e30, 2.0, 0.5, 2900.0]
