"""Properties of the renderer and the fitter under fuzzing (hypothesis, issue 8).

Example counts come from the "ci" settings profile registered in conftest.py (bounded,
derandomized, no deadline); ``HYPOTHESIS_PROFILE=thorough`` runs more.
"""
import math

import pytest
import torch

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import torchblur as tb  # noqa: E402
from torchblur.fit.sinusoid import fit_sinusoid  # noqa: E402

F64 = torch.float64
H, W = 24, 28
FIXED = tb.RenderSettings(nodes=48)  # a fixed quadrature: items rendered alone use the same nodes
ACCURATE = tb.RenderSettings(panel_path_sigmas=0.5)

floats = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def scenes(draw, batch=1):
    """A batch of (trajectory, PSF, window): tilted PSFs, Lissajous motions, any trigger phase,
    spot well inside an H x W frame."""
    def vec(lo, hi, shape=()):
        return torch.tensor(draw(st.lists(st.floats(lo, hi), min_size=math.prod(shape) or 1, max_size=math.prod(shape) or 1)),
                            dtype=F64).reshape(shape)

    b = (batch,)
    f = vec(20.0, 900.0, b)
    om = 2 * math.pi * f
    amp = vec(0.0, 4.0, b + (2,))
    phase = vec(-math.pi, math.pi, b + (2,))
    start = vec(0.0, 1.0, b) / f
    dur = vec(0.05, 1.5, b) / f
    centre = torch.stack([vec(11.0, 16.0, b), vec(10.0, 13.0, b)], -1)
    s_major = vec(1.0, 2.5, b)
    psf = tb.GaussianPSF.from_axes(centre, s_major, s_major * vec(0.4, 1.0, b), vec(-math.pi / 2, math.pi / 2, b), amplitude=vec(0.5, 3.0, b))
    return tb.Sinusoid(amp, phase, om), psf, tb.ExposureWindow(start, dur)


@given(scenes(batch=3))
def test_batch_equals_stacked_singles(scene):
    traj, psf, win = scene
    full = tb.render_blur(traj, psf, win, height=H, width=W, settings=FIXED)
    for k in range(3):
        one = tb.render_blur(traj[k], psf[k], win[k], height=H, width=W, settings=FIXED)
        torch.testing.assert_close(full[k], one, rtol=1e-10, atol=1e-12 * float(one.abs().max()))


@given(scenes(), st.integers(-3, 3), st.integers(-3, 3))
def test_translating_the_psf_translates_the_image(scene, dx, dy):
    traj, psf, win = scene
    pad = 4
    big = dict(height=H + 2 * pad, width=W + 2 * pad, settings=FIXED)
    base = tb.render_blur(traj, tb.GaussianPSF(psf.center + pad, psf.cov, psf.amplitude), win, **big)
    shift = torch.tensor([dx, dy], dtype=F64)
    moved = tb.render_blur(traj, tb.GaussianPSF(psf.center + pad + shift, psf.cov, psf.amplitude), win, **big)
    # moved[i + dy, j + dx] == base[i, j] wherever both are in the frame
    torch.testing.assert_close(torch.roll(base, shifts=(dy, dx), dims=(-2, -1))[..., pad:-pad, pad:-pad], moved[..., pad:-pad, pad:-pad],
                               rtol=1e-9, atol=1e-11 * float(base.max()))


@given(scenes())
def test_the_alias_pair_renders_the_same_image(scene):
    """PHYSICS.md Propositions 2 and 3: time reversal about the window centre, phi2 = pi - 2c - phi."""
    traj, psf, win = scene
    alias = tb.alias_phase(traj.phase, traj.omega[..., :1], win[..., None])
    a = tb.render_blur(traj, psf, win, height=H, width=W, settings=FIXED)
    b = tb.render_blur(tb.Sinusoid(traj.amplitude, alias, traj.omega), psf, win, height=H, width=W, settings=FIXED)
    torch.testing.assert_close(a, b, rtol=0, atol=1e-9 * float(a.abs().max()))


@given(scenes(), st.one_of(st.just(0.0), st.floats(1e-6, 50.0)))
def test_image_is_linear_in_the_psf_amplitude(scene, factor):
    traj, psf, win = scene
    a = tb.render_blur(traj, psf, win, height=H, width=W)
    b = tb.render_blur(traj, tb.GaussianPSF(psf.center, psf.cov, psf.amplitude * factor), win, height=H, width=W)
    torch.testing.assert_close(b, factor * a, rtol=1e-12, atol=1e-14 * factor * float(a.max()))


@st.composite
def designs(draw):
    """A dual-exposure design that resolves the alias (window centres ~ a quarter period apart),
    a motion along x, a tilted PSF."""
    f = draw(st.floats(20.0, 900.0))
    first = draw(st.floats(0.15, 0.4))
    second = first + draw(st.floats(0.4, 0.6))
    b = draw(st.floats(0.0, 2 * math.pi))
    M = draw(st.floats(1.0, 6.0))
    phi = draw(st.floats(-math.pi, math.pi))
    angle = draw(st.floats(-math.pi / 2, math.pi / 2))
    s_major = draw(st.floats(1.2, 2.5))
    s_minor = s_major * draw(st.floats(0.5, 1.0))
    return f, (first, second), b, M, phi, angle, s_major, s_minor


def _render_design(design):
    from torchblur.design.windows import dual_exposure_windows

    f, fractions, b, M, phi, angle, s1, s2 = design
    om = torch.tensor(2 * math.pi * f, dtype=F64)
    win = dual_exposure_windows(om, fractions=fractions, trigger_phase=b)
    psf = tb.GaussianPSF.from_axes(torch.tensor([13.5, 11.5], dtype=F64), s1, s2, angle)
    traj = tb.Sinusoid(torch.tensor([M, 0.0], dtype=F64), torch.tensor([phi, phi], dtype=F64), om)
    # panels of 0.5 PSF widths: converged to ~1e-11 of the peak (the default rule can be off by
    # 7e-5 of the peak, see test_default_quadrature_on_a_short_path_over_most_of_a_period)
    return tb.render_blur(traj, psf, win, height=H, width=W, settings=ACCURATE), psf, win, om


@given(designs(), st.integers(0, 2**31 - 1))
def test_fitter_recovers_the_rendered_motion_within_its_std(design, seed):
    clean, psf, win, om = _render_design(design)
    M, phi = design[3], design[4]
    sigma = 0.01 * float(clean.max())
    noisy = clean + sigma * torch.randn(clean.shape, generator=torch.Generator().manual_seed(seed), dtype=F64)
    res = fit_sinusoid(noisy, psf, win, om, noise_std=sigma)
    assert int(res.status) == 0
    assert abs(float(res.amplitude) - M) < 5 * float(res.amplitude_std)
    assert abs(float(tb.wrap_phase(res.phase - phi))) < 5 * float(res.phase_std)
    # noise-free: exact up to the fitter's own quadrature; its bias stays below 5% of the std
    # at 1% noise (measured: up to 4e-5 px on a 1 px motion of a 2 px spot at 20 Hz, where
    # the node rule gives one panel to most of a period, about 1% of that std)
    exact = fit_sinusoid(clean, psf, win, om)
    assert int(exact.status) == 0
    assert abs(float(exact.amplitude) - M) < 0.05 * float(res.amplitude_std)
    assert abs(float(tb.wrap_phase(exact.phase - phi))) < 0.05 * float(res.phase_std)


@given(st.sampled_from([0.0, 1e-9, 1e-4, 3.0]), st.sampled_from([0.3, 1.0, 30.0]), st.floats(-math.pi / 2, math.pi / 2),
       st.floats(0.02, 2.0), st.floats(-math.pi, math.pi))
def test_no_nan_gradient_in_the_valid_domain(motion_px, sigma_px, angle, periods, phase):
    """Zero, tiny and ordinary motion; PSFs from 0.3 px to wider than the frame."""
    amp = torch.tensor([motion_px, 0.5 * motion_px], dtype=F64, requires_grad=True)
    ph = torch.tensor([phase, phase + 0.3], dtype=F64, requires_grad=True)
    om = torch.tensor(2 * math.pi * 100.0, dtype=F64, requires_grad=True)
    centre = torch.tensor([13.2, 11.7], dtype=F64, requires_grad=True)
    s1 = torch.tensor(sigma_px, dtype=F64, requires_grad=True)
    s2 = torch.tensor(0.7 * sigma_px, dtype=F64, requires_grad=True)
    ang = torch.tensor(angle, dtype=F64, requires_grad=True)
    start = torch.tensor(1e-3, dtype=F64, requires_grad=True)
    dur = torch.tensor(periods / 100.0, dtype=F64, requires_grad=True)
    img = tb.render_blur(tb.Sinusoid(amp, ph, om), tb.GaussianPSF.from_axes(centre, s1, s2, ang), tb.ExposureWindow(start, dur),
                         height=H, width=W)
    weights = torch.linspace(-1, 1, H * W, dtype=F64).reshape(H, W)
    (img * weights).sum().backward()
    for name, t in dict(amp=amp, ph=ph, om=om, centre=centre, s1=s1, s2=s2, ang=ang, start=start, dur=dur).items():
        assert t.grad is not None and bool(torch.isfinite(t.grad).all()), name
    # and through the measurement-consistency loss
    amp2 = amp.detach().clone().requires_grad_(True)
    observed = img.detach()[None]
    loss = tb.blur_consistency({"amplitude": amp2, "phase": ph.detach(), "omega": om.detach()}, observed,
                               renderer=tb.BlurRenderer(H, W), psf=tb.GaussianPSF.from_axes(centre.detach(), sigma_px, 0.7 * sigma_px, angle),
                               window=tb.ExposureWindow(start.detach(), dur.detach()))
    loss.sum().backward()
    assert bool(torch.isfinite(amp2.grad).all())


def test_default_quadrature_on_a_short_path_over_most_of_a_period():
    """Found by the property tests: the node rule used to give one 8-node panel to a short path
    over most of a period (6.8e-5 of the peak); the phase bound per panel fixed it."""
    om = torch.tensor(2 * math.pi * 20.0, dtype=F64)
    win = tb.ExposureWindow(torch.zeros(2, dtype=F64), torch.tensor([0.375, 0.875], dtype=F64) / 20.0)
    psf = tb.GaussianPSF.isotropic(torch.tensor([13.5, 11.5], dtype=F64), 1.75)
    traj = tb.Sinusoid(torch.tensor([1.25, 0.0], dtype=F64), torch.zeros(2, dtype=F64), om)
    ref = tb.render_blur(traj, psf, win, height=H, width=W, settings=tb.RenderSettings(nodes=1024))
    img = tb.render_blur(traj, psf, win, height=H, width=W)
    assert float((img - ref).abs().max() / ref.max()) < 1e-6
