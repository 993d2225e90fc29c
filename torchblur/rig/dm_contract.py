"""The DM rig contract: what :func:`torchblur.identify` (a DM config) calls on a lab's deformable-mirror
rig (docs/dm_rig.md says it in words, with the timing and what the calibration needs).

:class:`DMRig` is the :class:`typing.Protocol` a rig implements (the simulated
:class:`~torchblur.rig.dm.SimulatedDMRig`, the serial :class:`~torchblur.hardware.serial_dm_rig.SerialDMRig`,
a lab's wrapper of its vendor SDK: docs/examples/vendor_dm.py). :func:`check_dm_rig` checks a rig
against it and against the run's config before the first frame, so a missing method or a
mirror of another size stops the run with an error that names what is missing, not a
traceback after the calibration.

Units at this interface: seconds, Hz, the command in the rig's input units (what
``dm.input_limit`` and the reported D are per), frames in ADU. A leaf: it imports nothing of
``torchblur.identify``.
"""
from __future__ import annotations

from typing import Protocol, Sequence, runtime_checkable

from torchblur.config.budget import dm_geometry, dm_sensor
from torchblur.errors import ConfigError, InputTypeError
from torchblur.rig.base import CameraRig, Capture

__all__ = ["DMRig", "REQUIRED_ATTRIBUTES", "REQUIRED_METHODS", "check_dm_rig"]

#: the methods every DM rig has (``pulse`` only where the latency is scanned: :func:`check_dm_rig`)
REQUIRED_METHODS = ("dark", "still", "pattern_sine")
#: the properties every DM rig has (the recording's camera description and the run's checks)
REQUIRED_ATTRIBUTES = ("frame_shape", "frame_rate_hz", "max_exposure_s", "readout_s", "input_limit", "n_actuators")


@runtime_checkable
class DMRig(CameraRig, Protocol):
    """A deformable mirror driven by a controller that fires the camera trigger on its own clock,
    and the Shack-Hartmann sensor's camera (docs/dm_rig.md).

    Every method returns a :class:`~torchblur.rig.base.Capture` (frames in ADU, float, and each
    frame's ``exposure_s``, ``trigger_offset_s`` and ``trigger_time_s``). The route calls
    ``pattern_sine`` by keyword (a recording stores the arguments by name). The camera's
    properties are :class:`~torchblur.rig.base.CameraRig`'s: here ``frame_shape`` is the sensor's
    (``wfs.n_across * wfs.pitch_px`` square) and ``input_limit`` the largest |command| of any actuator.
    """

    @property
    def n_actuators(self) -> int:
        """N, the actuators (the length of a pattern): the config's ``dm.n_across`` grid inside the pupil."""
        ...

    def dark(self, n: int, exposure_s: float) -> Capture:
        """``n`` frames with the light off: frames ``[n, H, W]`` (the dark level and read noise)."""
        ...

    def still(self, n: int, exposure_s: float, power: float = 1.0) -> Capture:
        """``n`` frames of the mirror at rest (every actuator at 0), the light at ``power``
        (relative; 1 if the source is not dimmable): frames ``[n, H, W]``. Called with
        ``n = 1`` on a ladder of exposures (the saturation curve) and with many frames at
        one exposure (each spot's PSF)."""
        ...

    def pattern_sine(self, pattern: Sequence[float], freq_hz: float, amplitude: float, exposures_s: Sequence[float],
                     trigger_offset_s: float | Sequence[float], n_repeats: int, settle_s: float | None = None,
                     power: float = 1.0) -> Capture:
        """Drive actuator j with ``amplitude * pattern[j] * sin(2 pi freq_hz t)`` (t = 0 the
        start of the sine, every actuator on the same clock), wait ``settle_s`` (None: the
        rig's own settling time, whole periods), then take ``n_repeats`` frames per exposure
        of ``exposures_s``, each triggered ``trigger_offset_s`` (one value or one per
        exposure) after an upward zero crossing of the sine: frames ``[E, R, H, W]``, with
        ``trigger_time_s [E, R]`` the trigger times on that clock (s)."""
        ...


def _has(rig, name: str) -> bool:
    try:
        return hasattr(rig, name)
    except Exception:  # a property that raises on a closed device: it is there, but unusable
        return False


def check_dm_rig(rig, cfg) -> None:
    """Refuse, before any frame, a rig that does not fulfil :class:`DMRig` for the DM config
    ``cfg``: a missing method or property, a mirror whose ``n_actuators`` differs from the
    config's geometry, or a frame shape other than the sensor's. (``pulse`` missing where the
    latency must be scanned: :func:`torchblur.identify.calibration.check_latency_source`, which
    :func:`torchblur.identify` (a DM config) calls beside this.)

    Raises:
        InputTypeError: naming ``rig`` and what it lacks.
        ConfigError: naming ``dm.n_across`` or ``wfs.pitch_px`` (the rig's mirror or frames do
            not match the config), or ``dm_plan.spot_model`` (ladder on a rig without ``pattern_ladder``).
    """
    missing = [f"{m}()" for m in REQUIRED_METHODS if not callable(getattr(rig, m, None))]
    missing += [a for a in REQUIRED_ATTRIBUTES if not _has(rig, a)]
    if missing:
        raise InputTypeError(f"rig: a {type(rig).__name__} lacks {', '.join(missing)} of the DM rig contract "
                             f"(torchblur.rig.dm_contract.DMRig, docs/dm_rig.md)")
    n = int(rig.n_actuators)
    want = dm_geometry(cfg).shape[1]
    if n != want:
        raise ConfigError(f"dm.n_across: the config's mirror ({cfg.dm.n_across} across) has {want} actuators inside the pupil, "
                          f"the rig's {n}; describe the rig's mirror in the dm section")
    shape = tuple(int(v) for v in rig.frame_shape)
    sensor = tuple(dm_sensor(cfg)[1].frame_shape)
    if shape != sensor:
        raise ConfigError(f"wfs.pitch_px: the sensor of the config (wfs.n_across {cfg.wfs.n_across} x wfs.pitch_px "
                          f"{cfg.wfs.pitch_px:g}) has {sensor[0]}x{sensor[1]} px frames, the rig's camera {shape[0]}x{shape[1]}; "
                          f"crop the camera to the lenslet array or describe it in the wfs section")
    if cfg.dm_plan.spot_model == "ladder" and not callable(getattr(rig, "pattern_ladder", None)):
        raise ConfigError(f"dm_plan.spot_model: ladder needs static holds of each pattern, and a {type(rig).__name__} has no "
                          f"pattern_ladder() (docs/dm_rig.md); use auto or shifted, or add pattern_ladder to the rig")
