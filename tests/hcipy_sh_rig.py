"""A user-written DM rig whose frames are HCIPy Shack-Hartmann frames (issue 23).

:class:`HcipyDMRig` implements what torchblur's DM route calls on a rig (``dark``, ``still``,
``pulse`` for the latency scan, ``pattern_sine``, ``pattern_ladder`` (static holds), ``n_actuators``,
``input_limit``, the camera's
timing) over :class:`hcipy_sh.HcipySH`: the timing, jitter, latency and camera noise (Poisson,
read noise, ADU rounding, saturation) of torchblur's :class:`~torchblur.rig.simulated.SimulatedRig`
(a lab's camera model), every image made by HCIPy's optics and the generator's own actuator
dynamics (:class:`hcipy_sh.Dynamics`), not by torchblur's mirror or renderer. It is not a
:class:`~torchblur.rig.dm.SimulatedDMRig`, so a run on it carries no simulated truth: tests and
benchmarks compare with :meth:`HcipyDMRig.truth`.

    gen = hcipy_sh.HcipySH()
    rig = hcipy_sh_rig.hcipy_dm_rig(cfg, gen, hcipy_sh.draw_dynamics(gen.n_actuators, seed=5))
    res = torchblur.identify(cfg, rig, record=out / "experiment")
    torchblur.identify.outputs.write_outputs(cfg, res, out, elapsed_s, stamp)
"""
from __future__ import annotations

import math

import numpy as np
import torch

import hcipy_sh as hs
from torchblur.errors import ShapeError, check_real_scalar
from torchblur.render.camera import CameraModel
from torchblur.rig.base import Capture, PatternSines, check_drive, float_list
from torchblur.rig.simulated import SimulatedRig
from torchblur.systems.lti import Plant

_F64 = torch.float64


class HcipyDMRig(PatternSines, SimulatedRig):
    """The HCIPy DM rig (module docstring). Keyword arguments as
    :class:`~torchblur.rig.simulated.SimulatedRig` (camera, timing, noise, ``peak_e_per_s``: the
    brightest still spot's peak at power 1, ``input_limit``), plus ``gen`` (the
    :class:`hcipy_sh.HcipySH`) and ``dynamics`` (its actuators' :class:`hcipy_sh.Dynamics`)."""

    def __init__(self, *, gen: hs.HcipySH, dynamics: hs.Dynamics, **kwargs):
        super().__init__(plant=Plant(num=(1.0,), den=(1.0,)), frame_shape=gen.shape, **kwargs)
        self.gen, self.dynamics = gen, dynamics
        self._slopes = gen.shift_truth()  # [2M, N] px per unit (the node count's motion)
        self.nodes_used: list[int] = []

    @property
    def n_actuators(self) -> int:
        return self.gen.n_actuators

    def truth(self, freq_hz) -> dict:
        """The generator's truth: dynamics and the fitted-shift static matrix ``D0 = S diag(gain)``
        (``S``: :meth:`hcipy_sh.HcipySH.shift_truth`)."""
        d = self.dynamics
        return {"mode_hz": d.mode_hz, "damping": d.damping, "gain": d.gain, "delay_s": d.delay_s,
                "D0": self._slopes * d.gain[None, :], "shift_slopes": self._slopes}

    def _settling_time_s(self) -> float:
        return self.settling_time_s()

    def settling_time_s(self, tol: float = 1e-7) -> float:
        d = self.dynamics
        return float(np.max(-math.log(tol) / (d.damping * 2 * np.pi * d.mode_hz)))

    def _still_image_per_s(self) -> torch.Tensor:
        if self._still_rate is None:
            self._still_rate = torch.as_tensor(self.gen.still() * self._peak_e_per_s, dtype=_F64)
        return self._still_rate

    def pattern_sine(self, pattern, freq_hz: float, amplitude: float, exposures_s, trigger_offset_s, n_repeats: int,
                     settle_s: float | None = None, power: float = 1.0) -> Capture:
        """Frames ``[E, R, H, W]`` (ADU) of the mirror driven with ``amplitude * pattern *
        sin(2 pi freq_hz t)`` in steady state, triggered as
        :meth:`~torchblur.rig.simulated.SimulatedRig.sine`."""
        N = self.n_actuators
        p = np.asarray(float_list(pattern, "pattern"), dtype=np.float64)
        if p.shape != (N,):
            raise ShapeError(f"pattern: expected [{N}] (one command per actuator), got shape {p.shape}")
        freq = check_real_scalar(freq_hz, "freq_hz", positive=True)
        amp = check_real_scalar(amplitude, "amplitude")
        check_drive(float(np.abs(amp * p).max()), self._input_limit)
        power = self._check_power(power)
        period = 1.0 / freq
        te, R, settle, trig_t, exp_t, off_t, window = self._triggers(period, exposures_s, trigger_offset_s, n_repeats, settle_s)
        omega = 2 * math.pi * freq
        h = self.dynamics.response(freq) * amp * p  # [N] complex surface command
        motion = np.abs(self._slopes @ h)  # [2M] px amplitude per axis (linear prediction)
        M = motion.size // 2
        motion_px = float(np.hypot(motion[:M], motion[M:]).max())
        starts, durs = window.start.reshape(-1).numpy(), window.duration.reshape(-1).numpy()
        nodes = [self.gen.node_count(motion_px, omega, float(d)) for d in durs]
        self.nodes_used += nodes
        img = self.gen.blurred(np.abs(h), np.angle(h), omega, starts, durs, nodes)
        expected = torch.as_tensor(img * (self._peak_e_per_s * power), dtype=_F64).clamp_min(0.0)
        expected = expected.reshape((len(te), R) + self._frame_shape)
        meta = {"kind": "pattern_sine", "pattern": p, "freq_hz": freq, "omega": omega, "period_s": period, "amplitude": amp,
                "settle_s": settle, "power": power, "trigger_delay_s": self._trigger_delay_s, "actual_start_s": window.start}
        return self._capture(expected, exp_t, off_t, trig_t, meta=meta)

    def pattern_ladder(self, pattern, levels, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """Frames ``[K, n, H, W]`` (ADU) of the mirror held still at ``levels[k] * pattern``: HCIPy's
        static intensity at each actuator's DC response to that command (its ``gain``)."""
        commands = self._ladder_commands(pattern, levels)
        check_drive(float(np.abs(commands).max()), self._input_limit)
        power = self._check_power(power)
        dc = np.real(self.dynamics.response(0.0))  # [N] each actuator's static gain
        rates = torch.as_tensor(self.gen.intensity(commands * dc[None, :]) * (self._peak_e_per_s * power), dtype=_F64).clamp_min(0.0)
        return self._hold_capture(rates, n, exposure_s, meta={"kind": "pattern_ladder", "power": power})

    def __repr__(self) -> str:
        return f"HcipyDMRig({self.n_actuators} actuators, {self.gen.valid.size} subapertures, {self.gen.optics})"


def hcipy_dm_rig(cfg, gen: hs.HcipySH, dynamics: hs.Dynamics, **kwargs) -> HcipyDMRig:
    """The HCIPy rig with the camera, timing and seed of the DM config ``cfg`` (as
    :func:`torchblur.identify.dm_plan.build_dm`)."""
    c = cfg.camera
    camera = CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                         bit_depth=int(c.bit_depth))
    limit = 5.0 if cfg.dm.input_limit is None else float(cfg.dm.input_limit)
    return HcipyDMRig(gen=gen, dynamics=dynamics, camera=camera, frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s,
                      readout_s=c.readout_s, max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s,
                      seed=int(cfg.seed), input_limit=limit, **kwargs)
