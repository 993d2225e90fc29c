"""A simulated laboratory rig: an LTI mirror, a Gaussian laser spot and a noisy camera.

Time model (all in seconds on the controller's clock):

- ``sine``: the command ``amplitude sin(2 pi f t)`` starts at t = 0 from rest. The controller
  waits ``settle_s``, then takes the frames one after another (exposure-major: all repeats of
  the first exposure, then of the second, ...). A frame's trigger is at an upward zero
  crossing of the command plus ``trigger_offset_s``, the first such time at or after the
  camera is ready; the camera is ready again ``max(1 / frame_rate_hz, Td + Te + Tr)`` after
  the previous trigger.
- The exposure starts ``Td + latency_s + jitter`` after the trigger (``jitter ~ N(0,
  jitter_s^2)`` per frame, then the camera model's own ``jitter_s`` if any) and lasts Te.
  ``latency_s`` is unknown to a pipeline: it calibrates it with :meth:`SimulatedRig.pulse`.
- The expected image is the exact plant output (:class:`~torchblur.systems.lti.LTISineTrajectory`,
  transient included) rendered over the actual window with pixel-area integration in
  float64, in electrons (the spot's peak is ``power * peak_e_per_s`` electrons per second),
  then :meth:`~torchblur.render.camera.CameraModel.expose` adds noise, saturation and rounding.

Random draws come from one ``torch.Generator`` seeded with ``seed``: the same seed and the
same sequence of calls give identical captures.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from torchblur.render.camera import CameraModel
from torchblur.errors import InputTypeError, ParameterError, ShapeError, as_tensor, check_finite, check_int, check_real_scalar
from torchblur.systems.lti import LTIMultisineTrajectory, LTISineTrajectory, Plant
from torchblur.systems.mimo import MIMOSineTrajectory, PlantMatrix
from torchblur.render.psf import GaussianPSF
from torchblur.render.blur import RenderSettings, choose_node_count, render_blur
from torchblur.render.window import ExposureWindow
from torchblur.render.trajectory import Sinusoid, Trajectory
from torchblur.rig.base import Capture, RigChecks, check_drive, check_slew, command_peak, command_slew, per_exposure

__all__ = ["SimulatedRig", "DEFAULT_INPUT_LIMIT", "periodic_triggers", "pulse_references"]

#: The simulated amplifier's input range (input units): the default mirror (20 px per unit at
#: DC, 0.064 px per unit at 5 kHz) moves 8 px with about 126 units at 5 kHz. The config's
#: ``plant.input_limit`` default is the same number (tests/test_safe_drive.py checks).
DEFAULT_INPUT_LIMIT = 200.0

_F64 = torch.float64
_MAX_NODES_PER_RENDER = 4096  # longer windows are split into sub-windows (the integral adds up)
_RENDER_BUDGET = 1 << 24  # elements of a splat factor per render call (memory bound)



def periodic_triggers(ready: float, period: float, offset: float, n: int, cycle_s: float) -> list[float]:
    """``n`` triggers (s) of a periodic command, each at ``k period + offset``, the first such time
    once the camera is ready (at ``ready``, then ``cycle_s`` after each trigger)."""
    out = []
    for _ in range(n):
        out.append(math.ceil((ready - offset) / period - 1e-9) * period + offset)
        ready = out[-1] + cycle_s
    return out


def pulse_references(offsets, pulse_time_s: float, pulse_width_s: float, cycle_s: float) -> tuple[list[float], float]:
    """The reference events (s) of a latency scan's frames, one per trigger offset (s), each once
    the camera is ready and the last pulse is over; and the time the last frame is done."""
    refs, ready = [], 0.0
    for o in offsets:
        refs.append(ready - min(o, pulse_time_s, 0.0))
        ready = max(refs[-1] + o + cycle_s, refs[-1] + pulse_time_s + pulse_width_s)
    return refs, ready


def _spots_model(plant, frame_shape: tuple, *, rest_px, direction, psf_sigma_px, psf_cov, peak: float, spots):
    """The rig's spots, checked: ``(direction [2] float64, GaussianPSF of amplitude ``peak``
    (e-/s) at the rest positions, batch [] or [K], SpotLayout or None)``. One spot: at
    ``rest_px`` (default the frame's centre), isotropic of ``psf_sigma_px`` or of covariance
    ``psf_cov``; ``spots`` (a SpotGrid or SpotLayout): its rest positions and covariances."""
    H, W = frame_shape
    if rest_px is None:
        rest = torch.tensor([(W - 1) / 2, (H - 1) / 2], dtype=_F64)
    else:
        rest = check_finite(as_tensor(rest_px, "rest_px", dtype=_F64), "rest_px")
        if rest.shape != (2,):
            raise ShapeError(f"rest_px: expected shape [2] (x, y px), got {tuple(rest.shape)}")
    d = check_finite(as_tensor(direction, "direction", dtype=_F64), "direction")
    if d.shape != (2,):
        raise ShapeError(f"direction: expected shape [2] (x, y), got {tuple(d.shape)}")
    if psf_cov is None:
        sigma = check_real_scalar(psf_sigma_px, "psf_sigma_px", positive=True)
        psf = GaussianPSF.isotropic(rest, torch.tensor(sigma, dtype=_F64), amplitude=peak)
    else:
        psf = GaussianPSF(rest, as_tensor(psf_cov, "psf_cov", dtype=_F64), amplitude=peak)
        if psf.shape != ():
            raise ShapeError(f"psf_cov: expected shape [2, 2], got {tuple(psf.cov.shape)}")
    layout = None
    if spots is not None:
        from torchblur.image.spots import SpotGrid, SpotLayout

        if isinstance(spots, SpotGrid):
            spots = spots.layout((H, W), plant.n_outputs if isinstance(plant, PlantMatrix) else 1)
        if not isinstance(spots, SpotLayout):
            raise InputTypeError(f"spots: expected None, a SpotGrid or a SpotLayout, got {type(spots).__name__}")
        n_out = plant.n_outputs if isinstance(plant, PlantMatrix) else 1
        if tuple(spots.response.shape[1:]) != (2, n_out):
            raise ShapeError(f"spots: expected responses [K, 2, {n_out}] for a plant with {n_out} output(s), "
                             f"got {tuple(spots.response.shape)}")
        layout = spots
        psf = GaussianPSF(spots.rest_px.to(_F64), spots.cov.to(_F64), torch.full((len(spots),), peak, dtype=_F64))
    return d, psf, layout

class SimulatedRig(RigChecks):
    """A simulated rig implementing :class:`~torchblur.rig.base.Rig`.

    Args (keyword-only):
        plant: the mirror, a :class:`~torchblur.systems.lti.Plant` (output in px per command unit
            along ``direction``) or a :class:`~torchblur.systems.mimo.PlantMatrix` (a tip-tilt
            mirror: outputs x and y move the spot along x and y; inputs ``"x"``, ``"y"``).
        camera: the sensor, a :class:`~torchblur.render.camera.CameraModel`.
        frame_shape: ``(H, W)`` in pixels.
        psf_sigma_px: standard deviation of the round spot (px); ignored when ``psf_cov``
            is given.
        psf_cov: ``[2, 2]`` covariance of a tilted spot (px^2), or None.
        rest_px: rest position (x, y) of the spot (px); default the frame centre
            ``((W - 1) / 2, (H - 1) / 2)``.
        direction: image motion per plant output unit along (x, y) (px per px).
        frame_rate_hz: highest frame rate (Hz).
        trigger_delay_s: Td, the nominal trigger-to-exposure delay (known to the pipeline).
        readout_s: Tr.
        max_exposure_s: the longest exposure accepted.
        latency_s: extra trigger-to-exposure latency (the truth; a pipeline must calibrate it).
        jitter_s: rms jitter of the exposure start, per frame.
        peak_e_per_s: peak electrons per second of the still spot at power 1.
        seed: seed of the generator behind every random draw.
        input_limit: the amplifier's input range: the largest |command| (input units) a
            :meth:`sine` or :meth:`multisine` may ask for (its peak, every input); a larger
            one raises :class:`~torchblur.errors.ParameterError` naming ``amplitude``.
        slew_limit: the amplifier's slew-rate limit (input units per second; None: none): a
            :meth:`sine` whose ``amplitude * 2 pi freq_hz`` (a :meth:`multisine` whose
            :func:`~torchblur.rig.base.command_slew`) exceeds it raises the same error.
        spots: None (one spot), or a :class:`~torchblur.image.spots.SpotGrid` /
            :class:`~torchblur.image.spots.SpotLayout`: K spots in the frame (a Shack-Hartmann
            sensor), each with its own PSF and its own motion ``G_k @ y(t)`` (see
            :mod:`torchblur.image.spots`); ``psf_sigma_px``, ``psf_cov``, ``rest_px`` and
            ``direction`` are then not used. Every spot's peak is ``peak_e_per_s``.
    """

    def __init__(
        self,
        *,
        plant: Plant,
        camera: CameraModel,
        frame_shape: Sequence[int] = (64, 64),
        psf_sigma_px: float = 2.0,
        psf_cov=None,
        rest_px=None,
        direction=(1.0, 0.0),
        frame_rate_hz: float = 30.0,
        trigger_delay_s: float = 0.0,
        readout_s: float = 1e-3,
        max_exposure_s: float = 1.0,
        latency_s: float = 12e-6,
        jitter_s: float = 0.2e-6,
        peak_e_per_s: float = 1e6,
        seed: int = 0,
        spots=None,
        input_limit: float = DEFAULT_INPUT_LIMIT,
        slew_limit: float | None = None,
    ):
        if not isinstance(plant, (Plant, PlantMatrix)):
            raise InputTypeError(f"plant: expected a torchblur.systems.lti.Plant or torchblur.systems.mimo.PlantMatrix, got {type(plant).__name__}")
        if not isinstance(camera, CameraModel):
            raise InputTypeError(f"camera: expected a torchblur.render.camera.CameraModel, got {type(camera).__name__}")
        if (
            isinstance(frame_shape, (str, bytes))
            or not hasattr(frame_shape, "__len__")
            or len(frame_shape) != 2
        ):
            raise ShapeError(f"frame_shape: expected (H, W), got {frame_shape!r}")
        H, W = (check_int(v, "frame_shape", low=1) for v in frame_shape)
        seed = check_int(seed, "seed", low=0)
        self._plant = plant
        self._camera = camera
        self._frame_shape = (H, W)
        self._frame_rate_hz = check_real_scalar(frame_rate_hz, "frame_rate_hz", positive=True)
        self._trigger_delay_s = check_real_scalar(trigger_delay_s, "trigger_delay_s", nonnegative=True)
        self._readout_s = check_real_scalar(readout_s, "readout_s", nonnegative=True)
        self._max_exposure_s = check_real_scalar(max_exposure_s, "max_exposure_s", positive=True)
        self._latency_s = check_real_scalar(latency_s, "latency_s", nonnegative=True)
        self._jitter_s = check_real_scalar(jitter_s, "jitter_s", nonnegative=True)
        self._peak_e_per_s = check_real_scalar(peak_e_per_s, "peak_e_per_s", nonnegative=True)
        self._seed = int(seed)
        self._input_limit = check_real_scalar(input_limit, "input_limit", positive=True)
        self._slew_limit = None if slew_limit is None else check_real_scalar(slew_limit, "slew_limit", positive=True)

        self._direction, self._psf, self._layout = _spots_model(plant, (H, W), rest_px=rest_px, direction=direction,
                                                                psf_sigma_px=psf_sigma_px, psf_cov=psf_cov,
                                                                peak=self._peak_e_per_s, spots=spots)
        self._settings = RenderSettings(pixel_integration=True, max_nodes=1 << 30)
        self._generator = torch.Generator().manual_seed(self._seed)
        self._next_counter = 0
        self._still_rate: torch.Tensor | None = None

    # ------------------------------------------------------------------ properties

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self._frame_shape

    @property
    def frame_rate_hz(self) -> float:
        return self._frame_rate_hz

    @property
    def max_exposure_s(self) -> float:
        return self._max_exposure_s

    @property
    def readout_s(self) -> float:
        return self._readout_s

    @property
    def input_limit(self) -> float:
        """The largest |command| (input units) the simulated amplifier takes."""
        return self._input_limit

    @property
    def slew_limit(self) -> float | None:
        """The largest |d command / dt| (input units per second) the simulated amplifier takes; None: no limit."""
        return self._slew_limit

    @property
    def trigger_delay_s(self) -> float:
        """Td, the nominal trigger-to-exposure delay (s)."""
        return self._trigger_delay_s

    @property
    def latency_s(self) -> float:
        """The true extra latency (s). For tests only: a pipeline must calibrate it."""
        return self._latency_s

    @property
    def jitter_s(self) -> float:
        return self._jitter_s

    @property
    def plant(self) -> Plant | PlantMatrix:
        return self._plant

    @property
    def inputs(self) -> tuple[str, ...]:
        """The inputs :meth:`sine` can drive: ``("x",)`` for a Plant, the PlantMatrix's labels."""
        return self._plant.input_labels if isinstance(self._plant, PlantMatrix) else ("x",)

    @property
    def spots(self):
        """The :class:`~torchblur.image.spots.SpotLayout` of a many-spot rig, or None."""
        return self._layout

    @property
    def camera(self) -> CameraModel:
        return self._camera

    @property
    def psf(self) -> GaussianPSF:
        """The spot at power 1 (amplitude ``peak_e_per_s``, electrons per second), float64."""
        return self._psf

    @property
    def direction(self) -> torch.Tensor:
        """``[2]`` image motion (x, y) per plant output unit."""
        return self._direction

    @property
    def frames_taken(self) -> int:
        """Frames taken so far (the next frame counter)."""
        return self._next_counter

    def truth(self, freq_hz):
        """``H(j 2 pi freq_hz)`` of the plant, delay included (not the ``direction`` scale):
        for a Plant a complex for a number, a complex numpy array ``[F]`` for an array; for a
        PlantMatrix a complex array ``[O, I]`` (``[O, I, F]`` for an array)."""
        f = np.asarray(freq_hz, dtype=np.float64)
        h = self._plant.frequency_response(2 * np.pi * f)
        if isinstance(self._plant, PlantMatrix):
            return h
        return complex(h) if h.ndim == 0 else h

    def spot_truth(self, freq_hz) -> np.ndarray:
        """The image motion response of every spot, ``G_k @ H``: complex ``[K, 2, I]``
        (``[K, 2, I, F]`` for an array of frequencies); K = 1 with ``G = direction`` for a
        one-spot rig with a Plant, ``G`` = identity for a PlantMatrix."""
        f = np.asarray(freq_hz, dtype=np.float64)
        h = np.asarray(self._plant.frequency_response(2 * np.pi * f))
        if not isinstance(self._plant, PlantMatrix):
            h = h[None, None]  # [1, 1, ...]
        G = self._image_matrices().numpy()  # [K, 2, O]
        return np.einsum("kao,oi...->kai...", G, h)

    def _image_matrices(self) -> torch.Tensor:
        """``[K, 2, O]`` image motion per plant output of each spot."""
        if self._layout is not None:
            return self._layout.response.to(_F64)
        if isinstance(self._plant, PlantMatrix):
            g = torch.zeros(1, 2, self._plant.n_outputs, dtype=_F64)
            g[0, 0, 0] = 1.0
            if self._plant.n_outputs > 1:
                g[0, 1, 1] = 1.0
            return g
        return self._direction[None, :, None]

    # ------------------------------------------------------------------ helpers

    def _cycle_s(self, exposure_s: float) -> float:
        """Shortest time from one trigger to the next."""
        return max(1.0 / self._frame_rate_hz, self._trigger_delay_s + exposure_s + self._readout_s)

    def _counters(self, shape) -> torch.Tensor:
        n = int(np.prod(shape)) if len(shape) else 1
        c = torch.arange(self._next_counter, self._next_counter + n, dtype=torch.long).reshape(shape)
        self._next_counter += n
        return c

    def _actual_starts(self, trigger_time_s: torch.Tensor, exposure_s: torch.Tensor) -> ExposureWindow:
        """Windows of the exposures: trigger + Td + latency + jitter, duration Te."""
        start = trigger_time_s + (self._trigger_delay_s + self._latency_s)
        if self._jitter_s > 0:
            start = start + self._jitter_s * torch.randn(start.shape, generator=self._generator, dtype=_F64)
        window = ExposureWindow(start, exposure_s)
        return self._camera.jitter_window(window, generator=self._generator)

    def _render(self, trajectory: Trajectory, psf: GaussianPSF, window: ExposureWindow, shape=None) -> torch.Tensor:
        """``render_blur`` over windows ``[N]`` -> ``[N, H, W]`` electrons, float64 (``shape``:
        another ``(H, W)``). Windows that need many time nodes are split into sub-windows (the
        integral over a window is the sum over its parts) and the batch is cut into chunks that
        bound the memory."""
        H, W = self._frame_shape if shape is None else shape
        N = window.shape[0]
        S = choose_node_count(trajectory.path_length(window), psf.sigma_min(), self._settings, trajectory.phase_span(window))
        K = max(1, math.ceil(S / _MAX_NODES_PER_RENDER))
        frac = torch.arange(K, dtype=_F64) / K
        start = (window.start[:, None] + window.duration[:, None] * frac).reshape(-1)
        dur = (window.duration[:, None] / K).expand(N, K).reshape(-1)
        per_item = max(1, min(S, _MAX_NODES_PER_RENDER)) * (H + W) * 16
        chunk = max(1, _RENDER_BUDGET // per_item)
        parts = []
        for i in range(0, N * K, chunk):
            win = ExposureWindow(start[i:i + chunk], dur[i:i + chunk])
            parts.append(render_blur(trajectory, psf, win, height=H, width=W, settings=self._settings))
        img = torch.cat(parts, 0).reshape(N, K, H, W).sum(1)
        return img.clamp_min(0.0)

    def _render_near(self, trajectory: Trajectory, psf: GaussianPSF, window: ExposureWindow) -> torch.Tensor:
        """:meth:`_render` of one spot, computed only over the part of the frame it can reach:
        its rest position +- (displacement at the window start + the path bound over the
        window + 9 PSF sigmas, beyond which the Gaussian is below 1e-17 of its peak); zero
        elsewhere. ``[N, H, W]``."""
        H, W = self._frame_shape
        with torch.no_grad():
            d0 = trajectory.position(window.start[:, None])[:, 0, :].norm(dim=-1)
            reach = float((d0 + trajectory.path_length(window)).max())
            sd = float(psf.cov.detach().diagonal(dim1=-2, dim2=-1).max().sqrt())
        m = reach + 9 * sd + 1
        cx, cy = (float(v) for v in psf.center.detach())
        x0, x1 = max(0, math.floor(cx - m)), min(W, math.ceil(cx + m) + 1)
        y0, y1 = max(0, math.floor(cy - m)), min(H, math.ceil(cy + m) + 1)
        if x1 <= x0 or y1 <= y0:
            return torch.zeros((window.shape[0], H, W), dtype=_F64)
        if (x1 - x0) * (y1 - y0) >= 0.8 * H * W:
            return self._render(trajectory, psf, window)
        part = self._render(trajectory, psf.cropped(x0, y0, x1, y1), window, shape=(y1 - y0, x1 - x0))
        out = torch.zeros((window.shape[0], H, W), dtype=_F64)
        out[:, y0:y1, x0:x1] = part
        return out

    def _still_image_per_s(self) -> torch.Tensor:
        """Electrons per second of the still spot at power 1, ``[H, W]`` (cached)."""
        if self._still_rate is None:
            still = Sinusoid(torch.zeros(2, dtype=_F64), torch.zeros(2, dtype=_F64), torch.tensor(1.0, dtype=_F64))
            if self._layout is None:
                self._still_rate = self._render(still, self._psf, ExposureWindow(torch.zeros(1, dtype=_F64), 1.0))[0]
            else:
                self._still_rate = sum(self._render(still, self._psf[k], ExposureWindow(torch.zeros(1, dtype=_F64), 1.0))[0]
                                       for k in range(len(self._layout)))
        return self._still_rate

    def _expose(self, expected_e: torch.Tensor) -> torch.Tensor:
        return self._camera.expose(expected_e, generator=self._generator)

    def _settling_time_s(self) -> float:
        """How long the command's transient lasts (s): the plant's settling time (a DM rig: its
        slowest actuator's). The default wait of :meth:`_schedule`."""
        return self._plant.settling_time_s()

    def _triggers(self, period: float, exposures_s, trigger_offset_s, n_repeats: int, settle_s):
        """The checked exposures, trigger offsets and repeats of a periodic command and their
        schedule: ``(te [E], R, settle_s, trigger times [E, R], exposures [E, R], offsets [E, R],
        window)``, ``window`` the frames' actual exposure windows (:meth:`_actual_starts`)."""
        te, offsets, R = self._check_periodic(exposures_s, trigger_offset_s, n_repeats)
        settle, trig_t, exp_t, off_t = self._schedule(period, te, offsets, R, settle_s)
        return te, R, settle, trig_t, exp_t, off_t, self._actual_starts(trig_t, exp_t)

    def _schedule(self, period: float, te: list, offsets: list, R: int, settle_s):
        """The triggers of a periodic command: ``R`` frames per exposure ``te[e]``, each fired
        ``offsets[e]`` after a period start, the first after the settling wait and each once
        the camera is ready. Returns ``(settle_s, trigger times [E, R], exposures [E, R],
        offsets within the period [E, R])``."""
        if settle_s is None:
            settle = math.ceil(self._settling_time_s() / period - 1e-9) * period
        else:
            settle = check_real_scalar(settle_s, "settle_s", nonnegative=True)
        E = len(te)
        trig, ready = [], settle
        for e in range(E):
            trig.append(periodic_triggers(ready, period, offsets[e], R, self._cycle_s(te[e])))
            ready = trig[-1][-1] + self._cycle_s(te[e])
        off_mod = []
        for o in offsets:
            m = o - math.floor(o / period) * period
            off_mod.append(0.0 if m >= period else m)
        trig_t = torch.as_tensor(trig, dtype=_F64)
        exp_t = torch.as_tensor(te, dtype=_F64)[:, None].expand(E, R).contiguous()
        off_t = torch.as_tensor(off_mod, dtype=_F64)[:, None].expand(E, R).contiguous()
        return settle, trig_t, exp_t, off_t

    def _capture(self, expected_e: torch.Tensor, exposure_s, trigger_offset_s, trigger_time_s, *, meta: dict) -> Capture:
        """Expose ``expected_e`` (electrons ``[..., H, W]``) and wrap the frames with their
        timing ``[...]`` and the next frame counters."""
        return Capture(frames=self._expose(expected_e), exposure_s=exposure_s, trigger_offset_s=trigger_offset_s,
                       trigger_time_s=trigger_time_s, frame_counter=self._counters(tuple(exposure_s.shape)), meta=meta)

    def _hold_capture(self, rate_e_per_s: torch.Tensor, n, exposure_s, *, meta: dict, generator=None) -> Capture:
        """``n`` frames of each still image ``rate_e_per_s`` ``[K, H, W]`` (e-/s) at ``exposure_s``:
        frames ``[K, n, H, W]`` (a DM rig's ``pattern_ladder``), drawn from ``generator`` (default the rig's)."""
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        K = rate_e_per_s.shape[0]
        expected = (rate_e_per_s * te)[:, None].expand((K, n) + self._frame_shape).contiguous()
        trig = (torch.arange(K * n, dtype=_F64) * self._cycle_s(te)).reshape(K, n)
        frames = self._camera.expose(expected, generator=self._generator if generator is None else generator)
        return Capture(frames=frames, exposure_s=torch.full((K, n), te, dtype=_F64), trigger_offset_s=torch.zeros(K, n, dtype=_F64),
                       trigger_time_s=trig, frame_counter=self._counters((K, n)), meta=meta)

    # ------------------------------------------------------------------ captures

    def dark(self, n: int, exposure_s: float) -> Capture:
        """``n`` frames with the laser off, ``[n, H, W]``."""
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        H, W = self._frame_shape
        trig = torch.arange(n, dtype=_F64) * self._cycle_s(te)
        window = self._actual_starts(trig, torch.full((n,), te, dtype=_F64))
        return self._capture(torch.zeros(n, H, W, dtype=_F64), torch.full((n,), te, dtype=_F64), torch.zeros(n, dtype=_F64), trig,
                             meta={"kind": "dark", "actual_start_s": window.start})

    def still(self, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """``n`` frames of the spot at rest, ``[n, H, W]``."""
        n = check_int(n, "n", low=1)
        te = self._check_exposure(exposure_s)
        power = self._check_power(power)
        trig = torch.arange(n, dtype=_F64) * self._cycle_s(te)
        window = self._actual_starts(trig, torch.full((n,), te, dtype=_F64))
        expected = (self._still_image_per_s() * (power * te)).expand((n,) + self._frame_shape)
        return self._capture(expected.contiguous(), torch.full((n,), te, dtype=_F64), torch.zeros(n, dtype=_F64), trig,
                             meta={"kind": "still", "power": power, "actual_start_s": window.start})

    def sine(
        self,
        freq_hz: float,
        amplitude: float,
        exposures_s: Sequence[float],
        trigger_offset_s: float | Sequence[float],
        n_repeats: int,
        settle_s: float | None = None,
        power: float = 1.0,
        input: str = "x",
    ) -> Capture:
        """Frames of the sine response ``[E, R, H, W]``, as :meth:`~torchblur.rig.base.Rig.sine`.

        ``meta`` holds ``freq_hz``, ``omega``, ``period_s``, ``amplitude``, ``settle_s``,
        ``power``, ``trigger_delay_s``, ``input`` and, for tests only, ``actual_start_s``
        ``[E, R]``.
        """
        if input not in self.inputs:
            raise ParameterError(f"input: expected one of {self.inputs}, got {input!r}")
        freq, amp = self._check_sine(freq_hz, amplitude)
        power = self._check_power(power)
        period = 1.0 / freq
        te, R, settle, trig_t, exp_t, off_t, window = self._triggers(period, exposures_s, trigger_offset_s, n_repeats, settle_s)
        E = len(te)
        omega = 2 * math.pi * freq
        psf = self._psf if power == 1.0 else GaussianPSF(self._psf.center, self._psf.cov, self._psf.amplitude * power)
        flat = ExposureWindow(window.start.reshape(-1), window.duration.reshape(-1))
        amp_t, om_t = torch.tensor(amp, dtype=_F64), torch.tensor(omega, dtype=_F64)
        if isinstance(self._plant, Plant) and self._layout is None:
            traj = LTISineTrajectory(self._plant, amp_t, om_t, direction=self._direction)
            expected = self._render(traj, psf, flat)
        else:  # each spot's own motion G_k @ y(t), rendered spot by spot (in the region it can reach) and added
            G = self._image_matrices()
            expected = sum(self._render_near(MIMOSineTrajectory(self._plant, amp_t, om_t, input=input, image_matrix=G[k]),
                                             psf if psf.shape == () else psf[k], flat) for k in range(G.shape[0]))
        expected = expected.reshape((E, R) + self._frame_shape)
        meta = {
            "kind": "sine",
            "freq_hz": freq,
            "omega": omega,
            "period_s": period,
            "amplitude": amp,
            "settle_s": settle,
            "power": power,
            "trigger_delay_s": self._trigger_delay_s,
            "input": input,
            "actual_start_s": window.start,
        }
        return self._capture(expected, exp_t, off_t, trig_t, meta=meta)

    def pulse(
        self,
        exposure_s: float,
        trigger_offset_s: float | Sequence[float],
        pulse_time_s: float,
        pulse_width_s: float,
        n: int,
        power: float = 1.0,
    ) -> Capture:
        """Latency calibration, as :meth:`~torchblur.rig.base.Rig.pulse`: frames ``[..., n, H, W]``.

        The light collected is the still spot times the overlap of the exposure
        ``[trigger + Td + latency, ... + Te]`` with the pulse, so brightness vs
        ``trigger_offset_s`` is a trapezoid: it falls to zero at
        ``trigger_offset_s = pulse_time_s + pulse_width_s - Td - latency`` and rises from
        zero at ``pulse_time_s - Td - latency - Te``. ``meta`` holds the pulse,
        ``reference_time_s`` and, for tests only, ``actual_start_s``.
        """
        te, n, power, p0, width = self._check_pulse(exposure_s, n, power, pulse_time_s, pulse_width_s)
        offs = check_finite(as_tensor(trigger_offset_s, "trigger_offset_s", dtype=_F64), "trigger_offset_s")
        shape = tuple(offs.shape) + (n,)
        off_flat = offs[..., None].expand(shape).reshape(-1).tolist()
        ref = pulse_references(off_flat, p0, width, self._cycle_s(te))[0]
        ref_t = torch.as_tensor(ref, dtype=_F64).reshape(shape)
        off_t = torch.as_tensor(off_flat, dtype=_F64).reshape(shape)
        trig_t = ref_t + off_t
        exp_t = torch.full(shape, te, dtype=_F64)
        window = self._actual_starts(trig_t, exp_t)
        on0 = ref_t + p0
        overlap = (torch.minimum(window.end, on0 + width) - torch.maximum(window.start, on0)).clamp_min(0.0)
        expected = self._still_image_per_s() * (power * overlap)[..., None, None]
        meta = {
            "kind": "pulse",
            "pulse_time_s": p0,
            "pulse_width_s": width,
            "power": power,
            "trigger_delay_s": self._trigger_delay_s,
            "reference_time_s": ref_t,
            "actual_start_s": window.start,
        }
        return self._capture(expected, exp_t, off_t, trig_t, meta=meta)

    def multisine(
        self,
        freq_hz: Sequence[float],
        amplitude: Sequence[float],
        phase_rad: Sequence[float],
        exposures_s: Sequence[float],
        trigger_offset_s: float | Sequence[float],
        n_repeats: int,
        base_freq_hz: float | None = None,
        settle_s: float | None = None,
        power: float | Sequence[float] = 1.0,
    ) -> Capture:
        """Frames of the multisine response ``[E, R, H, W]``, as :meth:`~torchblur.rig.base.Rig.multisine`:
        the exact plant output (:class:`~torchblur.systems.lti.LTIMultisineTrajectory`, transients
        included). ``meta`` holds the tones, ``base_freq_hz``, ``period_s``, ``settle_s``, ``power``,
        ``trigger_delay_s`` and, for tests only, ``actual_start_s`` ``[E, R]``.
        """
        freqs, amps, phases, f0 = self._check_tones(freq_hz, amplitude, phase_rad, base_freq_hz)
        check_drive(command_peak(freqs, amps, phases, f0), self._input_limit)
        check_slew(command_slew(freqs, amps, phases, f0), self._slew_limit)
        te, offsets, R = self._check_periodic(exposures_s, trigger_offset_s, n_repeats)
        E = len(te)
        powers = [self._check_power(v) for v in per_exposure(power, E, "power")]  # checked before the jitter draws
        period = 1.0 / f0
        settle, trig_t, exp_t, off_t = self._schedule(period, te, offsets, R, settle_s)
        window = self._actual_starts(trig_t, exp_t)
        omega = [2 * math.pi * f for f in freqs]
        traj = LTIMultisineTrajectory(self._plant, torch.tensor(amps, dtype=_F64), torch.tensor(omega, dtype=_F64),
                                      torch.tensor(phases, dtype=_F64), direction=self._direction)
        flat = ExposureWindow(window.start.reshape(-1), window.duration.reshape(-1))
        expected = self._render(traj, self._psf, flat).reshape((E, R) + self._frame_shape)
        expected = expected * torch.as_tensor(powers, dtype=_F64)[:, None, None, None]  # the image is linear in the power
        meta = {
            "kind": "multisine",
            "freq_hz": freqs,
            "amplitude": amps,
            "phase_rad": phases,
            "base_freq_hz": f0,
            "period_s": period,
            "settle_s": settle,
            "power": powers if len(set(powers)) > 1 else powers[0],
            "trigger_delay_s": self._trigger_delay_s,
            "actual_start_s": window.start,
        }
        return self._capture(expected, exp_t, off_t, trig_t, meta=meta)

    def __repr__(self) -> str:
        kind = f"{self._plant.n_outputs}x{self._plant.n_inputs} plant" if isinstance(self._plant, PlantMatrix) else "plant"
        spots = "" if self._layout is None else f", {len(self._layout)} spots"
        return (
            f"SimulatedRig(frame_shape={self._frame_shape}, {kind} order {self._plant.order}, "
            f"delay {self._plant.delay_s:g} s, frame_rate_hz={self._frame_rate_hz:g}, seed={self._seed}{spots})"
        )
