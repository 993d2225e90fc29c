"""Test helper: Shack-Hartmann frames of a deformable mirror rendered with HCIPy (issue 23).

An independent optics engine for the DM route. HCIPy makes every optical part:

- the pupil: a circular aperture of diameter ``D`` (10 lenslets across, the DM's 8 actuator
  pitches), sampled at the camera's pixels (``pitch_px`` samples per lenslet);
- the DM: HCIPy's :class:`hcipy.DeformableMirror` with Gaussian influence functions
  (:func:`hcipy.make_gaussian_influence_functions`, 8 x 8 grid, crosstalk ``coupling`` at one
  pitch), the actuators whose centre lies within ``n_across / 2 + 0.1`` pitches of the pupil
  centre kept (52 of 64), in row-major order, the surface doubled on reflection (HCIPy's
  ``exp(2 i k surface)``); optionally misregistered: actuator ``(x, y)`` (pitches) sits at
  ``magnification R(rotation) (x, y) + shift`` in the pupil;
- the lenslets: a square :class:`hcipy.MicroLensArray` of ``n_lenslets x n_lenslets``
  (centres at ``(i - (n - 1) / 2) d``, the layout of ``configs/identify_dm.yaml``: spot (r, c)
  at rest at pixel ``((c + 1/2) pitch_px - 1/2, (r + 1/2) pitch_px - 1/2)``) and HCIPy's
  :class:`hcipy.FresnelPropagator` over its focal length to the camera: every lenslet's spot is
  the diffraction pattern of its square subaperture (sinc^2 with its wings), the fields of all
  lenslets add coherently (the crosstalk between neighbours) and the camera samples the
  intensity at the pixel centres.

The propagation of many time samples at once uses HCIPy's own propagator's pieces (the lenslet
array's phase and the Fresnel filter's transfer function, zero padded as HCIPy does) in one
batched numpy FFT; ``tests/test_dm_hcipy.py`` checks it against HCIPy's ``forward`` to round-off.

Dynamics: actuator j's surface follows its command through
``H_j(s) = gain_j wn_j^2 / (s^2 + 2 zeta_j wn_j s + wn_j^2) exp(-s delay_j)`` (seeded draws,
one dead, one weak). A pattern sine ``amplitude pattern sin(omega t)`` in steady state gives
``a_j(t) = amplitude pattern_j |H_j| sin(omega t + arg H_j)``; the surface is linear in the
``a_j`` but the spot image is not linear in the surface, so each exposure is the sum of the
images at Gauss-Legendre nodes in time (the count from the motion's path,
:meth:`HcipySH.node_count`; a test checks that doubling it changes a frame by < 1e-3 of its peak).

Intensity unit: 1 at the peak of the brightest still spot; frames are that times the rig's
``peak_e_per_s`` and the exposure (electrons). Conventions are torchblur's (x = column, y = row,
t = 0 at the command's upward zero crossing).

HCIPy (PyPI ``hcipy``) is imported here only; tests that use this module skip without it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import hcipy
import numpy as np
import scipy.fft

from hcipy_frames import one_blas_thread

__all__ = ["SHOptics", "Dynamics", "HcipySH", "draw_dynamics"]

_WAVELENGTH = 1e-6  # m
_PIXEL = 10e-6  # m: one camera pixel = one pupil sample


@dataclass(frozen=True)
class SHOptics:
    """The sensor and the mirror's geometry.

    Args:
        n_lenslets: lenslets across the pupil (10).
        pitch_px: camera pixels per lenslet (16).
        q: spot size, px per ``lambda f / d`` (the sinc^2's first zero; 3: a core of FWHM 2.7 px).
        dm_across: actuators across the pupil (8).
        coupling: influence function at one actuator pitch (0.15).
        slope_px: spot motion (px) per unit mean influence slope per actuator pitch (sets the
            stroke: torchblur's ``wfs.slope_px``).
        shift: DM shift (x, y) in actuator pitches; rotation_deg; magnification: the misregistration.
        zero_padding: the Fresnel filter's zero padding (HCIPy's default 2).
    """

    n_lenslets: int = 10
    pitch_px: int = 16
    q: float = 3.0
    dm_across: int = 8
    coupling: float = 0.15
    slope_px: float = 1.0
    shift: tuple = (0.0, 0.0)
    rotation_deg: float = 0.0
    magnification: float = 1.0
    zero_padding: float = 2.0


@dataclass(frozen=True)
class Dynamics:
    """Per-actuator dynamics ``[N]``: mode (Hz), damping, gain, delay (s)."""

    mode_hz: np.ndarray
    damping: np.ndarray
    gain: np.ndarray
    delay_s: np.ndarray

    def response(self, freq_hz) -> np.ndarray:
        """``H_j(j 2 pi f)``: ``[N]`` complex for a number, ``[N, F]`` for an array."""
        f = np.asarray(freq_hz, dtype=float)
        w = 2 * np.pi * f[..., None] if f.ndim else 2 * np.pi * f
        wn = 2 * np.pi * self.mode_hz
        h = self.gain * wn**2 / (wn**2 - w**2 + 2j * self.damping * wn * w) * np.exp(-1j * w * self.delay_s)
        return h.T if f.ndim else h

    @property
    def dead(self) -> np.ndarray:
        return self.gain == 0


def draw_dynamics(n: int, seed: int, *, mode_hz: float = 900.0, damping: float = 0.08, delay_s: float = 20e-6,
                  dead: int = 20, weak: int = 33, weak_gain: float = 0.4) -> Dynamics:
    """Seeded dynamics of ``n`` actuators: mode +-5 %, damping +-10 %, gain +-2 %, delay +-5 us
    (uniform), actuator ``dead`` gain 0, ``weak`` ``weak_gain`` times its gain."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, size=(4, n))
    gain = 1 + 0.02 * u[2]
    gain[weak] *= weak_gain
    gain[dead] = 0.0
    return Dynamics(mode_hz=mode_hz * (1 + 0.05 * u[0]), damping=damping * (1 + 0.1 * u[1]), gain=gain,
                    delay_s=delay_s + 5e-6 * u[3])


class HcipySH:
    """The HCIPy Shack-Hartmann sensor behind a DM (module docstring)."""

    def __init__(self, optics: SHOptics = SHOptics()):
        self.optics = o = optics
        self.workers = 1  # scipy.fft threads of the batched propagation (a benchmark's --jobs)
        self.device = None  # a torch device: the batched propagation in torch there (a benchmark's --device)
        self._on = None
        n_px = o.n_lenslets * o.pitch_px
        self.shape = (n_px, n_px)
        d = o.pitch_px * _PIXEL  # lenslet pitch (m)
        self.D = o.n_lenslets * d
        self.act_pitch = self.D / o.dm_across
        self.focal = o.q * _PIXEL * d / _WAVELENGTH  # lambda f / d = q px
        self.grid = hcipy.make_pupil_grid(n_px, self.D)
        self.aperture = np.asarray(hcipy.evaluate_supersampled(hcipy.make_circular_aperture(self.D), self.grid, 4))
        x = (np.arange(o.n_lenslets) - (o.n_lenslets - 1) / 2) * d
        mla = hcipy.MicroLensArray(self.grid, hcipy.CartesianGrid(hcipy.SeparatedCoords((x, x))), self.focal)
        self.sh_optics = hcipy.ShackHartmannWavefrontSensorOptics(self.grid, mla)
        self.dm = hcipy.DeformableMirror(self._influence())
        self.n_actuators = self.dm.num_actuators
        # the stroke: slope_px px per unit mean slope of a unit influence function (per actuator pitch)
        self.stroke = o.slope_px * _PIXEL * self.act_pitch / (2 * self.focal)
        tm = self.dm.influence_functions.transformation_matrix
        self._if = np.asarray(tm.todense() if hasattr(tm, "todense") else tm).T * self.stroke  # [N, P] m/unit
        self._lens, self._tf, self._cut = self._propagation_pieces()
        self._pupil_lens = (self.aperture * self._lens).astype(np.complex64)
        self._tf = self._tf.astype(np.complex64)
        self._norm = 1.0
        self._norm = float(self.intensity(np.zeros((1, self.n_actuators)))[0].max())
        self.valid = self._valid_subapertures()

    # ------------------------------------------------------------------ optics

    def _influence(self) -> hcipy.ModeBasis:
        """HCIPy's Gaussian influence functions (:func:`hcipy.make_gaussian_pokes` with the width
        and cut-off :func:`hcipy.make_gaussian_influence_functions` uses) at the kept actuators of
        HCIPy's actuator grid (:func:`hcipy.make_actuator_positions`), moved by the misregistration
        (the width scales with the magnification)."""
        o = self.optics
        n = o.dm_across
        pos = hcipy.make_actuator_positions(n, self.act_pitch)
        xy = np.stack([np.asarray(pos.x), np.asarray(pos.y)], -1) / self.act_pitch  # pitches, row-major (x fastest)
        keep = np.flatnonzero(np.hypot(xy[:, 0], xy[:, 1]) <= n / 2 + 0.1)
        self.actuator_xy = xy[keep]  # nominal (pitches)
        th = math.radians(o.rotation_deg)
        rot = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        true_xy = o.magnification * self.actuator_xy @ rot.T + np.asarray(o.shift, dtype=float)
        self.true_actuator_xy = true_xy
        sigma = o.magnification * self.act_pitch / np.sqrt(-2 * np.log(o.coupling))
        mu = hcipy.CartesianGrid(hcipy.UnstructuredCoords((true_xy[:, 0] * self.act_pitch, true_xy[:, 1] * self.act_pitch)))
        pokes = hcipy.make_gaussian_pokes(None, mu, sigma, cutoff=3 * o.magnification * self.act_pitch / sigma)
        cols = [np.asarray(f.todense() if hasattr(f, "todense") else f).reshape(-1) for f in
                hcipy.evaluate_supersampled(pokes, self.grid, 1, make_sparse=True)]
        return hcipy.ModeBasis(np.stack(cols, 1), self.grid)  # [P, N]

    def _propagation_pieces(self):
        """HCIPy's lenslet phase ``[P]``, the Fresnel filter's transfer function (ifftshifted,
        on its zero-padded grid) and the cut-out of the input grid in it."""
        prop = hcipy.FresnelPropagator(self.grid, self.focal, zero_padding=self.optics.zero_padding)
        self.propagator = prop
        lens = self.sh_optics.micro_lens_array.forward(hcipy.Wavefront(self.grid.ones() + 0j, _WAVELENGTH))
        prop.forward(lens)  # builds its instance: the Fourier filter and its transfer function
        ff = next(iter(prop._instance_data_cache.values())).fourier_filter
        return np.asarray(lens.electric_field), np.asarray(ff._transfer_function), ff.cutout

    def _image_of(self, pupil_field) -> np.ndarray:
        """``[H, W]`` intensity of one pupil field ``[P]`` (after the lenslets) on the camera."""
        H, W = self.shape
        buf = pupil_field.reshape(H, W) if self._cut is None else np.zeros(self._tf.shape, dtype=np.complex64)
        if self._cut is not None:
            buf[self._cut] = pupil_field.reshape(H, W)
        f = scipy.fft.ifft2(scipy.fft.fft2(buf) * self._tf)
        f = f if self._cut is None else f[self._cut]
        return (f.real**2 + f.imag**2) / self._norm

    def surface(self, commands) -> np.ndarray:
        """``[S, P]`` DM surface (m) of the actuator commands ``[S, N]``."""
        return np.asarray(commands, dtype=float) @ self._if

    def field(self, commands) -> np.ndarray:
        """``[S, H, W]`` complex64 field on the camera of the commands ``[S, N]`` (batched FFT in
        single precision: 1e-6 of the peak from HCIPy's double-precision ``forward``)."""
        k = 2 * np.pi / _WAVELENGTH
        phase = (2 * k * self.surface(commands)).astype(np.float32)  # [S, P]
        e = (np.cos(phase) + 1j * np.sin(phase)).astype(np.complex64) * self._pupil_lens
        S = e.shape[0]
        H, W = self.shape
        if self._cut is None:
            buf = e.reshape(S, H, W)
        else:
            buf = np.zeros((S,) + self._tf.shape, dtype=np.complex64)
            buf[(slice(None),) + self._cut] = e.reshape(S, H, W)
        f = scipy.fft.fft2(buf, workers=self.workers, overwrite_x=True)
        f *= self._tf
        f = scipy.fft.ifft2(f, workers=self.workers, overwrite_x=True)
        return f if self._cut is None else f[(slice(None),) + self._cut]

    def intensity(self, commands) -> np.ndarray:
        """``[S, H, W]`` camera intensity (1 at the brightest still spot's peak); with
        :attr:`device` set, :meth:`field`'s propagation in torch on that device (the same
        single-precision FFTs; a test checks the two agree)."""
        if self.device is not None:
            return self._intensity_torch(commands)
        f = self.field(commands)
        return (f.real**2 + f.imag**2) / self._norm

    def _intensity_torch(self, commands) -> np.ndarray:
        import torch

        dev = torch.device(self.device)
        if self._on is None or self._on[0] != dev:
            self._on = (dev, torch.as_tensor(self._if, device=dev), torch.as_tensor(self._pupil_lens, device=dev),
                        torch.as_tensor(self._tf, device=dev))
        _, infl, lens, tf = self._on
        phase = (2 * (2 * np.pi / _WAVELENGTH) * (torch.as_tensor(np.asarray(commands, dtype=float), device=dev) @ infl)).float()
        e = torch.polar(torch.ones_like(phase), phase) * lens
        S, (H, W) = e.shape[0], self.shape
        if self._cut is None:
            buf = e.reshape(S, H, W)
        else:
            buf = torch.zeros((S,) + tuple(tf.shape), dtype=torch.complex64, device=dev)
            buf[(slice(None),) + self._cut] = e.reshape(S, H, W)
        f = torch.fft.ifft2(torch.fft.fft2(buf) * tf)
        f = f if self._cut is None else f[(slice(None),) + self._cut]
        return ((f.real**2 + f.imag**2) / self._norm).cpu().numpy()

    def reference_intensity(self, command) -> np.ndarray:
        """``[H, W]`` the same by HCIPy's own ``DeformableMirror.forward`` and the sensor optics'
        ``forward`` (one command ``[N]``; slow; the check of :meth:`intensity`)."""
        self.dm.actuators = np.asarray(command, dtype=float) * self.stroke
        wf = hcipy.Wavefront(hcipy.Field(self.aperture + 0j, self.grid), _WAVELENGTH)
        lens = self.sh_optics.micro_lens_array.forward(self.dm.forward(wf))
        out = self.propagator.forward(lens)  # = sh_optics.forward, zero padded as the batched path
        return np.asarray(out.intensity).reshape(self.shape) / self._norm

    def still(self) -> np.ndarray:
        """``[H, W]`` the still frame's intensity."""
        return self.intensity(np.zeros((1, self.n_actuators)))[0]

    def _valid_subapertures(self) -> np.ndarray:
        """``[M]`` row-major lenslet indices at least half lit (80 of 10 x 10)."""
        n, p = self.optics.n_lenslets, self.optics.pitch_px
        lit = self.aperture.reshape(n, p, n, p).mean((1, 3))
        return np.flatnonzero(lit.reshape(-1) >= 0.5)

    @property
    def rest_px(self) -> np.ndarray:
        """``[M, 2]`` nominal rest positions (x, y px) of the valid spots."""
        r, c = np.divmod(self.valid, self.optics.n_lenslets)
        p = self.optics.pitch_px
        return np.stack([(c + 0.5) * p - 0.5, (r + 0.5) * p - 0.5], -1).astype(float)

    # ------------------------------------------------------------------ motion

    def tilted(self, tx: float, ty: float) -> np.ndarray:
        """``[H, W]`` the still frame under a whole-pupil tilt that moves every spot by ``(tx, ty)``
        px (wavefront slope ``t px / f``)."""
        k = 2 * np.pi / _WAVELENGTH
        X, Y = np.asarray(self.grid.x), np.asarray(self.grid.y)
        return self._image_of(self._pupil_lens * np.exp(1j * k * (tx * X + ty * Y) * _PIXEL / self.focal).astype(np.complex64))

    def tilt_derivatives(self, h: float = 0.05) -> tuple:
        """``(dx, dy)`` ``[H, W]`` each: the image's derivatives along a spot shift in x and y, from
        whole-pupil tilts of ``+-h`` px (:meth:`tilted`)."""
        return (self.tilted(h, 0) - self.tilted(-h, 0)) / (2 * h), (self.tilted(0, h) - self.tilted(0, -h)) / (2 * h)

    def shift_truth(self, poke: float = 0.05) -> np.ndarray:
        """``[2M, N]`` the fitted-shift truth of the static interaction matrix (px per unit
        command): spot m's best-fit shift under a +-``poke`` command of actuator j (least squares
        of the image change in its 16 x 16 cell on the image's derivatives along x and y, these
        from whole-pupil tilts of +-0.05 px), rows x of all M spots then y."""
        N, p = self.n_actuators, self.optics.pitch_px
        dx, dy = self.tilt_derivatives()
        cmd = np.concatenate([poke * np.eye(N), -poke * np.eye(N)])
        I = self.intensity(cmd)
        dI = (I[:N] - I[N:]) / (2 * poke)  # [N, H, W]
        r, c = np.divmod(self.valid, self.optics.n_lenslets)
        out = np.zeros((2, self.valid.size, N))
        for m, (ri, ci) in enumerate(zip(r, c)):
            cell = (slice(ri * p, ri * p + p), slice(ci * p, ci * p + p))
            J = np.stack([dx[cell].reshape(-1), dy[cell].reshape(-1)], 1)
            out[:, m] = np.linalg.lstsq(J, dI[(slice(None),) + cell].reshape(N, -1).T, rcond=None)[0]
        return out.reshape(2 * self.valid.size, N)

    def node_count(self, motion_px: float, omega: float, duration_s: float) -> int:
        """Gauss-Legendre nodes for an exposure of a spot moving ``motion_px`` (amplitude):
        3 per px of path plus 8, at most 512 (the convergence test's rule)."""
        path = motion_px * min(omega * duration_s, 2 * math.pi * math.ceil(omega * duration_s / (2 * math.pi)))
        return int(min(512, 8 + math.ceil(3 * path)))

    def blurred(self, command_amplitude, command_phase, omega: float, starts, durations, nodes) -> np.ndarray:
        """``[n, H, W]`` time integrals (intensity x s) over windows ``[start, start + duration]``
        of the actuators moving as ``a_j(t) = command_amplitude[j] sin(omega t + command_phase[j])``
        (``[N]``), ``nodes`` Gauss-Legendre nodes per window (a number or ``[n]``)."""
        starts = np.atleast_1d(np.asarray(starts, dtype=float))
        durs = np.broadcast_to(np.asarray(durations, dtype=float), starts.shape)
        nodes = np.broadcast_to(np.asarray(nodes, dtype=int), starts.shape)
        out = np.zeros((starts.size,) + self.shape)
        A, ph = np.asarray(command_amplitude, float), np.asarray(command_phase, float)
        for i, (t0, te, S) in enumerate(zip(starts, durs, nodes)):
            x, w = np.polynomial.legendre.leggauss(int(S))
            t = t0 + (x + 1) * te / 2
            cmd = A[None, :] * np.sin(omega * t[:, None] + ph[None, :])
            step = 32 if self.device is None else 256
            for s in range(0, int(S), step):
                out[i] += np.tensordot(w[s:s + step], self.intensity(cmd[s:s + step]), 1)
            out[i] *= te / 2
        return out
