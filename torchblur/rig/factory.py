"""The simulated rig of a configuration: :func:`build_simulated_rig` and the plant it moves
(:func:`plant_of`).

Both take any object with the ``plant``, ``camera``, ``seed`` (and optionally ``spots``)
sections of :class:`~torchblur.config.IdentifyConfig`; nothing here imports the
identification pipeline, so the bench emulator builds its rig from here.
"""
from __future__ import annotations

from torchblur.render.camera import CameraModel
from torchblur.rig.simulated import SimulatedRig
from torchblur.systems.mimo import plant_from_coefficients

__all__ = ["build_simulated_rig", "plant_of"]


def plant_of(cfg):
    """The plant of ``cfg.plant``: a :class:`~torchblur.systems.lti.Plant`, or a
    :class:`~torchblur.systems.mimo.PlantMatrix` for 2x2 nested ``num``/``den``."""
    return plant_from_coefficients(cfg.plant.num, cfg.plant.den, cfg.plant.delay_s)


def build_simulated_rig(cfg) -> SimulatedRig:
    """The simulated rig of a config (plant, camera, timing, noise)."""
    c = cfg.camera
    camera = CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                         bit_depth=int(c.bit_depth))
    spots = cfg.spots.grid(c) if getattr(cfg, "spots", None) is not None else None
    direction = tuple(float(v) for v in cfg.plant.direction) if not cfg.plant.is_mimo else (1.0, 0.0)
    return SimulatedRig(plant=plant_of(cfg), camera=camera, frame_shape=(int(c.height), int(c.width)), psf_sigma_px=c.psf_sigma_px,
                        frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s, readout_s=c.readout_s,
                        max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s, seed=int(cfg.seed), spots=spots,
                        direction=direction, input_limit=float(cfg.plant.input_limit),
                        slew_limit=None if cfg.plant.slew_limit is None else float(cfg.plant.slew_limit))
