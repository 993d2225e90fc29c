"""The simulated rig of a configuration: :func:`build_simulated_rig` and the plant it moves
(:func:`plant_of`); a DM config's simulated mirror, sensor and rig (:func:`build_dm`).

Both take any object with the ``plant``, ``camera``, ``seed`` (and optionally ``spots``)
sections of :class:`~torchblur.config.IdentifyConfig`; nothing here imports the
identification pipeline, so the bench emulator builds its rig from here.
"""
from __future__ import annotations

from torchblur.dm.mirror import DeformableMirror
from torchblur.dm.registration import Registration
from torchblur.dm.shack_hartmann import ShackHartmann
from torchblur.render.camera import CameraModel
from torchblur.rig.dm import SimulatedDMRig
from torchblur.rig.simulated import SimulatedRig
from torchblur.systems.mimo import plant_from_coefficients

__all__ = ["build_dm", "build_simulated_rig", "camera_of", "plant_of"]


def camera_of(c) -> CameraModel:
    """The camera model of a config's ``camera`` section (its sensor: dark level, read noise, gain, full well, bit depth)."""
    return CameraModel(dark_level_adu=c.dark_level, read_noise_e=c.read_noise, gain_e_per_adu=c.gain, full_well_e=c.full_well,
                       bit_depth=int(c.bit_depth))


def plant_of(cfg):
    """The plant of ``cfg.plant``: a :class:`~torchblur.systems.lti.Plant`, or a
    :class:`~torchblur.systems.mimo.PlantMatrix` for 2x2 nested ``num``/``den``."""
    return plant_from_coefficients(cfg.plant.num, cfg.plant.den, cfg.plant.delay_s)


def build_simulated_rig(cfg) -> SimulatedRig:
    """The simulated rig of a config (plant, camera, timing, noise)."""
    c = cfg.camera
    camera = camera_of(c)
    spots = cfg.spots.grid(c) if getattr(cfg, "spots", None) is not None else None
    direction = tuple(float(v) for v in cfg.plant.direction) if not cfg.plant.is_mimo else (1.0, 0.0)
    return SimulatedRig(plant=plant_of(cfg), camera=camera, frame_shape=(int(c.height), int(c.width)), psf_sigma_px=c.psf_sigma_px,
                        frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s, readout_s=c.readout_s,
                        max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s, seed=int(cfg.seed), spots=spots,
                        direction=direction, input_limit=float(cfg.plant.input_limit),
                        slew_limit=None if cfg.plant.slew_limit is None else float(cfg.plant.slew_limit))


def build_dm(cfg, *, base_dir: str | None = None, rig_seed: int | None = None):
    """``(mirror, wfs, rig)`` of a DM config: the simulated mirror (``dm`` section, seeded by
    ``seed``), the sensor (``wfs``) and the :class:`~torchblur.rig.dm.SimulatedDMRig` with the
    ``camera`` section's sensor and timing (its noise seeded by ``rig_seed``, default ``seed``)
    and the mirror's true registration ``dm.registration``."""
    mirror = DeformableMirror.from_config(cfg.dm, base_dir=base_dir, seed=int(cfg.seed))
    wfs = ShackHartmann.from_config(cfg.wfs, mirror)
    c = cfg.camera
    camera = camera_of(c)
    rig = SimulatedDMRig(mirror=mirror, wfs=wfs, camera=camera, frame_rate_hz=c.frame_rate_hz, trigger_delay_s=c.trigger_delay_s,
                         readout_s=c.readout_s, max_exposure_s=c.max_exposure_s, latency_s=c.latency_s, jitter_s=c.jitter_s,
                         seed=int(cfg.seed) if rig_seed is None else int(rig_seed),
                         registration=Registration.from_config(cfg.dm.registration))
    return mirror, wfs, rig
