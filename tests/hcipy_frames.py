"""Test helper: still and blurred frames of a diffraction-limited spot rendered with HCIPy.

An independent optics engine for checking torchblur outside its own simulation. A pupil
(a circular aperture, optionally centrally obstructed, with small Zernike aberrations; or a
Gaussian apodisation for the convention check) is propagated to the focal plane by HCIPy's
Fraunhofer propagation, evaluated at the pixel centres. Motion is a pupil tilt: the spot moves
by ``(dx, dy)`` px when the pupil field is multiplied by ``exp(2 pi i (dx x + dy y) / q)``
(pupil coordinates in units of the diameter D, focal coordinates in lambda/D, ``q`` px per
lambda/D). HCIPy makes the pupil (aperture, Zernike modes); the thousands of tilted
propagations of a blurred frame are one batched separable DFT in numpy, checked against
HCIPy's ``FraunhoferPropagator`` to round-off (``tests/test_hcipy_truth.py``).

Conventions are torchblur's: ``image[..., i, j]`` is the value at the centre of row i,
column j (x = j, y = i; point-sampled, no pixel-area integration); t = 0 at the command's
upward zero crossing and a window's ``start`` is measured from it; the motion is
``rest + A sin(omega t + phi) * direction``; ``peak_rate`` is the still spot's intensity per
second at its centre (a PSF's ``amplitude``), so frames are integrated counts (electrons).
The time integral is a midpoint rule with ``n_time`` samples per exposure (2000 by default;
``tests/test_hcipy_truth.py`` checks that doubling it changes the image by < 1e-4 of peak).

HCIPy (PyPI ``hcipy``) is imported here only; tests that use this module skip without it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import hcipy
import numpy as np
import torch
from threadpoolctl import threadpool_limits

from torchblur.design.windows import dual_exposure_windows
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.image.psf_from_still import psf_from_still
from torchblur.render.blur import render_blur
from torchblur.render.psf import GaussianPSF, KernelPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow

__all__ = ["SpotOptics", "HcipySpot", "camera_noise", "one_blas_thread", "make_problem", "fit_problems"]


def one_blas_thread():
    """numpy's BLAS on one thread inside the block (the batched DFT's small products run several
    times slower on two threads of a busy machine)."""
    return threadpool_limits(limits=1, user_api="blas")


@dataclass(frozen=True)
class SpotOptics:
    """Settings of the optical system.

    Args:
        q: focal-plane sampling, px per lambda/D (2.5: the Airy core's FWHM is ~2.6 px).
        pupil_px: samples across the pupil grid.
        obstruction: central obstruction ratio (0: a clear circular aperture).
        zernike_waves: ``((noll_index, coefficient in waves rms), ...)``; the default is
            0.035 wave of astigmatism (Noll 5) and 0.035 wave of coma (Noll 8): 0.05 wave rms.
        gaussian_pupil: if set, the pupil is ``exp(-r^2 / (2 s^2))`` with ``s`` this many
            pupil diameters, no aperture and no aberration (the focal spot is then a
            Gaussian of std ``q / (2 sqrt(2) pi s)`` px: the convention check).
    """

    q: float = 2.5
    pupil_px: int = 64
    obstruction: float = 0.0
    zernike_waves: tuple = ((5, 0.035), (8, 0.035))
    gaussian_pupil: float | None = None

    def gaussian_sigma_px(self) -> float:
        """Std (px) of the focal spot of a Gaussian pupil."""
        return self.q / (2 * math.sqrt(2) * math.pi * self.gaussian_pupil)


class HcipySpot:
    """A spot of given optics in a frame of ``height x width`` px with its rest position at
    ``center`` (x, y px)."""

    def __init__(self, optics: SpotOptics, center, height: int, width: int):
        self.optics, self.height, self.width = optics, height, width
        self.center = (float(center[0]), float(center[1]))
        q = optics.q
        if optics.gaussian_pupil is None:
            self.pupil_grid = hcipy.make_pupil_grid(optics.pupil_px, 1.0)
            if optics.obstruction > 0:
                ap = hcipy.make_obstructed_circular_aperture(1.0, optics.obstruction)
            else:
                ap = hcipy.make_circular_aperture(1.0)
            amp = np.asarray(hcipy.evaluate_supersampled(ap, self.pupil_grid, 4))
            phase = np.zeros_like(amp)
            if optics.zernike_waves:
                modes = max(n for n, _ in optics.zernike_waves)
                basis = np.asarray(hcipy.make_zernike_basis(modes, 1.0, self.pupil_grid, starting_mode=1).transformation_matrix)
                for noll, c in optics.zernike_waves:
                    phase = phase + 2 * math.pi * c * basis[:, noll - 1]
        else:
            # a grid of 10 s: the amplitude at its edge is exp(-12.5), about 4e-6
            self.pupil_grid = hcipy.make_pupil_grid(optics.pupil_px, 10 * optics.gaussian_pupil)
            r2 = np.asarray(self.pupil_grid.x) ** 2 + np.asarray(self.pupil_grid.y) ** 2
            amp = np.exp(-r2 / (2 * optics.gaussian_pupil**2))
            phase = np.zeros_like(amp)
        self.pupil = amp * np.exp(1j * phase)
        self._u = (np.arange(width) - self.center[0]) / q  # pixel centres in lambda/D
        self._v = (np.arange(height) - self.center[1]) / q
        xs, ys = (np.asarray(c) for c in self.pupil_grid.separated_coords)
        self._xs, self._ys = xs, ys
        self._P = self.pupil.reshape(ys.size, xs.size)  # [y, x]: HCIPy's order (x fastest)
        self._peak = float(np.abs(self._P.sum()) ** 2)  # the field at the undisplaced centre

    def reference_intensity(self, dx: float, dy: float) -> np.ndarray:
        """``[H, W]`` like :meth:`intensity`, by HCIPy's ``FraunhoferPropagator`` of the tilted
        pupil (slow: one propagation per call; the check of :meth:`intensity`)."""
        grid = hcipy.CartesianGrid(hcipy.SeparatedCoords([self._u, self._v]))
        prop = hcipy.FraunhoferPropagator(self.pupil_grid, grid)
        x, y = np.asarray(self.pupil_grid.x), np.asarray(self.pupil_grid.y)
        e = self.pupil * np.exp(2j * math.pi * (dx * x + dy * y) / self.optics.q)
        centre = hcipy.CartesianGrid(hcipy.SeparatedCoords([np.array([0.0, 1.0]), np.array([0.0, 1.0])]))
        peak = hcipy.FraunhoferPropagator(self.pupil_grid, centre).forward(hcipy.Wavefront(hcipy.Field(self.pupil, self.pupil_grid)))
        img = np.asarray(prop.forward(hcipy.Wavefront(hcipy.Field(e, self.pupil_grid))).intensity)
        return img.reshape(self.height, self.width) / float(np.asarray(peak.intensity)[0])

    def intensity(self, dx, dy) -> np.ndarray:
        """``[S, H, W]`` (or ``[H, W]`` for numbers): the spot displaced by ``(dx[s], dy[s])`` px,
        1 at the undisplaced centre. The Fraunhofer integral of the tilted pupil as a batched
        separable DFT to the pixel centres: a tilt of ``(dx, dy) / q`` shifts the focal
        coordinates, ``E_s(u, v) = sum_yx P[y, x] exp(-2 pi i ((u - dx_s / q) x + (v - dy_s / q) y))``
        (equal to :meth:`reference_intensity`, HCIPy's propagator, to round-off; a test)."""
        dx, dy = np.broadcast_arrays(np.asarray(dx, dtype=float), np.asarray(dy, dtype=float))
        q = self.optics.q
        # exp(-2 pi i (u - d / q) x) = exp(-2 pi i u x) exp(2 pi i d x / q): [S, W, nx] and [S, H, ny]
        ax = np.exp(-2j * math.pi * self._u[:, None] * self._xs)[None] * np.exp(2j * math.pi * dx.reshape(-1, 1) / q * self._xs)[:, None, :]
        ay = np.exp(-2j * math.pi * self._v[:, None] * self._ys)[None] * np.exp(2j * math.pi * dy.reshape(-1, 1) / q * self._ys)[:, None, :]
        with one_blas_thread():
            field = (ay @ self._P) @ ax.transpose(0, 2, 1)  # [S, H, W]
        out = (field.real ** 2 + field.imag ** 2) / self._peak
        return out.reshape(dx.shape + (self.height, self.width))

    def still(self, peak_rate: float, exposure_s: float) -> np.ndarray:
        """``[H, W]`` noise-free still frame (integrated intensity)."""
        return peak_rate * exposure_s * self.intensity(0.0, 0.0)

    def blurred(self, peak_rate: float, start_s, duration_s, amplitude: float, phase: float, omega: float,
                direction=(1.0, 0.0), n_time: int = 2000) -> np.ndarray:
        """``[E, H, W]`` noise-free frames of the motion ``amplitude sin(omega t + phase)``
        (px) along the unit ``direction`` over windows ``[start_s[e], start_s[e] + duration_s[e]]``."""
        starts = np.atleast_1d(np.asarray(start_s, dtype=float))
        durs = np.broadcast_to(np.asarray(duration_s, dtype=float), starts.shape)
        d = np.asarray(direction, dtype=float)
        d = d / np.linalg.norm(d)
        out = np.zeros((starts.size, self.height, self.width))
        for e, (t0, te) in enumerate(zip(starts, durs)):
            t = t0 + (np.arange(n_time) + 0.5) * te / n_time
            s = amplitude * np.sin(omega * t + phase)
            for chunk in np.array_split(s, max(1, n_time // 200)):
                out[e] += self.intensity(chunk * d[0], chunk * d[1]).sum(0)
            out[e] *= peak_rate * te / n_time
        return out


def camera_noise(frames: np.ndarray, rng: np.random.Generator, *, background: float = 20.0, read_noise: float = 3.0) -> np.ndarray:
    """Camera frames in electrons: ``Poisson(frames + background) + Normal(0, read_noise)``
    (the background, stray light plus dark current, stays in the frames)."""
    return rng.poisson(np.clip(frames, 0, None) + background).astype(float) + read_noise * rng.standard_normal(frames.shape)


# --------------------------------------------------------------------------- benchmark problems

H, W = 48, 64


def make_problem(seed: int, *, optics: SpotOptics = SpotOptics(), n_still: int = 32, n_time: int = 2000, rotated: bool = False,
                 still_peak: float = 3000.0, blur_peak: float = 4000.0, background: float = 20.0, read_noise: float = 3.0) -> dict:
    """One seeded problem: raw still frames and two raw blurred exposures of an HCIPy spot.

    20-800 Hz, M 3-10 px, random phase and trigger phase, windows from
    ``design.dual_exposure_windows`` (0.3 and 0.8 of the period, one start); the motion along x,
    or along a direction 0.5 rad from x (``rotated``). The source is set so the still spot's
    peak is ``blur_peak`` e- in the longer exposure (a lab sets its laser for its exposures);
    ``n_still`` still frames of peak ``still_peak`` e- (exposure chosen for it). Frames in
    electrons with the background and the noise of :func:`camera_noise`.
    """
    rng = np.random.default_rng(seed)
    f = 20 + 780 * rng.random()
    omega = 2 * math.pi * f
    M = 3 + 7 * rng.random()
    phi = (2 * rng.random() - 1) * math.pi
    trig = 2 * math.pi * rng.random()
    center = (31.5 + rng.random() - 0.5, 23.5 + rng.random() - 0.5)
    direction = (math.cos(0.5), math.sin(0.5)) if rotated else (1.0, 0.0)
    win = dual_exposure_windows(omega, fractions=(0.3, 0.8), trigger_phase=trig)
    spot = HcipySpot(optics, center, H, W)
    durs = win.duration.numpy()
    rate = blur_peak / durs.max()
    clean = spot.blurred(rate, win.start.numpy(), durs, M, phi, omega, direction=direction, n_time=n_time)
    still_exposure = still_peak / rate
    still_clean = spot.still(rate, still_exposure)
    return dict(
        still=camera_noise(np.broadcast_to(still_clean, (n_still, H, W)), rng, background=background, read_noise=read_noise),
        still_exposure=still_exposure, still_clean=still_clean, frames=camera_noise(clean, rng, background=background, read_noise=read_noise),
        clean=clean, window=win, omega=omega, direction=direction, M=M, phi=phi, freq_hz=f, rate=rate,
    )


def _fit_group(problems: list, res: list, passes: int):
    """One batched two-pass ``fit_sinusoid`` of problems whose PSFs are of one kind."""
    raw = torch.stack([torch.as_tensor(p["frames"]) for p in problems])
    images = raw - torch.stack([r.background for r in res])[:, None, None, None]
    if res[0].kind == "gaussian":
        psf = GaussianPSF(torch.stack([r.psf.center for r in res]), torch.stack([r.psf.cov for r in res]),
                          torch.stack([r.psf.amplitude for r in res]))
        psf_e = GaussianPSF(psf.center[:, None], psf.cov[:, None], psf.amplitude[:, None])
    else:
        psf = KernelPSF(torch.stack([r.psf.kernel for r in res]))
        psf_e = KernelPSF(psf.kernel[:, None])
    win = ExposureWindow(torch.stack([p["window"].start for p in problems]), torch.stack([p["window"].duration for p in problems]))
    omega = torch.tensor([p["omega"] for p in problems], dtype=torch.float64)
    d = torch.tensor([p["direction"] for p in problems], dtype=torch.float64)
    noise = torch.stack([r.frame_noise_std(x) for r, x in zip(res, raw)])
    for k in range(passes):
        fit = fit_sinusoid(images, psf, win, omega, axes=d, noise_std=noise)
        if k + 1 < passes:
            traj = Sinusoid(fit.amplitude[:, None, None] * d[:, None, :], fit.phase[:, None, None].expand(-1, 1, 2), omega[:, None])
            model = render_blur(traj, psf_e, win, height=H, width=W)
            noise = torch.stack([r.frame_noise_std(m + r.background) for r, m in zip(res, model)])
    return fit


def fit_problems(problems: list, kind: str, *, passes: int = 2, background: float | None = None) -> dict:
    """``psf_from_still(kind=...)`` per problem, then batched ``fit_sinusoid`` (one batch per
    PSF kind) along each problem's direction, weighted by the camera noise model the still
    frames gave (``StillPSF.frame_noise_std``): first of the raw frames, then (``passes`` = 2)
    of the first fit's model plus the background, which removes the bias of weights taken from
    noisy data. ``background``: the frames' level, if known (else psf_from_still estimates
    it). Returns numpy arrays: errors (M in %, phase in deg), error / std, status,
    chosen kinds, the chi2 of each PSF and ``StillPSF.kernel_noise_factor``."""
    res = [psf_from_still(torch.as_tensor(p["still"]), p["still_exposure"], kind=kind, background=background) for p in problems]
    n = len(problems)
    amp, ph, amp_std, ph_std, status, chi2 = (np.full(n, np.nan) for _ in range(6))
    for k in ("gaussian", "kernel"):
        idx = [i for i, r in enumerate(res) if r.kind == k]
        if idx:
            fit = _fit_group([problems[i] for i in idx], [res[i] for i in idx], passes)
            amp[idx], ph[idx] = fit.amplitude.numpy(), fit.phase.numpy()
            amp_std[idx], ph_std[idx], status[idx] = fit.amplitude_std.numpy(), fit.phase_std.numpy(), fit.status.numpy()
            chi2[idx] = fit.reduced_chi2.numpy()
    M = np.array([p["M"] for p in problems])
    dphi = np.angle(np.exp(1j * (ph - np.array([p["phi"] for p in problems]))))
    factor = np.array([float(r.kernel_noise_factor(p["window"].duration)) for r, p in zip(res, problems)])
    return dict(
        factor=factor, err_M_pct=100 * (amp - M) / M, err_phi_deg=np.degrees(dphi), z_M=(amp - M) / amp_std, z_phi=dphi / ph_std, status=status,
        kinds=[r.kind for r in res], chi2_gaussian=np.array([float(r.chi2_gaussian) for r in res]),
        chi2_kernel=np.array([float(r.chi2_kernel) for r in res]), reduced_chi2=chi2, freq_hz=np.array([p["freq_hz"] for p in problems]),
    )
