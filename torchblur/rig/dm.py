"""A simulated deformable-mirror rig: a :class:`~torchblur.dm.mirror.DeformableMirror` read by a
:class:`~torchblur.dm.shack_hartmann.ShackHartmann` sensor whose camera is slow.

:class:`SimulatedDMRig` is a :class:`~torchblur.rig.simulated.SimulatedRig` whose spots are the
sensor's M valid spots, with :meth:`SimulatedDMRig.pattern_sine`: actuator j driven with
``amplitude * pattern[j] * sin(omega t)`` from rest at t = 0; after the settling wait spot m moves
on ``s(t) = amplitude Im(D(j omega) pattern e^{j omega t})`` (x: rows m, y: rows M + m),
``D(j omega) = G diag(H_j(j omega))`` ``[2M, N]`` (:meth:`SimulatedDMRig.truth_D`), px per command
unit. Each spot is rendered on a square crop of side ``ceil(pitch_px) + 2 ceil(6 sigma)`` px; a
command that would carry a spot within 6 PSF sigmas of its crop's edge is refused
(``ParameterError`` naming ``amplitude``): docs/deformable_mirrors.md, "The simulated rig".
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from torchblur.errors import InputTypeError, ParameterError, check_real_scalar, check_type
from torchblur.image.spots import SpotLayout
from torchblur.render.blur import render_blur
from torchblur.render.camera import CameraModel
from torchblur.render.psf import GaussianPSF
from torchblur.render.trajectory import Sinusoid
from torchblur.render.window import ExposureWindow
from torchblur.rig.base import Capture, PatternSines
from torchblur.rig.simulated import SimulatedRig
from torchblur.systems.lti import Plant
from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.registration import Registration
from torchblur.dm.shack_hartmann import ShackHartmann

__all__ = ["SimulatedDMRig", "spot_motion"]

_F64 = torch.float64
_EDGE_SIGMAS = 6.0
_CHUNK_ELEMENTS = 1 << 22  # crop pixels x spots x frames per render call


def spot_motion(D: np.ndarray, pattern: np.ndarray, amplitude: float) -> tuple[np.ndarray, np.ndarray]:
    """The sinusoid of every spot for one pattern: ``(amplitude_px [M, 2], phase_rad [M, 2])``
    with ``s_a(t) = amplitude_px[m, a] sin(omega t + phase_rad[m, a])`` and ``Y = D @ pattern``
    (``D [2M, N]`` complex at omega, ``pattern [N]``, rows x of all M then y)."""
    Y = amplitude * (np.asarray(D) @ np.asarray(pattern, dtype=np.float64))
    M = Y.shape[0] // 2
    Y = np.stack([Y[:M], Y[M:]], -1)
    return np.abs(Y), np.angle(Y)


class SimulatedDMRig(PatternSines, SimulatedRig):
    """The simulated DM rig (module docstring).

    Args (keyword-only):
        mirror: the :class:`~torchblur.dm.mirror.DeformableMirror` (its ``input_limit`` bounds
            every command).
        wfs: the :class:`~torchblur.dm.shack_hartmann.ShackHartmann` sensor (frame shape, spot
            positions and PSFs).
        camera: the :class:`~torchblur.render.camera.CameraModel`.
        frame_rate_hz, trigger_delay_s, readout_s, max_exposure_s, latency_s, jitter_s,
        peak_e_per_s, seed: as :class:`~torchblur.rig.simulated.SimulatedRig`.
        registration: the mirror's true :class:`~torchblur.dm.registration.Registration` on the
            sensor (None: nominal); its G is then the geometry at that registration.
    """

    def __init__(self, *, mirror: DeformableMirror, wfs: ShackHartmann, camera: CameraModel, frame_rate_hz: float = 30.0,
                 trigger_delay_s: float = 0.0, readout_s: float = 1e-3, max_exposure_s: float = 1.0, latency_s: float = 12e-6,
                 jitter_s: float = 0.2e-6, peak_e_per_s: float = 1e6, seed: int = 0, registration: Registration | None = None):
        check_type(mirror, "mirror", DeformableMirror, "a DeformableMirror")
        check_type(wfs, "wfs", ShackHartmann, "a ShackHartmann")
        M = wfs.n_valid
        rest = torch.as_tensor(wfs.rest_px, dtype=_F64)
        sigma = torch.as_tensor(wfs.sigma_spots_px, dtype=_F64)
        layout = SpotLayout(rest_px=rest, cov=sigma[:, None, None] ** 2 * torch.eye(2, dtype=_F64),
                            response=torch.zeros(M, 2, 1, dtype=_F64), index=torch.as_tensor(wfs.grid_index))
        super().__init__(plant=Plant(num=(1.0,), den=(1.0,)), camera=camera, frame_shape=wfs.frame_shape, frame_rate_hz=frame_rate_hz,
                         trigger_delay_s=trigger_delay_s, readout_s=readout_s, max_exposure_s=max_exposure_s, latency_s=latency_s,
                         jitter_s=jitter_s, peak_e_per_s=peak_e_per_s, seed=seed, spots=layout)
        self._mirror = mirror
        self._wfs = wfs
        if registration is not None and not isinstance(registration, Registration):
            raise InputTypeError(f"registration: expected a Registration or None, got {type(registration).__name__}")
        self._registration = Registration() if registration is None else registration
        self._hold_generator = None  # pattern_ladder's noise stream (created at its first call)
        self._G = wfs.geometry_matrix(mirror, registration=registration)
        pad = math.ceil(_EDGE_SIGMAS * float(sigma.max()))
        self._crop = math.ceil(wfs.pitch_px) + 2 * pad
        corner = torch.floor(rest - (self._crop - 1) / 2).long()  # [M, 2] (x0, y0) of each crop
        self._corner = corner
        self._margin = int(max(0, -int(corner.min()), int((corner + self._crop).max()) - min(wfs.frame_shape)))

    # ------------------------------------------------------------------ the model

    @property
    def mirror(self) -> DeformableMirror:
        return self._mirror

    @property
    def wfs(self) -> ShackHartmann:
        return self._wfs

    @property
    def registration(self) -> Registration:
        """The mirror's true registration on the sensor (for tests: a pipeline fits it)."""
        return self._registration

    @property
    def geometry(self) -> np.ndarray:
        """G ``[2M, N]`` (px per input unit of the nominal actuator, at the true registration)."""
        return self._G.copy()

    @property
    def input_limit(self) -> float:
        """The largest command magnitude (input units) the mirror accepts."""
        return self._mirror.input_limit

    @property
    def n_actuators(self) -> int:
        """N, the mirror's actuators."""
        return self._mirror.n_actuators

    def truth_D(self, freq_hz) -> np.ndarray:
        """The dynamic interaction matrix ``D = G diag(H_j)``: complex ``[2M, N, F]`` (``[2M, N]``
        for a number). For tests and benchmarks only: a pipeline must measure it."""
        h = self._mirror.response(freq_hz)
        return self._G[:, :, None] * h[None] if h.ndim == 2 else self._G * h[None, :]

    def truth(self, freq_hz):  # the base rig's single-plant truth has no meaning here
        raise ParameterError("truth: a DM rig has no single plant; use truth_D(freq_hz)")

    def spot_truth(self, freq_hz):
        raise ParameterError("spot_truth: a DM rig has no single plant; use truth_D(freq_hz)")

    # ------------------------------------------------------------------ rendering

    def _render_spots(self, amplitude: torch.Tensor, phase: torch.Tensor, omega: float, window: ExposureWindow,
                      power: float) -> torch.Tensor:
        """Expected electrons ``[n, H, W]`` of every spot moving on its sinusoid
        (``amplitude``, ``phase`` ``[M, 2]``) over the windows ``[n]`` (module docstring)."""
        H, W = self._frame_shape
        M, c, pad = amplitude.shape[0], self._crop, self._margin
        centre = self._psf.center - self._corner.to(_F64)  # [M, 2] in crop coordinates
        psf = GaussianPSF(centre, self._psf.cov, self._psf.amplitude * power)
        traj = Sinusoid(amplitude, phase, torch.tensor(omega, dtype=_F64))
        n = window.shape[0]
        out = torch.zeros((n, H + 2 * pad, W + 2 * pad), dtype=_F64)
        step = max(1, _CHUNK_ELEMENTS // (M * c * c))
        x0 = (self._corner[:, 0] + pad).tolist()
        y0 = (self._corner[:, 1] + pad).tolist()
        for i in range(0, n, step):
            win = ExposureWindow(window.start[i:i + step, None], window.duration[i:i + step, None])
            crops = render_blur(traj, psf, win, height=c, width=c, settings=self._settings)  # [b, M, c, c]
            for m in range(M):
                out[i:i + step, y0[m]:y0[m] + c, x0[m]:x0[m] + c] += crops[:, m]
        return out[:, pad:pad + H, pad:pad + W].clamp_min(0.0)

    def _check_reach(self, amplitude_px: np.ndarray, what: str = "amplitude") -> None:
        off = np.abs(self._wfs.rest_px - self._corner.numpy() - (self._crop - 1) / 2).max(-1)  # rest off the crop centre
        room = (self._crop - 1) / 2 - off - _EDGE_SIGMAS * self._wfs.sigma_spots_px
        reach = np.hypot(amplitude_px[:, 0], amplitude_px[:, 1])
        worst = int(np.argmax(reach - room))
        if reach[worst] > room[worst]:
            raise ParameterError(f"{what}: spot {worst} would move {reach[worst]:.3g} px, more than the {room[worst]:.3g} px its "
                                 f"crop allows (rest to crop edge less {_EDGE_SIGMAS:g} PSF sigmas); lower the {what}")

    def _still_image_per_s(self) -> torch.Tensor:
        """Electrons per second of the still spots at power 1, ``[H, W]`` (cached; the crops)."""
        if self._still_rate is None:
            M = self._wfs.n_valid
            zero = torch.zeros(M, 2, dtype=_F64)
            self._still_rate = self._render_spots(zero, zero, 1.0, ExposureWindow(torch.zeros(1, dtype=_F64), 1.0), 1.0)[0]
        return self._still_rate

    # ------------------------------------------------------------------ commands

    def _settling_time_s(self) -> float:
        """The slowest actuator's settling time (s): the default wait before the first trigger."""
        return self._mirror.settling_time_s()

    def pattern_sine(self, pattern, freq_hz: float, amplitude: float, exposures_s: Sequence[float],
                     trigger_offset_s: float | Sequence[float], n_repeats: int, settle_s: float | None = None,
                     power: float = 1.0) -> Capture:
        """Frames ``[E, R, H, W]`` of the mirror driven with ``amplitude * pattern * sin(2 pi
        freq_hz t)``, as :meth:`~torchblur.rig.dm_contract.DMRig.pattern_sine` (module docstring).

        Raises:
            ParameterError: naming ``amplitude`` when a command exceeds the mirror's
                ``input_limit`` or a spot would leave its crop; ``pattern`` when it is not [N].

        ``meta`` holds ``pattern``, ``freq_hz``, ``omega``, ``period_s``, ``amplitude``,
        ``settle_s``, ``power``, ``trigger_delay_s`` and, for tests only, ``actual_start_s``.
        """
        p, freq, amp, a_px, ph = self._pattern_motion(pattern, freq_hz, amplitude)
        power = self._check_power(power)
        period = 1.0 / freq
        te, R, settle, trig_t, exp_t, off_t, window = self._triggers(period, exposures_s, trigger_offset_s, n_repeats, settle_s)
        flat = ExposureWindow(window.start.reshape(-1), window.duration.reshape(-1))
        omega = 2 * math.pi * freq
        expected = self._render_spots(torch.as_tensor(a_px), torch.as_tensor(ph), omega, flat, power)
        expected = expected.reshape((len(te), R) + self._frame_shape)
        meta = {"kind": "pattern_sine", "pattern": p, "freq_hz": freq, "omega": omega, "period_s": period, "amplitude": amp,
                "settle_s": settle, "power": power, "trigger_delay_s": self._trigger_delay_s, "actual_start_s": window.start}
        return self._capture(expected, exp_t, off_t, trig_t, meta=meta)

    def pattern_ladder(self, pattern, levels: Sequence[float], n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """Frames ``[K, n, H, W]`` of the mirror held still at ``levels[k] * pattern`` (input units;
        every spot at its static position ``(G diag(gain) levels[k] pattern)[m]``), ``n`` frames per
        level at ``exposure_s`` and laser ``power`` (docs/dm_rig.md). Their noise is drawn from a
        stream of its own (from the seed), so that taking a ladder leaves the sweep's frames as
        they would be without it.

        Raises:
            ParameterError: naming ``levels`` for a command beyond ``input_limit`` or a spot
                leaving its crop; ShapeError naming ``pattern`` when it is not [N].
        """
        shifts = self._hold_shifts(pattern, levels)
        power = self._check_power(power)
        one = ExposureWindow(torch.zeros(1, dtype=_F64), 1.0)
        rates = []
        for s in shifts:
            # a fixed displacement: a sinusoid of amplitude |s| at phase +-pi/2, too slow to move in the window
            rates.append(self._render_spots(torch.as_tensor(np.abs(s)), torch.as_tensor(np.where(s < 0, -np.pi / 2, np.pi / 2)),
                                            1e-12, one, power)[0])
        if self._hold_generator is None:
            self._hold_generator = torch.Generator().manual_seed(int(np.random.SeedSequence([self._seed, 1]).generate_state(1)[0]))
        return self._hold_capture(torch.stack(rates), n, exposure_s, meta={"kind": "pattern_ladder", "power": power},
                                  generator=self._hold_generator)

    def _hold_shifts(self, pattern, levels) -> list[np.ndarray]:
        """Every spot's static shift ``[M, 2]`` (px, x and y) at each level of ``pattern_ladder``,
        the commands checked (what :meth:`pattern_ladder` raises)."""
        out = []
        for c in self._ladder_commands(pattern, levels):
            self._mirror.check_command(c, "levels")
            s = np.real(self.truth_D(0.0) @ c)  # [2M] static shift (px)
            M = s.size // 2
            s = np.stack([s[:M], s[M:]], -1)
            self._check_reach(np.abs(s), "levels")
            out.append(s)
        return out

    def check_ladder(self, pattern, levels) -> None:
        """Raise what :meth:`pattern_ladder` raises for these holds (``pattern`` not [N], a command
        beyond ``input_limit`` or a spot leaving its crop), without rendering: the bench emulator
        refuses such a hold when it starts."""
        self._hold_shifts(pattern, levels)

    def check_pattern(self, pattern, freq_hz: float, amplitude: float) -> None:
        """Raise what :meth:`pattern_sine` raises for this command (``pattern`` not [N], a
        command beyond ``input_limit`` or a spot leaving its crop), without rendering: the
        bench emulator refuses such a waveform when it starts."""
        self._pattern_motion(pattern, freq_hz, amplitude)

    def _pattern_motion(self, pattern, freq_hz, amplitude):
        """The checked command and every spot's sinusoid: ``(pattern [N], freq_hz, amplitude,
        amplitude_px [M, 2], phase_rad [M, 2])``."""
        p = self._check_pattern(pattern)
        freq = check_real_scalar(freq_hz, "freq_hz", positive=True)
        amp = check_real_scalar(amplitude, "amplitude")
        self._mirror.check_command(amp * p, "amplitude")
        a_px, ph = spot_motion(self.truth_D(freq), p, amp)
        self._check_reach(a_px)
        return p, freq, amp, a_px, ph

    def __repr__(self) -> str:
        return (f"SimulatedDMRig({self._mirror.n_actuators} actuators, {self._wfs.n_valid} spots, frame {self._frame_shape}, "
                f"frame_rate_hz={self._frame_rate_hz:g}, seed={self._seed})")
