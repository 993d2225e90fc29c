"""Which spot model removes the DM spot fits' bias on HCIPy lenslet spots (issue 23): the run's
shifted still against models built from static frames of each Hadamard pattern.

bench_dm_spot_causes.py traced the bias: under a Hadamard pattern the surface under a lenslet is
curved, not only tilted, so each spot changes shape as it moves, and the run's model (the spot's
still, shifted along two sinusoids) reads that change as motion (a phase lead of ~0.04-0.06 rad at
3 px, barely moving spots fitted with 0.5 px). Here the same noiseless frames (tests/hcipy_sh.py,
configs/identify_dm.yaml's geometry and plan, a 3 px largest motion, exposures 0.3 and 0.8 of the
period, weights from the camera noise of a 1650 e- still peak) are fitted per (pattern, spot) by
scipy's least squares with four models, and the responses compared with the fitted-shift truth
``shift_truth x pattern x H(jw)``:

- ``base``: the run's fit (:func:`torchblur.dm.spot_fit.fit_spot_problems`, each spot's still as
  its kernel).
- ``linear``: base plus a shape image driven linearly by the pattern's command: the odd part of
  the residuals left by a shifted still fitted to static frames of the pattern at +-its amplitude,
  its phasor free (2 parameters).
- ``ladder``: the spot's image *is* the static image of the pattern at the instantaneous command
  ``u(t) = Re(g e^{i w t})`` (a ladder of static frames at ``LADDER`` levels of the pattern's
  amplitude, a cubic spline in u per pixel; the crop, the neighbours' light and the shift's
  nonlinearity all included): 2 parameters per spot, its motion ``g`` times the spot's
  small-signal shift per unit u (dI/du at 0 on the still's Fourier derivatives). Exact when every
  actuator has the same dynamics.
- ``ladder+delta``: the ladder plus a small free motion ``delta(t)`` (x and y sinusoids, to first
  order: ``L(u) + delta . dL/dshift(u)``) for the actuators' differing dynamics; the response is
  the ladder's motion plus delta.
- ``fast``: the run's fitter, :func:`torchblur.dm.ladder_fit.fit_ladder_problems` (batched,
  analytic Jacobian, torch LM: the ladder at the shape's own command, moved along ``s`` and
  across it by the Taylor series of a shift), on a ladder of the same levels times the command of
  a static motion of the sweep's largest (the run's ``ladder_levels``: the ladder spans the
  motion; noiseless: variance 0) and the same frames; ``former``: the same with the shape tied to
  the motion (the shift's own command held at 0 by a vanishing prior: the model before issue 23's
  cause 2 was measured); ``shape``: the first-order candidate of ``benchmarks/dm_ladder_shape.py``
  (measured, not landed). Each prints beside the
  summary the pull toward the pattern's common command (``b`` of ``Y - Yt = b (Yt - Yc)``, ``Yc``
  every live actuator at their mean response) and rms(|error|/std) with the fit's own stds
  (those of one set of noisy frames).

    python benchmarks/bench_dm_spot_models.py [--patterns 1] [--freq 342] [--same-dynamics]
        [--models base,linear,ladder,ladder+delta,fast,former,shape] [--spots 0:80]

Slow (scipy with finite-difference Jacobians, one spot at a time: minutes per model and
pattern); ``fast`` is the batched one (the wall times of one run compare them).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
import scipy.optimize as so
import torch
from scipy.interpolate import CubicSpline

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bench_dm_spot_causes as bc  # noqa: E402
import hcipy_sh as hs  # noqa: E402

import dm_ladder_shape  # noqa: E402

import torchblur.dm.ladder_fit as lf  # noqa: E402
from torchblur.config import load_config  # noqa: E402
from torchblur.config.budget import dm_plan  # noqa: E402
from torchblur.dm.ladder_fit import PatternLadder, fit_ladder_problems  # noqa: E402
from torchblur.dm.spot_fit import crop_problems, fit_spot_problems, pattern_responses  # noqa: E402
from torchblur.render.blur import _kernel_fourier  # noqa: E402
from torchblur.render.camera import camera_noise_std  # noqa: E402
from torchblur.render.psf import KernelPSF  # noqa: E402

#: the ladder's levels (units of the pattern's sweep amplitude; the motion reaches |H| ~ 1.2 of it)
LADDER = np.linspace(-1.4, 1.4, 29)
_F64 = torch.float64
NODES = 96  #: Gauss-Legendre nodes per exposure of the fitted models


def _shift(img, dx, dy, pad=6):
    """``img [..., h, w]`` moved by (dx, dy) px (Fourier shift, one node)."""
    n = img.reshape(-1, *img.shape[-2:]).shape[0]
    one = torch.ones(n, 1, dtype=_F64)
    return _kernel_fourier(img.reshape(n, *img.shape[-2:]), one * dx, one * dy, one, pad=pad).reshape(img.shape)


def _shift_residual(img, K):
    """The residual ``img - a K(x - s)`` of the best shifted still (uniform weights), and ``s``."""
    def res(s):
        return (s[2] * _shift(K, s[0], s[1]) - img).reshape(-1).numpy()
    sol = so.least_squares(res, [0.0, 0.0, 1.0], x_scale=[1, 1, 0.1])
    return -torch.as_tensor(res(sol.x)).reshape(img.shape), sol.x[:2]


class Case:
    """The frames, truth and base fit of one frequency (``--patterns`` patterns from row 1 of the plan)."""

    def __init__(self, n_patterns: int, f: float, same: bool):
        cfg = load_config("configs/identify_dm.yaml", ["sweep.n=4", "dm_plan.budget_frames=512"])
        self.gen = gen = hs.HcipySH()
        dyn = hs.draw_dynamics(gen.n_actuators, 23)
        if same:
            N = gen.n_actuators
            dyn = hs.Dynamics(mode_hz=np.full(N, 900.0), damping=np.full(N, 0.08), gain=np.ones(N), delay_s=np.full(N, 20e-6))
        S = gen.shift_truth()
        self.pats = dm_plan(cfg)[0].patterns[1:1 + n_patterns]
        n, self.pitch = gen.optics.n_lenslets, gen.optics.pitch_px
        r, c = np.divmod(gen.valid, n)
        self.offset = torch.as_tensor(np.stack([c * self.pitch, r * self.pitch], -1))
        self.size = (self.pitch, self.pitch)
        self.f, self.om = f, 2 * math.pi * f
        self.power = bc.PEAK_E / (bc.EXPOSURES[1] / f)
        self.window = bc.windows(f, len(self.pats))
        self.M = S.shape[0] // 2
        frames, self.Yt, self.amps = bc.dm_frames(gen, dyn, S, self.pats, f, self.window, self.power, 1.0)
        H = dyn.response(f)
        Ys = (S @ self.pats.T).T  # [P, 2M] static motion per unit command
        self.static_unit = bc.TARGET_PX / np.hypot(np.abs(Ys[:, :self.M]), np.abs(Ys[:, self.M:])).max(1) / self.amps  # [P]
        self.Yc = (S @ (np.mean(H[~dyn.dead]) * self.pats.T)).T  # [P, 2M]: every live actuator at their mean response
        self.crops, inside = crop_problems(frames[:, None], self.offset, self.size)  # [P, 1, M, E, h, w]
        self.kern = self._crop(torch.as_tensor(gen.still() * self.power))  # [M, h, w]
        self.fits = fit_spot_problems(self.crops, KernelPSF(self.kern), self.window, torch.tensor([self.om], dtype=_F64),
                                      noise_std=camera_noise_std(self.crops, bc.READ_NOISE_E), mask=inside[:, None])
        self.Y0 = pattern_responses(self.fits, self.amps[:, None])[0][..., 0]  # [P, 2M]
        st, du = self.window.start[0, 0], self.window.duration[0, 0]
        x, w = np.polynomial.legendre.leggauss(NODES)
        self.t = [(st[e] + du[e] * torch.as_tensor((x + 1) / 2)).numpy() for e in range(2)]  # node times per exposure
        self.w = [(du[e] * torch.as_tensor(w / 2)).numpy() for e in range(2)]  # node weights (s)

    def _crop(self, img):
        return crop_problems(img[None, None, None], self.offset, self.size)[0][0, 0, :, 0]

    def static(self, p: int, levels) -> torch.Tensor:
        """Static frames of pattern ``p`` at ``levels`` of its amplitude, cropped: ``[L, M, h, w]`` (rate x power)."""
        imgs = self.gen.intensity(np.asarray(levels)[:, None] * self.amps[p] * self.pats[p][None]) * self.power
        return crop_problems(torch.as_tensor(imgs)[:, None, None], self.offset, self.size)[0][:, 0, :, 0]

    def ladder(self, spots):
        """``(levels [P, K] input units, images [P, K, S, h, w] e-/s)``: the fast fit's ladder of the
        spots ``spots``, ``LADDER`` times the command of a static motion of the sweep's largest
        (the run's ``ladder_levels``: the ladder spans the motion, not the command, which above
        the modes is several times larger)."""
        unit = torch.as_tensor(self.static_unit * self.amps)[:, None]
        imgs = torch.stack([self.static(p, LADDER * self.static_unit[p])[:, list(spots)] for p in range(len(self.pats))])
        return torch.as_tensor(LADDER)[None] * unit, imgs

    def data(self, p, m):
        d = self.crops[p, 0, m]
        return d.numpy(), camera_noise_std(d, bc.READ_NOISE_E).numpy()

    def start_phasor(self, p, m, sl):
        """A start for u's phasor (gc, gs): the base fit's motion on the spot's larger static axis over its static shift."""
        a = int(np.argmax(np.abs(sl)))
        amp, ph = float(self.fits.amplitude[p, 0, m, a]), float(self.fits.phase[p, 0, m, a])
        r0, phi = amp / max(abs(sl[a]), 1e-9), ph + (np.pi if sl[a] < 0 else 0.0)
        return [r0 * np.sin(phi), r0 * np.cos(phi)]


def fit_linear(case: Case, p: int, spots):
    """``linear`` (module docstring): ``{m: (x phasor, y phasor, chi2)}`` px."""
    st = case.static(p, [1.0, -1.0])
    st_, du = case.window.start[0, 0], case.window.duration[0, 0]
    Wc = ((torch.sin(case.om * (st_ + du)) - torch.sin(case.om * st_)) / case.om).numpy()
    Ws = (-(torch.cos(case.om * (st_ + du)) - torch.cos(case.om * st_)) / case.om).numpy()
    out = {}
    for m in spots:
        B = ((_shift_residual(st[0, m], case.kern[m])[0] - _shift_residual(st[1, m], case.kern[m])[0]) / 2).numpy()
        data, sig = case.data(p, m)
        K = case.kern[m]

        def model(th):
            ax, px, ay, py, gc, gs = th
            imgs = []
            for e in range(2):
                t = torch.as_tensor(case.t[e])
                img = _kernel_fourier(K, ax * torch.sin(case.om * t + px), ay * torch.sin(case.om * t + py), torch.as_tensor(case.w[e]), pad=8)
                imgs.append(img.numpy() + (gc * Wc[e] + gs * Ws[e]) * B)
            return np.stack(imgs)
        th0 = [float(case.fits.amplitude[p, 0, m, 0]), float(case.fits.phase[p, 0, m, 0]), float(case.fits.amplitude[p, 0, m, 1]),
               float(case.fits.phase[p, 0, m, 1]), 0.0, 0.0]
        sol = so.least_squares(lambda th: ((model(th) - data) / sig).ravel(), th0, x_scale=[0.1, 0.01, 0.1, 0.01, 100, 100])
        ax, px, ay, py = sol.x[:4]
        out[m] = (ax * np.exp(1j * px), ay * np.exp(1j * py), float(np.sum(sol.fun ** 2)))
    return out


def fit_ladder(case: Case, p: int, spots, delta: bool):
    """``ladder`` / ``ladder+delta`` (module docstring): ``{m: (x phasor, y phasor, chi2)}`` px."""
    L = case.static(p, LADDER)  # [L, M, h, w]
    spl = CubicSpline(LADDER, L.numpy(), axis=0)
    dL0 = spl.derivative()(0.0)  # [M, h, w] per unit u at rest
    h = 0.05
    jx = ((_shift(case.kern, h, 0.0) - _shift(case.kern, -h, 0.0)) / (2 * h)).numpy()
    jy = ((_shift(case.kern, 0.0, h) - _shift(case.kern, 0.0, -h)) / (2 * h)).numpy()
    if delta:
        Lf = L.reshape(-1, *L.shape[-2:])
        splx = CubicSpline(LADDER, ((_shift(Lf, h, 0.0) - _shift(Lf, -h, 0.0)) / (2 * h)).reshape(L.shape).numpy(), axis=0)
        sply = CubicSpline(LADDER, ((_shift(Lf, 0.0, h) - _shift(Lf, 0.0, -h)) / (2 * h)).reshape(L.shape).numpy(), axis=0)
    out = {}
    for m in spots:
        J = np.stack([jx[m].ravel(), jy[m].ravel()], 1)
        sl = np.linalg.lstsq(J, dL0[m].ravel(), rcond=None)[0]  # px per unit u (the truth's convention: LSQ on the derivatives)
        data, sig = case.data(p, m)

        def model(g):
            imgs = []
            for e in range(2):
                t, w = case.t[e], case.w[e]
                u = np.clip(g[0] * np.cos(case.om * t) + g[1] * np.sin(case.om * t), LADDER[0], LADDER[-1])
                img = np.tensordot(w, spl(u)[:, m], 1)
                if delta:
                    dx = g[2] * np.cos(case.om * t) + g[3] * np.sin(case.om * t)
                    dy = g[4] * np.cos(case.om * t) + g[5] * np.sin(case.om * t)
                    img = img + np.tensordot(w * dx, splx(u)[:, m], 1) + np.tensordot(w * dy, sply(u)[:, m], 1)
                imgs.append(img)
            return np.stack(imgs)
        sol = so.least_squares(lambda g: ((model(g) - data) / sig).ravel(), case.start_phasor(p, m, sl) + [0.0] * (4 * delta))
        G = sol.x[1] + 1j * sol.x[0]  # u(t) = |G| sin(w t + arg G)
        dxp = sol.x[3] + 1j * sol.x[2] if delta else 0.0
        dyp = sol.x[5] + 1j * sol.x[4] if delta else 0.0
        out[m] = (sl[0] * G + dxp, sl[1] * G + dyp, float(np.sum(sol.fun ** 2)))
    return out


def fit_fast(case: Case, spots, fit=fit_ladder_problems):
    """``fast`` (module docstring): ``(Y [P, 2S] per unit amplitude, chi2 [P, S], std [P, 2S])`` of
    the spots ``spots`` (S of them); ``std`` the fit's own (the camera noise's weights: what one
    noisy set of frames would give); ``fit``: the run's or the candidate's ``fit_ladder_problems``."""
    sp = list(spots)
    levels, imgs = case.ladder(sp)  # [P, K] input units, [P, K, S, h, w] e-/s at the sweep's power
    ladder = PatternLadder(levels, imgs, torch.zeros_like(imgs), case.kern[sp])
    crops = case.crops[:, :, sp]
    t0 = time.perf_counter()
    fits = fit(crops, ladder, case.window, torch.tensor([case.om], dtype=_F64), torch.as_tensor(case.amps)[:, None],
               power=1.0, noise_std=camera_noise_std(crops, bc.READ_NOISE_E))
    print(f"  fast: the fit of {crops.shape[0] * crops.shape[2]} problems took {time.perf_counter() - t0:.3f} s (the rest: the static frames)")
    bad = int((fits.status != 0).sum())
    if bad:
        print(f"  fast: {bad} problems failed (status {sorted(set(fits.status.flatten().tolist()))})")
    Y, C = pattern_responses(fits, case.amps[:, None])
    return Y[..., 0], fits.reduced_chi2[:, 0].numpy() * 2 * case.pitch ** 2, np.sqrt(np.trace(C[:, :, 0], axis1=-2, axis2=-1) / 2)


def fit_noisy(case: Case, spots, draws: int, frames: int, seed: int = 0, fit_problems=fit_ladder_problems) -> None:
    """``--noisy``: ``fast`` on noisy frames: the sweep's crops with Poisson and read noise, a ladder
    of ``frames`` frames per level (each over the longer exposure: the mean, its variance from the
    expected signal), a still of 256 such frames; ``draws`` noise draws. Prints rms(error/std) of
    the pattern responses (the 2 x 2 Mahalanobis length per slope over sqrt 2) against the
    fitted-shift truth and against the noiseless fit, and the share of the ladder in the variance."""
    sp = list(spots)
    rng = np.random.default_rng(seed)
    T = float(case.window.duration[0, 0, 1])  # the ladder's and the still's exposure (s)
    levels, clean_l = case.ladder(sp)
    clean_l = clean_l * T  # e- per frame
    crops = case.crops[:, :, sp]
    Yt = case.Yt[:, np.concatenate([np.asarray(sp), case.M + np.asarray(sp)])]

    def noisy(e, n):  # the mean of n frames of expected electrons e (Poisson + read noise), and its variance
        mean = sum(rng.poisson(e.numpy()) + bc.READ_NOISE_E * rng.standard_normal(e.shape) for _ in range(n)) / n
        return torch.as_tensor(mean), (e + bc.READ_NOISE_E ** 2) / n

    def fit(data, ladder):  # weighted by the camera noise of the expected signal
        f = fit_problems(data, ladder, case.window, torch.tensor([case.om], dtype=_F64), torch.as_tensor(case.amps)[:, None],
                                power=1.0, noise_std=camera_noise_std(crops, bc.READ_NOISE_E))
        Y, C = pattern_responses(f, case.amps[:, None])
        return Y[..., 0], C[:, :, 0], f
    Y0 = fit(crops, PatternLadder(levels, clean_l / T, torch.zeros_like(clean_l), case.kern[sp]))[0]
    z_t, z_0, chi2 = [], [], []
    for _ in range(draws):
        lad, lvar = noisy(clean_l, frames)
        still = noisy(case.kern[sp] * T, 256)[0] / T
        Y, C, f = fit(noisy(crops, 1)[0], PatternLadder(levels, lad / T, lvar / T ** 2, still))
        Ci = np.linalg.inv(C)
        for ref, out in ((Yt, z_t), (Y0, z_0)):
            e = np.stack([(Y - ref).real, (Y - ref).imag], -1)
            out.append(np.einsum("...i,...ij,...j->...", e, Ci, e) / 2)
        chi2.append(f.reduced_chi2.numpy().ravel())
    big = np.abs(Yt) > 0.3 * np.abs(Yt).max(1, keepdims=True)
    z_t, z_0 = np.stack(z_t), np.stack(z_0)
    print(f"  noisy ({draws} draws, ladder {frames} frame(s) per level of {T * 1e3:.3g} ms, {len(LADDER)} levels; still peak {bc.PEAK_E:g} e-): "
          f"rms(error/std) against the fitted-shift truth {np.sqrt(np.nanmean(z_t)):.2f} (slopes > 0.3 max: "
          f"{np.sqrt(np.nanmean(z_t[:, big])):.2f}), against the noiseless fit {np.sqrt(np.nanmean(z_0)):.2f} "
          f"({np.sqrt(np.nanmean(z_0[:, big])):.2f}); {z_t.size} slopes; reduced chi2 median {np.nanmedian(np.concatenate(chi2)):.3f}", flush=True)


def pull(name, Y, Yt, Yc, std):
    """The pull toward the common command: the least-squares complex ``b`` of the responses'
    errors on their distance from the common command's (``Y - Yt = b (Yt - Yc)``, per pattern,
    ``Yc`` every live actuator at their mean response), its share of the error's power, and
    rms(error/std) of the responses with the fit's own stds (per pattern and over all)."""
    err, dist = Y - Yt, Yt - Yc
    ok = np.isfinite(err)
    e, d = np.where(ok, err, 0), np.where(ok, dist, 0)
    b = np.sum(np.conj(d) * e) / np.sum(np.abs(d) ** 2)
    share = 1 - np.sum(np.abs(e - b * d) ** 2) / np.sum(np.abs(e) ** 2)
    z = np.abs(err) / std
    per = ", ".join(f"{np.sqrt(np.nanmean(zp ** 2)):.2f}" for zp in z)
    print(f"  {name:13s} pull b {b.real:+.4f}{b.imag:+.4f}j ({share:.2f} of the error power; spread |Yt - Yc| / |Yt| "
          f"{np.sqrt(np.sum(np.abs(d) ** 2) / np.sum(np.abs(np.where(ok, Yt, 0)) ** 2)) * 100:.2f} % rms); "
          f"rms(|error|/std) {np.sqrt(np.nanmean(z ** 2)):.2f} (per pattern {per})", flush=True)


def summary(name, Y, Yt, chi2, n_pixels, seconds):
    """One line: noiseless reduced chi2 median, D error rms over max, the mean relative gain and phase errors of the large slopes."""
    err = Y - Yt
    big = np.abs(Yt) > 0.3 * np.abs(Yt).max(1, keepdims=True)
    rr = err[big] / Yt[big]
    if np.isnan(err).any():
        print(f"  {name}: {int(np.isnan(err).sum())} of {err.size} slopes failed (left out below)")
    err, rr = err[~np.isnan(err)], rr[~np.isnan(rr)]
    print(f"  {name:13s} noiseless reduced chi2 median {np.nanmedian(chi2) / n_pixels:.4f}; D error rms/max "
          f"{np.sqrt(np.mean(np.abs(err) ** 2)) / np.abs(Yt).max() * 100:.3f} %; large slopes: gain {np.mean(rr.real) * 100:+.3f} %, "
          f"phase {np.mean(rr.imag):+.5f} rad, rms |relative error| {np.sqrt(np.mean(np.abs(rr) ** 2)) * 100:.3f} % ({seconds:.3g} s)", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patterns", type=int, default=1)
    ap.add_argument("--freq", type=float, default=342.0)
    ap.add_argument("--same-dynamics", action="store_true", help="every actuator 900 Hz, damping 0.08, gain 1, delay 20 us")
    ap.add_argument("--models", default="base,linear,ladder,ladder+delta")
    ap.add_argument("--spots", default="0:80", help="a slice of the 80 spots (start:stop[:step])")
    ap.add_argument("--noisy", type=int, default=0, help="with the fast model: this many noisy draws (rms(error/std))")
    ap.add_argument("--ladder-frames", type=int, default=4, help="--noisy: frames per level of the ladder")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    case = Case(a.patterns, a.freq, a.same_dynamics)
    spots = range(case.M)[slice(*[int(v) for v in a.spots.split(":")])]
    cols = np.concatenate([np.asarray(spots), case.M + np.asarray(spots)])
    print(f"HCIPy frames, noiseless: {len(case.pats)} Hadamard pattern(s), {case.f:g} Hz, 3 px, {len(spots)} spots, dynamics "
          f"{'all the same' if a.same_dynamics else 'seed 23 (mode +-5 %, damping +-10 %, delay +-5 us, one dead, one weak)'} "
          f"({time.perf_counter() - t0:.0f} s set-up)")
    n_pix = 2 * case.pitch ** 2
    for name in a.models.split(","):
        t1 = time.perf_counter()
        if name == "base":
            Y, chi2 = case.Y0, case.fits.reduced_chi2[:, 0].numpy() * n_pix
            summary(name, Y[:, cols], case.Yt[:, cols], chi2[:, list(spots)], n_pix, time.perf_counter() - t1)
            continue
        base_name, _, prior_arg = name.partition("@")
        if base_name in ("fast", "former", "shape"):
            fit = dm_ladder_shape.fit_ladder_problems if base_name == "shape" else fit_ladder_problems
            prior = lf.SHAPE_PRIOR
            lf.SHAPE_PRIOR = 1e-12 if base_name == "former" else float(prior_arg) if prior_arg else prior
            try:
                Y, chi2, std = fit_fast(case, spots, fit)
                summary(name, Y, case.Yt[:, cols], chi2, n_pix, time.perf_counter() - t1)
                pull(name, Y, case.Yt[:, cols], case.Yc[:, cols], std)
                if a.noisy:
                    fit_noisy(case, spots, a.noisy, a.ladder_frames, fit_problems=fit)
            finally:
                lf.SHAPE_PRIOR = prior
            continue
        Y = np.full((len(case.pats), 2 * case.M), np.nan + 0j)
        chi2 = []
        for p in range(len(case.pats)):
            res = fit_linear(case, p, spots) if name == "linear" else fit_ladder(case, p, spots, delta=name == "ladder+delta")
            for m, (zx, zy, c2) in res.items():
                Y[p, m], Y[p, case.M + m] = zx / case.amps[p], zy / case.amps[p]
                chi2.append(c2)
        summary(name, Y[:, cols], case.Yt[:, cols], np.asarray(chi2), n_pix, time.perf_counter() - t1)


if __name__ == "__main__":
    main()
