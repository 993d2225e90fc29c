"""Where the run's frames come from: the rig of the config (:func:`build_rig`; the simulated
rig itself is built by :mod:`torchblur.rig.factory`) and the recording it is written to or
resumed from (:func:`open_experiment`, :func:`check_resume_config`, :func:`check_refit_config`), and a
run's session of it (:func:`session`, :func:`session_info`: every plan's)."""
from __future__ import annotations

import contextlib
from dataclasses import replace
from pathlib import Path

from torchblur.errors import ConfigError
from torchblur.hardware.errors import HardwareError, RecordingError
from torchblur.hardware.frames import CameraInfo
from torchblur.hardware.recording import Experiment
from torchblur.hardware.serial_rig import SerialRig
from torchblur.config import IdentifyConfig, config_keys, config_to_yaml, load_dataclass
from torchblur.identify.drive import SESSION_KEY, SLEW_KEY
from torchblur.identify.record import LOGGER
from torchblur.rig.factory import build_simulated_rig, plant_of
from torchblur.sysid.frequency_response_io import json_floats

__all__ = ["build_rig", "build_simulated_rig", "check_refit_config", "check_resume_config", "open_experiment", "plant_of", "session",
           "session_info"]


def build_rig(cfg: IdentifyConfig, *, log=None):
    """The rig of ``cfg.rig``: the simulated rig, or a :class:`~torchblur.hardware.SerialRig`
    on ``rig.port`` (controller) and ``rig.frames`` (camera). A camera whose frame shape
    differs from ``camera.height`` x ``camera.width`` is a :class:`ConfigError`."""
    if cfg.rig.kind == "simulated":
        return build_simulated_rig(cfg)
    rig = SerialRig.open(cfg.rig.port, cfg.rig.frames, timeout_s=float(cfg.rig.timeout_s), retries=int(cfg.rig.retries), log=log)
    shape = (int(cfg.camera.height), int(cfg.camera.width))
    if tuple(rig.frame_shape) != shape:
        rig.close()
        raise ConfigError(f"camera.height: the camera on {cfg.rig.frames} delivers {rig.frame_shape[0]}x{rig.frame_shape[1]} "
                          f"frames, the config says {shape[0]}x{shape[1]} (camera.height x camera.width)")
    return rig


_RESUMABLE_SECTIONS = ("rig", "fit", "model", "report")


def check_resume_config(recorded, cfg, *, allowed=_RESUMABLE_SECTIONS) -> None:
    """Raise :class:`~torchblur.hardware.errors.RecordingError` naming the first key where
    ``cfg`` differs from the ``recorded`` config outside the sections in ``allowed``."""
    for (key, was, _), (_, now, _) in zip(config_keys(recorded), config_keys(cfg)):
        if key.split(".", 1)[0] not in allowed and was != now:
            raise RecordingError(f"{key}: the recording was made with {was!r}, got {now!r}; only "
                                 f"{', '.join(s + '.*' for s in allowed)} may change")


def check_refit_config(recorded, cfg, *, allowed=("fit", "model", "report")):
    """:func:`check_resume_config` of a re-fit, which may also change ``dm_plan.support_threshold``
    (:func:`torchblur.identify.dm_record.recorded_plan`). Returns ``cfg`` with the recorded threshold."""
    aligned = replace(cfg, dm_plan=replace(cfg.dm_plan, support_threshold=recorded.dm_plan.support_threshold))
    check_resume_config(recorded, aligned, allowed=allowed)
    return aligned


def session_info(cfg, rig, **extra) -> dict:
    """What a recording's session notes of its rig: ``rig.*`` kind, port, frames, its repr, its input range and slew limit
    (None where it has none: a replay plans within the recorded ones, :mod:`torchblur.identify.drive`), and ``extra``."""
    return {"kind": cfg.rig.kind, "port": cfg.rig.port, "frames": cfg.rig.frames, "rig": repr(rig),
            SESSION_KEY: json_floats(getattr(rig, "input_limit", None)),
            SLEW_KEY: json_floats(getattr(rig, "slew_limit", None)), **extra}


def open_experiment(record, cfg, rig):
    """An :class:`~torchblur.hardware.Experiment` from ``record`` (None, a path or one), checked
    against ``cfg`` (only ``rig.*``, ``fit.*``, ``model.*`` and ``report.*`` may differ from the
    recorded config, and for a read-only recording, a re-fit, ``dm_plan.support_threshold``:
    :func:`check_refit_config`) and ``rig``'s frame shape."""
    if record is None:
        return None
    if isinstance(record, Experiment):
        exp = record
    else:
        path = Path(record)
        if (path / "experiment.json").is_file():
            exp = Experiment.open(path)
        else:
            return Experiment.create(path, config_yaml=config_to_yaml(cfg), camera=CameraInfo.of(rig))
    recorded = load_dataclass(type(cfg), str(exp.path / "config.yaml"), trusted=False)
    if exp.writable:
        check_resume_config(recorded, cfg)
    else:
        check_refit_config(recorded, cfg, allowed=_RESUMABLE_SECTIONS)
    shape = tuple(exp.camera_info.frame_shape)
    if tuple(rig.frame_shape) != shape:
        raise RecordingError(f"{exp.path}: recorded with {shape[0]}x{shape[1]} frames, the rig delivers "
                             f"{rig.frame_shape[0]}x{rig.frame_shape[1]}")
    return exp


@contextlib.contextmanager
def session(exp, rig_info: dict):
    """A session of the recording ``exp`` (none: nothing) around the ``with`` block: started with
    ``rig_info``, ended ``complete``, or ``interrupted`` (KeyboardInterrupt), ``stopped`` (the
    rig's :class:`~torchblur.hardware.errors.HardwareError`) or ``failed``, then re-raised; a
    resumed recording's reused groups are logged. A read-only recording (a re-fit) gets no session."""
    if exp is None or not exp.writable:
        yield
        return
    exp.start_session(rig_info)
    if len(exp.groups):
        LOGGER.info(f"resume: {len(exp.groups)} recorded group(s) in {exp.path} are reused")
    try:
        yield
    except KeyboardInterrupt:
        exp.end_session("interrupted", "KeyboardInterrupt")
        raise
    except BaseException as exc:
        exp.end_session("stopped" if isinstance(exc, HardwareError) else "failed", f"{type(exc).__name__}: {exc}")
        raise
    exp.end_session("complete")
