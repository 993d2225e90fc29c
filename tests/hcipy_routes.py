"""Test helper (issue 29): diffraction spots from HCIPy on the multisine, direct and many-spot routes.

An independent optics engine (HCIPy pupils propagated by :class:`hcipy_frames.HcipySpot`, its
batched Fraunhofer DFT checked against HCIPy's propagator in ``tests/test_hcipy_truth.py``) makes
the frames; torchblur fits them with the PSF :func:`~torchblur.image.psf_from_still.psf_from_still`
chooses from still frames (``kind="auto"``: the measured kernel on these spots) or a forced
Gaussian (``kind="gaussian"``) for contrast, as identify's routes do (dark level known and
subtracted, ``background=0``; the noise model the still frames measured, two passes: the second
weighted by the first fit's model; the kernel's own noise in the stds: multisine propagates
its pixel variance exactly (``fit_multisine(kernel_var=)``), the direct and many-spot routes
multiply by ``StillPSF.kernel_noise_factor`` of the light fitted together, as identify does).

Optics (not those of ``hcipy_frames``' default): a circular aperture with a 25 % central
obstruction, 0.03 wave rms of defocus (Noll 4), 0.04 of oblique astigmatism (Noll 6) and 0.03 of
coma (Noll 7), 2.4 px per lambda/D; the many-spot grid gives each spot its own random aberrations.
Time integrals: composite Gauss-Legendre rules in numpy (``n_panels`` x 8 nodes per exposure,
independent of torchblur's renderer; :func:`time_convergence` checks the rule against twice the panels).
Frames in electrons: ``Poisson(frames + 20) + Normal(0, 3)``, the 20 e- dark level subtracted.

Routes and their problems (each seeded):

- multisine: three tones (harmonics 3, 4, 5 of 20-100 Hz; 3-6 px each, random phases) along x,
  twelve frames of random windows (0.1-0.6 of the common period) each at a laser power that makes its
  peak about 4000 e- (:func:`multisine_problem`); fitted by ``fit_multisine``.
- direct: a resonant plant ``g wn^2 / (s^2 + 2 zeta wn s + wn^2) e^{-s 30 us}`` (150-400 Hz, zeta
  0.05-0.2), 12 points from 0.3 to 2.5 times the resonance, each driven for about 4 px of motion,
  two exposures (0.3 and 0.8 of the period, one start); the two-step start (``fit_sinusoid`` per point,
  ``fit_transfer_function``, 2 poles + delay) then ``fit_direct`` (:func:`direct_problem`).
- spots: a 3x3 grid of spots (pitch 32 px, a 96x96 frame) moved together by a tip-tilt
  ``(Mx sin(w t + px), My sin(w t + py))`` (3-6 px per axis, 20-800 Hz), two exposures (0.3 and
  0.8 of the period) of 4 images each (configs/identify_spots.yaml's sweep); ``locate_spots`` crops, ``psf_from_still`` per spot crop, ``fit_sinusoid``
  ``axes="xy"`` with a PSF per spot (:func:`spots_problem`), as identify's many-spot route.
"""
from __future__ import annotations

import math

import numpy as np
import torch

import hcipy_frames as hf
from torchblur.design.windows import dual_exposure_windows
from torchblur.fit.multisine import fit_multisine, render_multisine
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.image.psf_from_still import psf_from_still
from torchblur.image.spots import crop_spots, locate_spots
from torchblur.render.blur import render_blur
from torchblur.render.camera import camera_noise_std
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow
from torchblur.sysid.direct import fit_direct
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function

F64 = torch.float64
OPTICS = hf.SpotOptics(q=2.4, obstruction=0.25, zernike_waves=((4, 0.03), (6, 0.04), (7, 0.03)))
DARK, READ = 20.0, 3.0
PEAK, STILL_PEAK, N_STILL = 4000.0, 3000.0, 32


def gl_frames(spots, rate, starts, durs, motion, n_panels: int = 32) -> np.ndarray:
    """``[E, H, W]`` noise-free frames (e-): the spots' light (``spots``: HcipySpot list, each
    of peak rate ``rate`` e-/s at power 1 times ``power``) moved by ``motion(t) -> (dx [S], dy [S])``
    px, integrated over ``[start_e, start_e + dur_e]`` by ``n_panels`` x 8 Gauss-Legendre nodes."""
    x, w = np.polynomial.legendre.leggauss(8)
    tau = ((np.arange(n_panels)[:, None] + (x + 1) / 2) / n_panels).ravel()
    wq = np.tile(w / 2 / n_panels, n_panels)
    out = []
    for t0, te in zip(np.atleast_1d(starts), np.atleast_1d(durs)):
        dx, dy = motion(t0 + te * tau)
        img = sum(np.tensordot(wq, s.intensity(dx, dy), 1) for s in spots)
        out.append(rate * te * img)
    return np.stack(out)


def noisy(clean: np.ndarray, rng) -> np.ndarray:
    """Camera frames less the known dark level (e-)."""
    return hf.camera_noise(clean, rng, background=DARK, read_noise=READ) - DARK


def _still(spots, rate, rng, H, W):
    """``(still frames [N, H, W], exposure s)``: N_STILL frames of peak STILL_PEAK e-."""
    te = STILL_PEAK / rate
    clean = sum(s.still(rate, te) for s in spots)
    return noisy(np.broadcast_to(clean, (N_STILL, H, W)), rng), te


# ----------------------------------------------------------------------------------- multisine

def multisine_problem(seed: int, *, n_panels: int = 48, H: int = 40, W: int = 56) -> dict:
    """One seeded multisine problem (module docstring): raw frames ``[12, H, W]`` at power
    ``power [12]`` (images / power are at power 1), windows, tones, the still frames."""
    rng = np.random.default_rng(seed)
    f0 = 20 + 80 * rng.random()
    om = 2 * math.pi * f0 * np.array([3.0, 4.0, 5.0])
    M = 3 + 3 * rng.random(3)
    phi = (2 * rng.random(3) - 1) * math.pi
    T0 = 1 / f0
    E = 12
    starts = T0 * rng.random(E)
    durs = T0 * (0.1 + 0.5 * rng.random(E))
    spot = hf.HcipySpot(OPTICS, (W / 2 - 0.5 + rng.random() - 0.5, H / 2 - 0.5 + rng.random() - 0.5), H, W)
    rate = PEAK / T0  # e-/s at power 1
    power = T0 / durs  # every frame about PEAK e- at its peak

    def motion(t):
        return (M[:, None] * np.sin(om[:, None] * t + phi[:, None])).sum(0), np.zeros_like(t)

    clean = np.concatenate([gl_frames([spot], rate * p, [s], [d], motion, n_panels) for s, d, p in zip(starts, durs, power)])
    still, te = _still([spot], rate, rng, H, W)
    return dict(frames=noisy(clean, rng), clean=clean, power=power, window=ExposureWindow(torch.tensor(starts), torch.tensor(durs)),
                omega=om, M=M, phi=phi, still=still, still_exposure=te)


def fit_multisine_problems(problems: list, kind: str) -> dict:
    """Every problem's tones by ``fit_multisine`` (one batch) with ``psf_from_still(kind=kind)``'s
    PSF, two passes -> errors (M %, phase deg), error / std (the second pass given the kernel's
    pixel variance: its noise propagated into the covariance, ``fit_multisine(kernel_var=)``),
    error / std by the scalar rule instead (``zrule_*``: the data's part of the covariance times
    ``StillPSF.kernel_noise_factor``), status, reduced chi2, factor; arrays ``[n, 3]`` (``[n]`` for the last three)."""
    res = [psf_from_still(torch.as_tensor(p["still"]), p["still_exposure"], kind=kind, background=0.0) for p in problems]
    pw = torch.tensor(np.stack([p["power"] for p in problems]))  # [n, E]
    raw = torch.tensor(np.stack([p["frames"] for p in problems]))
    images = raw / pw[..., None, None]
    psf = _batched_psf(res)
    win = ExposureWindow(torch.stack([p["window"].start for p in problems]), torch.stack([p["window"].duration for p in problems]))
    om = torch.tensor(np.stack([p["omega"] for p in problems]))
    noise = torch.stack([r.frame_noise_std(x) for r, x in zip(res, raw)]) / pw[..., None, None]
    fit = fit_multisine(images, psf, win, om, noise_std=noise)
    theta = torch.cat([fit.amplitude, fit.phase, fit.scale[:, None]], -1)
    model = render_multisine(theta, om, psf, win, height=images.shape[-2], width=images.shape[-1]) * pw[..., None, None]
    noise = torch.stack([r.frame_noise_std(m) for r, m in zip(res, model)]) / pw[..., None, None]
    kvar = torch.stack([r.kernel_variance() for r in res]) if res[0].kind == "kernel" else None
    fit = fit_multisine(images, psf, win, om, noise_std=noise, amplitude_guess=fit.amplitude, phase_guess=fit.phase, n_starts=0,
                        kernel_var=kvar)
    N = om.shape[-1]
    own = fit.covariance - fit.extras["kernel_covariance"] if kvar is not None else fit.covariance  # the data's part alone
    own_std = torch.diagonal(own, dim1=-2, dim2=-1).sqrt().numpy()
    factor = torch.stack([r.kernel_noise_factor(win.duration[i] * pw[i]) for i, r in enumerate(res)]).reshape(-1, 1).numpy()
    M, phi = np.stack([p["M"] for p in problems]), np.stack([p["phi"] for p in problems])
    dphi = np.angle(np.exp(1j * (fit.phase.numpy() - phi)))
    dM = fit.amplitude.numpy() - M
    return dict(err_M_pct=100 * dM / M, err_phi_deg=np.degrees(dphi),
                z_M=dM / fit.amplitude_std.numpy(), z_phi=dphi / fit.phase_std.numpy(),
                zrule_M=dM / (own_std[:, :N] * factor), zrule_phi=dphi / (own_std[:, N:2 * N] * factor),
                status=fit.status.numpy(), reduced_chi2=fit.extras["reduced_chi2"].numpy(), factor=factor[:, 0],
                kinds=[r.kind for r in res])


def _batched_psf(res: list):
    """One PSF of batch ``[n]`` from n StillPSFs of one kind."""
    if res[0].kind == "kernel":
        return KernelPSF(torch.stack([r.psf.kernel for r in res]))
    return GaussianPSF(torch.stack([r.psf.center for r in res]), torch.stack([r.psf.cov for r in res]),
                       torch.stack([r.psf.amplitude for r in res]))


# -------------------------------------------------------------------------------------- direct

DELAY_S = 30e-6
N_POINTS = 12


def direct_problem(seed: int, *, n_panels: int = 32, H: int = 40, W: int = 56, n_points: int = N_POINTS) -> dict:
    """One seeded sweep of a resonant plant (module docstring): raw frames ``[F, 2, H, W]``,
    windows ``[F, 2]``, omega ``[F]``, input amplitudes ``[F]``, point powers ``[F]``, the truth."""
    rng = np.random.default_rng(seed)
    fn = 150 + 250 * rng.random()
    zeta = 0.05 + 0.15 * rng.random()
    wn = 2 * math.pi * fn
    g = 8.0
    freqs = fn * np.geomspace(0.3, 2.5, n_points)
    om = 2 * math.pi * freqs
    s = 1j * om
    Hs = g * wn**2 / (s**2 + 2 * zeta * wn * s + wn**2) * np.exp(-s * DELAY_S)
    A = 4.0 / np.abs(Hs) * (1 + 0.1 * rng.random(n_points))
    spot = hf.HcipySpot(OPTICS, (W / 2 - 0.5 + rng.random() - 0.5, H / 2 - 0.5 + rng.random() - 0.5), H, W)
    rate = PEAK / 0.01  # e-/s at power 1 (a 10 ms exposure peaks at PEAK)
    frames, starts, durs, power = [], [], [], []
    for k in range(n_points):
        win = dual_exposure_windows(torch.tensor(om[k], dtype=F64), fractions=(0.3, 0.8), trigger_phase=2 * math.pi * rng.random())
        st, du = win.start.numpy(), win.duration.numpy()
        p = 0.01 / du.max()  # the longer exposure peaks at PEAK
        M, ph = A[k] * abs(Hs[k]), float(np.angle(Hs[k]))
        motion = (lambda t, M=M, ph=ph, w=om[k]: (M * np.sin(w * t + ph), np.zeros_like(t)))
        frames.append(gl_frames([spot], rate * p, st, du, motion, n_panels))
        starts.append(st)
        durs.append(du)
        power.append(p)
    still, te = _still([spot], rate, rng, H, W)
    clean = np.stack(frames)
    return dict(frames=noisy(clean, rng), clean=clean, window=ExposureWindow(torch.tensor(np.stack(starts)), torch.tensor(np.stack(durs))),
                omega=om, amplitude=A, power=np.array(power), fn=fn, zeta=zeta, still=still, still_exposure=te)


def fit_direct_problem(p: dict, kind: str) -> dict:
    """The two-step start and the direct fit of one sweep with ``psf_from_still(kind=kind)``'s PSF
    (the kernel times each point's power, as identify's direct stage), the noise model's weights
    (two passes) -> the resonance's frequency and damping, their errors (%) and error / std (the
    direct model's stds times the factor of a point's mean light:
    :func:`~torchblur.identify.model.direct_kernel_noise_factor`)."""
    from torchblur.identify.model import direct_kernel_noise_factor, with_kernel_noise

    r = psf_from_still(torch.as_tensor(p["still"]), p["still_exposure"], kind=kind, background=0.0)
    raw = torch.as_tensor(p["frames"])
    pw = torch.as_tensor(p["power"])
    win, om, A = p["window"], torch.as_tensor(p["omega"]), torch.as_tensor(p["amplitude"])
    F, E, H, W = raw.shape
    if r.kind == "kernel":
        psf = KernelPSF(r.psf.kernel.expand(F, H, W) * pw[:, None, None])
    else:
        psf = GaussianPSF(r.psf.center.expand(F, 2), r.psf.cov.expand(F, 2, 2), r.psf.amplitude * pw)
    noise = r.frame_noise_std(raw)
    sweep = fit_sinusoid(raw, psf, win, om, axes="x", noise_std=noise)
    traj = Sinusoid(torch.stack([sweep.amplitude, torch.zeros_like(sweep.amplitude)], -1)[:, None],
                    sweep.phase[:, None, None].expand(-1, 1, 2), om[:, None])
    psf_e = KernelPSF(psf.kernel[:, None]) if r.kind == "kernel" else GaussianPSF(psf.center[:, None], psf.cov[:, None], psf.amplitude[:, None])
    noise = r.frame_noise_std(render_blur(traj, psf_e, win, height=H, width=W))
    sweep = fit_sinusoid(raw, psf, win, om, axes="x", noise_std=noise)
    frf = _frf(sweep, A, om)
    start = fit_transfer_function(frf, n_poles=2, n_zeros=0)
    d = fit_direct(raw, psf, win, om, A, start, form="modal", axis="x", noise_std=noise)
    if r.kind == "kernel":
        d = with_kernel_noise(d, direct_kernel_noise_factor(r, win, pw, d.used))
    m = d.modal_parameters()[0]
    return dict(err_f_pct=100 * (m["freq_hz"] - p["fn"]) / p["fn"], err_zeta_pct=100 * (m["zeta"] - p["zeta"]) / p["zeta"],
                z_f=(m["freq_hz"] - p["fn"]) / m["freq_hz_std"], z_zeta=(m["zeta"] - p["zeta"]) / m["zeta_std"],
                converged=bool(d.converged), reduced_chi2=float(d.reduced_chi2), kind=r.kind)


def _frf(fit, A, om) -> FrequencyResponse:
    """The two-step points as a 1x1 FrequencyResponse (``identify.assemble.assemble_siso``'s layout, no timing terms)."""
    mag, mag_std = (fit.amplitude / A).numpy(), (fit.amplitude_std / A).numpy()
    ph_std = fit.phase_std.numpy()
    corr = (fit.covariance[:, 0, 1] / (fit.amplitude_std * fit.phase_std)).numpy()
    cov = np.zeros((mag.size, 2, 2))
    cov[:, 0, 0], cov[:, 1, 1] = mag_std**2, ph_std**2
    cov[:, 0, 1] = cov[:, 1, 0] = corr * mag_std * ph_std
    return FrequencyResponse(om.numpy(), mag * np.exp(1j * fit.phase.numpy()), cov=cov, input_labels=["x"], output_labels=["x"])


# --------------------------------------------------------------------------------------- spots

PITCH = 32
REPEATS = 4  # images per exposure, as configs/identify_spots.yaml


def spots_problem(seed: int, *, n_panels: int = 16, size: int = 96) -> dict:
    """One seeded 3x3 grid (module docstring): raw frames ``[2 * REPEATS, size, size]``, windows
    ``[2 * REPEATS]`` (each exposure REPEATS times, its own noise), omega, the tip-tilt
    ``(Mx, My, phase_x, phase_y)``, the still frames."""
    rng = np.random.default_rng(seed)
    f = 20 + 780 * rng.random()
    om = 2 * math.pi * f
    Mx, My = 3 + 3 * rng.random(2)
    px, py = (2 * rng.random(2) - 1) * math.pi
    spots = []
    for i in range(3):
        for j in range(3):
            ab = ((4, 0.04 * rng.standard_normal()), (5, 0.04 * rng.standard_normal()), (6, 0.04 * rng.standard_normal()),
                  (7, 0.03 * rng.standard_normal()), (8, 0.03 * rng.standard_normal()))
            c = (PITCH / 2 - 0.5 + PITCH * j + rng.random() - 0.5, PITCH / 2 - 0.5 + PITCH * i + rng.random() - 0.5)
            spots.append(hf.HcipySpot(hf.SpotOptics(q=2.4, obstruction=0.25, zernike_waves=ab), c, size, size))
    win = dual_exposure_windows(torch.tensor(om, dtype=F64), fractions=(0.3, 0.8), trigger_phase=2 * math.pi * rng.random())
    rate = PEAK / float(win.duration.max())

    def motion(t):
        return Mx * np.sin(om * t + px), My * np.sin(om * t + py)

    clean = np.repeat(gl_frames(spots, rate, win.start.numpy(), win.duration.numpy(), motion, n_panels), REPEATS, axis=0)
    still, te = _still(spots, rate, rng, size, size)
    win = ExposureWindow(win.start.repeat_interleave(REPEATS), win.duration.repeat_interleave(REPEATS))
    return dict(frames=noisy(clean, rng), clean=clean, window=win, omega=om, truth=np.array([Mx, My, px, py]), still=still,
                still_exposure=te, seed=seed)


def fit_spots_problems(problems: list, kind: str) -> dict:
    """Every problem's spots (``locate_spots`` crops of ``PITCH`` px, ``psf_from_still(kind=kind)``
    per crop, one batched ``fit_sinusoid`` ``axes="xy"`` ``[n, K]``, two passes) -> per spot and
    axis errors (M %, phase deg) and error / std (stds times the kernel-noise factor), ``[n, K, 2]``,
    of the grids where ``locate_spots`` found the 9 spots; ``found [n]``: how many it found in each."""
    per = []
    for p in problems:
        still = torch.as_tensor(p["still"])
        mean = still.mean(0)
        loc = locate_spots(mean, exposure_s=p["still_exposure"], noise_std=camera_noise_std(float(mean.max()), READ) / 4,
                           pitch_px=float(PITCH), crop_px=PITCH)
        crops = crop_spots(still, loc.offset, loc.size)  # [N, K, h, w]
        res = [psf_from_still(crops[:, k], p["still_exposure"], kind=kind, background=0.0) for k in range(len(loc))]
        per.append((loc, res, crop_spots(torch.as_tensor(p["frames"]), loc.offset, loc.size).transpose(0, 1)))  # [K, E, h, w]
    found = np.array([len(loc) for loc, _, _ in per])
    good = [i for i in range(len(per)) if found[i] == 9]  # a grid where locate_spots found another count is a gross error
    if len(good) < len(per):
        print(f"  spots: locate_spots found {found.tolist()} spots (9 expected) in the grids of seeds "
              f"{[p.get('seed') for p in problems]}", flush=True)
    if not good:
        return dict(found=found)
    per, problems = [per[i] for i in good], [problems[i] for i in good]
    K = 9
    raw = torch.stack([c for _, _, c in per])  # [n, K, E, h, w]
    res_all = [r for _, res, _ in per for r in res]
    n, _, E, h, w = raw.shape
    flat = _batched_psf(res_all)
    psf = KernelPSF(flat.kernel.reshape(n, K, h, w)) if res_all[0].kind == "kernel" else GaussianPSF(
        flat.center.reshape(n, K, 2), flat.cov.reshape(n, K, 2, 2), flat.amplitude.reshape(n, K))
    win = ExposureWindow(torch.stack([p["window"].start for p in problems])[:, None], torch.stack([p["window"].duration for p in problems])[:, None])
    om = torch.tensor([p["omega"] for p in problems], dtype=F64)[:, None]
    noise = torch.stack([r.frame_noise_std(x) for r, x in zip(res_all, raw.reshape(n * K, E, h, w))]).reshape(raw.shape)
    fit = fit_sinusoid(raw, psf, win, om, axes="xy", noise_std=noise)
    traj = Sinusoid(fit.amplitude[..., None, :], fit.phase[..., None, :], om[..., None])
    model = render_blur(traj, psf[..., None], win, height=h, width=w)
    noise = torch.stack([r.frame_noise_std(m) for r, m in zip(res_all, model.reshape(n * K, E, h, w))]).reshape(raw.shape)
    fit = fit_sinusoid(raw, psf, win, om, axes="xy", noise_std=noise)
    factor = torch.stack([r.kernel_noise_factor(win.duration[i // K, 0]) for i, r in enumerate(res_all)]).reshape(n, K, 1).numpy()
    truth = np.stack([p["truth"] for p in problems])  # [n, 4]
    M, phi = truth[:, None, :2], truth[:, None, 2:]
    dphi = np.angle(np.exp(1j * (fit.phase.numpy() - phi)))
    return dict(err_M_pct=100 * (fit.amplitude.numpy() - M) / M, err_phi_deg=np.degrees(dphi),
                z_M=(fit.amplitude.numpy() - M) / (fit.amplitude_std.numpy() * factor), z_phi=dphi / (fit.phase_std.numpy() * factor),
                status=fit.status.numpy(), reduced_chi2=fit.reduced_chi2.numpy(), kinds=[r.kind for _, res, _ in per for r in res],
                found=found)


def time_convergence(seed: int = 0) -> float:
    """Largest change (fraction of the peak) of a multisine problem's noise-free frames when the
    time rule's panels double: the truth's own integration error."""
    a = multisine_problem(seed)["clean"]
    b = multisine_problem(seed, n_panels=96)["clean"]
    return float(np.abs(a - b).max() / np.abs(b).max())
