"""A user rig whose frames are HCIPy diffraction spots (issue 30): the simulated rig's plant,
camera, timing and noise, but every image rendered by HCIPy's optics (a circular aperture with
astigmatism and coma, :class:`hcipy_frames.HcipySpot`) instead of torchblur's Gaussian
renderer: an independent optics engine, which torchblur's Gaussian direct model does not match.

    rig = hcipy_rig.hcipy_rig(cfg)          # cfg: an IdentifyConfig (plant, camera, seed)
    res = torchblur.identify(cfg, rig)
"""
from __future__ import annotations

import math

import numpy as np
import torch

import hcipy_frames as hf
from torchblur.render.camera import CameraModel
from torchblur.rig.factory import plant_of
from torchblur.rig.simulated import SimulatedRig


class HcipyRig(SimulatedRig):
    """:class:`~torchblur.rig.simulated.SimulatedRig` whose ``_render`` integrates HCIPy spots
    over each exposure (``n_time`` midpoint nodes per window); the PSF's centre and amplitude
    (peak electrons per second) are the rig's, its covariance is ignored (the optics decide)."""

    def __init__(self, *args, optics: hf.SpotOptics = hf.SpotOptics(), n_time: int = 300, **kwargs):
        super().__init__(*args, **kwargs)
        self.optics, self.n_time, self._spots = optics, int(n_time), {}

    def _spot(self, cx: float, cy: float, h: int, w: int) -> hf.HcipySpot:
        key = (round(cx, 9), round(cy, 9), h, w)
        if key not in self._spots:
            self._spots[key] = hf.HcipySpot(self.optics, (cx, cy), h, w)
        return self._spots[key]

    def _render(self, trajectory, psf, window, shape=None) -> torch.Tensor:
        H, W = self._frame_shape if shape is None else shape
        cx, cy = (float(v) for v in psf.center.detach().reshape(-1)[:2])
        spot = self._spot(cx, cy, H, W)
        N = window.shape[0]
        # midpoint nodes, 20 per px of path (at most n_time; one for a spot at rest)
        path = float(trajectory.path_length(window).detach().max()) if window.shape[0] else 0.0
        S = int(min(self.n_time, max(1, math.ceil(20 * path))))
        t = window.start.detach()[:, None] + window.duration.detach()[:, None] * ((torch.arange(S, dtype=torch.float64) + 0.5) / S)
        pos = trajectory.position(t).detach().numpy()  # [N, S, 2] px
        amp = float(psf.amplitude.detach().reshape(-1)[0])
        if S == 1 and not np.any(pos):
            out = np.broadcast_to(spot.intensity(0.0, 0.0), (N, H, W)).copy()
        else:
            out = np.stack([spot.intensity(pos[n, :, 0], pos[n, :, 1]).sum(0) for n in range(N)])
        out *= amp * (window.duration.detach().numpy() / S)[:, None, None]
        return torch.from_numpy(out).clamp_min(0.0)

    def _render_near(self, trajectory, psf, window) -> torch.Tensor:
        return self._render(trajectory, psf, window)


def hcipy_rig(cfg, **kwargs) -> HcipyRig:
    """The rig of ``cfg`` (as :func:`torchblur.rig.factory.build_simulated_rig`) with HCIPy spots."""
    c = cfg.camera
    camera = CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                         bit_depth=int(c.bit_depth))
    return HcipyRig(plant=plant_of(cfg), camera=camera, frame_shape=(int(c.height), int(c.width)), psf_sigma_px=c.psf_sigma_px,
                    frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s, readout_s=c.readout_s,
                    max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s, seed=int(cfg.seed),
                    direction=tuple(float(v) for v in cfg.plant.direction), input_limit=float(cfg.plant.input_limit), **kwargs)


def issue30_plant(delay_s: float = 25e-6, gain: float = 10.0):
    """``(num, den, delay_s)``: modes at 600 Hz (damping 0.08) and 2 kHz (damping 0.05), ``gain`` px
    per input unit at DC, 25 us delay (the plant of issue 30)."""
    w1, w2 = 2 * math.pi * 600.0, 2 * math.pi * 2000.0
    den = np.polymul([1.0, 2 * 0.08 * w1, w1 * w1], [1.0, 2 * 0.05 * w2, w2 * w2])
    return [gain * w1 * w1 * w2 * w2], [float(v) for v in den], delay_s
