"""A worked example: a lab's own deformable mirror and camera, driven through their vendor's
Python SDK, identified by :func:`torchblur.identify` (a DM config) (the rig contract: docs/dm_rig.md).

Two parts:

1. ``acme`` below stands in for the vendor's package (in a lab: ``import acme_dm``). It has what
   such SDKs have: method names of its own, commands in volts, exposures in microseconds, the
   stroke in microns, integer error codes instead of exceptions, uint16 frames. So that the
   example runs anywhere, its "hardware" is torchblur's simulated DM (:class:`~torchblur.rig.dm.SimulatedDMRig`);
   nothing of it is visible through the SDK's methods.
2. :class:`AcmeDMRig`, the part a lab writes: about 100 lines that map the SDK onto the contract
   (:class:`torchblur.rig.DMRig`): ``dark``, ``still``, ``pattern_sine`` and the camera's
   properties, error codes turned into torchblur's errors; the optional ``pattern_ladder`` (the
   mirror held still at a ladder of levels: the spot model ``dm_plan.spot_model``) is one more SDK
   call, ``acme_hold``, before the camera's snapshots. The mirror has no gated laser, so
   the rig has no ``pulse()``: the camera's trigger-to-exposure latency is given instead
   (``camera.latency_s`` and ``camera.latency_std_s``, from the camera's datasheet).

Run it (a 4-actuator mirror under 2 x 2 subapertures)::

    python docs/examples/vendor_dm.py --out runs/vendor_dm

``tests/test_dm_lab.py`` runs it end to end.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from torchblur.errors import ParameterError
from torchblur.hardware.errors import HardwareError
from torchblur.rig.base import Capture

# ====================================================================== 1. the stand-in vendor SDK

ACME_OK, ACME_ERR_RANGE, ACME_ERR_NOT_ARMED, ACME_ERR_EXPOSURE = 0, -3, -5, -8
ACME_ERRORS = {ACME_ERR_RANGE: "voltage out of range", ACME_ERR_NOT_ARMED: "camera not armed", ACME_ERR_EXPOSURE: "exposure out of range"}


class _Bench:
    """The stand-in's hardware: torchblur's simulated DM rig (hidden from the SDK's user)."""

    def __init__(self, sim):
        self.sim, self.waveform, self.light, self.armed, self.buffer, self.hold = sim, None, 0.0, None, None, None


class AcmeMirror:
    """The vendor's mirror controller: per-actuator sine waveforms in volts, a trigger output."""

    def __init__(self, bench: _Bench):
        self._b = bench

    def acme_num_actuators(self) -> int:
        return self._b.sim.n_actuators

    def acme_max_volts(self) -> float:
        return float(self._b.sim.input_limit)

    def acme_stroke_um_per_volt(self) -> float:
        return 0.25  # informational: the surface moves 0.25 um per volt

    def acme_load_sine(self, volts: list, freq_hz: float) -> int:
        """Load ``volts[j] * sin(2 pi freq_hz t)`` on actuator j (not started)."""
        if max(abs(v) for v in volts) > self.acme_max_volts():
            return ACME_ERR_RANGE
        self._b.waveform = (np.asarray(volts, dtype=float), float(freq_hz))
        return ACME_OK

    def acme_hold(self, volts: list) -> int:
        """Hold actuator j still at ``volts[j]`` (all zeros: the mirror flat) until the next call."""
        if max(abs(v) for v in volts) > self.acme_max_volts():
            return ACME_ERR_RANGE
        self._b.hold = np.asarray(volts, dtype=float) if any(volts) else None
        return ACME_OK

    def acme_run_triggered(self, trigger_delays_s: list, frames_per_delay: int, settle_s: float | None) -> int:
        """Start the waveforms from rest, wait ``settle_s``, then fire the camera ``frames_per_delay``
        times per entry of ``trigger_delays_s`` after an upward zero crossing (the camera's
        armed exposures, one per entry); the frames go to the camera's buffer."""
        b = self._b
        if b.armed is None:
            return ACME_ERR_NOT_ARMED
        volts, f = b.waveform
        b.buffer = b.sim.pattern_sine(pattern=volts, freq_hz=f, amplitude=1.0, exposures_s=[us * 1e-6 for us in b.armed],
                                      trigger_offset_s=list(trigger_delays_s), n_repeats=frames_per_delay, settle_s=settle_s,
                                      power=max(b.light, 1e-12))
        b.armed = None
        return ACME_OK


class AcmeCamera:
    """The vendor's camera: exposures in microseconds, uint16 frames, a light source switch."""

    def __init__(self, bench: _Bench):
        self._b = bench

    def acme_sensor_size(self) -> tuple:
        return tuple(self._b.sim.frame_shape)

    def acme_timing_us(self) -> dict:
        s = self._b.sim
        return {"max_exposure": s.max_exposure_s * 1e6, "readout": s.readout_s * 1e6, "frame_period": 1e6 / s.frame_rate_hz,
                "trigger_delay": s.trigger_delay_s * 1e6}

    def acme_light(self, level: float) -> int:
        self._b.light = float(level)
        return ACME_OK

    def acme_arm(self, exposures_us: list) -> int:
        if any(not 0 < us <= self.acme_timing_us()["max_exposure"] for us in exposures_us):
            return ACME_ERR_EXPOSURE
        self._b.armed = list(exposures_us)
        return ACME_OK

    def acme_snap(self, n: int, exposure_us: float):
        """``n`` free-running frames (the mirror flat, or as ``acme_hold`` holds it): ``(code, frames uint16 [n, H, W])``."""
        b, te = self._b, exposure_us * 1e-6
        if b.light <= 0:
            cap = b.sim.dark(n=n, exposure_s=te)
        elif b.hold is not None:
            cap = b.sim.pattern_ladder(pattern=b.hold, levels=[1.0], n=n, exposure_s=te, power=b.light)
        else:
            cap = b.sim.still(n=n, exposure_s=te, power=b.light)
        return ACME_OK, cap.frames.reshape((n,) + tuple(cap.frames.shape[-2:])).numpy().astype(np.uint16)

    def acme_fetch(self):
        """The triggered frames: ``(code, frames uint16 [E, R, H, W], trigger times s [E, R], counters [E, R])``."""
        cap, self._b.buffer = self._b.buffer, None
        if cap is None:
            return ACME_ERR_NOT_ARMED, None, None, None
        return ACME_OK, cap.frames.numpy().astype(np.uint16), cap.trigger_time_s.numpy(), cap.frame_counter.numpy()


def acme_open(cfg):
    """``(mirror, camera)`` of the stand-in SDK, its hardware the simulated DM of the torchblur config ``cfg``."""
    from torchblur.rig.factory import build_dm

    bench = _Bench(build_dm(cfg)[2])
    return AcmeMirror(bench), AcmeCamera(bench)


# ====================================================================== 2. the lab's rig: the SDK on the contract


def _ok(code: int, what: str) -> None:
    """An SDK error code as torchblur's error: a range error names ``amplitude`` (the contract), the rest HardwareError."""
    if code == ACME_ERR_RANGE:
        raise ParameterError(f"amplitude: {what}: the controller refused it ({ACME_ERRORS[code]})")
    if code != ACME_OK:
        raise HardwareError(f"{what}: Acme error {code} ({ACME_ERRORS.get(code, 'unknown')})")


class AcmeDMRig:
    """The Acme mirror and camera as a torchblur DM rig (:class:`torchblur.rig.DMRig`, docs/dm_rig.md).
    Input units: volts. No ``pulse()``: give ``camera.latency_s`` and ``camera.latency_std_s``."""

    def __init__(self, mirror: AcmeMirror, camera: AcmeCamera):
        self._m, self._c = mirror, camera
        t = camera.acme_timing_us()
        self.frame_shape = tuple(int(v) for v in camera.acme_sensor_size())
        self.frame_rate_hz, self.max_exposure_s = 1e6 / t["frame_period"], t["max_exposure"] * 1e-6
        self.readout_s, self.trigger_delay_s = t["readout"] * 1e-6, t["trigger_delay"] * 1e-6
        self.input_limit, self.n_actuators = mirror.acme_max_volts(), mirror.acme_num_actuators()
        self._counter = 0

    def _frames(self, n: int, exposure_s: float, light: float) -> Capture:
        _ok(self._c.acme_light(light), "light")
        code, frames = self._c.acme_snap(int(n), exposure_s * 1e6)
        _ok(code, "snap")
        z = torch.zeros(int(n), dtype=torch.float64)
        counter = torch.arange(self._counter, self._counter + int(n))
        self._counter += int(n)
        return Capture(frames=torch.as_tensor(frames.astype(np.float64)), exposure_s=z + exposure_s, trigger_offset_s=z,
                       trigger_time_s=z, frame_counter=counter)

    def dark(self, n: int, exposure_s: float) -> Capture:
        return self._frames(n, exposure_s, 0.0)

    def still(self, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        return self._frames(n, exposure_s, power)

    def pattern_ladder(self, pattern, levels, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """The mirror held still at ``levels[k] * pattern`` (volts), ``n`` frames each: frames ``[K, n, H, W]``."""
        caps = []
        try:
            for u in levels:
                volts = [float(u) * float(p) for p in pattern]
                if max(abs(v) for v in volts) > self.input_limit:
                    raise ParameterError(f"levels: a command of {max(abs(v) for v in volts):.4g} V is beyond the mirror's "
                                         f"+-{self.input_limit:g} V")
                _ok(self._m.acme_hold(volts), "hold")
                caps.append(self._frames(n, exposure_s, power))
        finally:
            self._m.acme_hold([0.0] * self.n_actuators)  # the mirror flat again
        return Capture(frames=torch.stack([c.frames for c in caps]), exposure_s=torch.stack([c.exposure_s for c in caps]),
                       trigger_offset_s=torch.stack([c.trigger_offset_s for c in caps]),
                       trigger_time_s=torch.stack([c.trigger_time_s for c in caps]), frame_counter=torch.stack([c.frame_counter for c in caps]))

    def pattern_sine(self, pattern, freq_hz: float, amplitude: float, exposures_s, trigger_offset_s, n_repeats: int,
                     settle_s: float | None = None, power: float = 1.0) -> Capture:
        volts = [float(amplitude) * float(p) for p in pattern]
        if max(abs(v) for v in volts) > self.input_limit:
            raise ParameterError(f"amplitude: a command of {max(abs(v) for v in volts):.4g} V is beyond the mirror's "
                                 f"+-{self.input_limit:g} V")
        E = len(exposures_s)
        offsets = list(trigger_offset_s) if np.ndim(trigger_offset_s) else [float(trigger_offset_s)] * E
        _ok(self._m.acme_load_sine(volts, float(freq_hz)), "load_sine")
        _ok(self._c.acme_light(power), "light")
        _ok(self._c.acme_arm([float(t) * 1e6 for t in exposures_s]), "arm")
        _ok(self._m.acme_run_triggered(offsets, int(n_repeats), settle_s), "run_triggered")
        code, frames, t_trig, counters = self._c.acme_fetch()
        _ok(code, "fetch")
        shape = (E, int(n_repeats))
        period = 1.0 / float(freq_hz)
        return Capture(frames=torch.as_tensor(frames.astype(np.float64)),
                       exposure_s=torch.tensor(exposures_s, dtype=torch.float64)[:, None].expand(shape).clone(),
                       trigger_offset_s=torch.as_tensor(np.mod(t_trig, period)), trigger_time_s=torch.as_tensor(t_trig),
                       frame_counter=torch.as_tensor(counters), meta={"volts": volts})

    def __repr__(self) -> str:
        return f"AcmeDMRig({self.n_actuators} actuators, frame {self.frame_shape})"


# ====================================================================== 3. using it

#: a small mirror (4 actuators under 2 x 2 subapertures) and sweep, the latency given (no pulse())
EXAMPLE = ["dm.n_across=2", "dm.mode_hz=600.0", "dm.damping=0.1", "dm.mode_spread=0.05", "dm.input_limit=10.0",
           "wfs.n_across=2", "wfs.pitch_px=16.0", "wfs.sigma_px=1.2", "dm_plan.kind=hadamard", "dm_plan.budget_frames=null",
           "dm_plan.n_repeats=1", "sweep.f_min_hz=50.0", "sweep.f_max_hz=1500.0", "sweep.n=5", "sweep.exposures=[0.3,0.8]",
           "excitation.target_px=3.0", "camera.latency_s=1.2e-05", "camera.latency_std_s=1e-07"]


def identify_with_acme(overrides=(), *, record=None):
    """``(result, rig)``: :func:`torchblur.identify` (a DM config) of the Acme mirror (the config
    :data:`EXAMPLE` and ``overrides`` describe the mirror and the sensor; recorded in ``record``)."""
    import torchblur as tb

    cfg = tb.load_config(None, EXAMPLE + list(overrides))
    rig = AcmeDMRig(*acme_open(cfg))
    return tb.identify(cfg, rig, record=record, progress=False), rig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="record the run in OUT/experiment (then `torchblur fit` can re-fit it)")
    args = ap.parse_args(argv)
    res, rig = identify_with_acme(record=None if args.out is None else Path(args.out) / "experiment")
    t = res.actuators
    print(f"{rig!r}: {res.n_frames} sweep frames")
    for j in range(len(t)):
        print(f"actuator {j}: {t.status[j]}, mode {t.mode_hz[j]:.1f} +- {t.mode_hz_std[j]:.2g} Hz, damping {t.damping[j]:.4f} "
              f"+- {t.damping_std[j]:.2g}, DC gain {t.dc_gain[j]:.4f} +- {t.dc_gain_std[j]:.2g} (relative to the nominal geometry G)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
