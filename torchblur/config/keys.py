"""Every key of ``torchblur identify``'s config with its value and unit: ``torchblur config``.

:func:`config_keys` walks the resolved :class:`~torchblur.config.schema.IdentifyConfig`
(defaults, a ``--config`` file and overrides merged by
:func:`~torchblur.config.load.load_config`); the unit of a key comes from its name's
suffix (``_hz`` Hz, ``_s`` s, ``_px`` px, ``_rad`` rad, ``_deg`` deg) or, for the keys whose
name does not say it, from :data:`UNITS`. ``-`` marks a key without a unit (a count, a choice,
a flag).
"""
from __future__ import annotations

import json
from dataclasses import fields, is_dataclass

__all__ = ["config_keys", "format_config_keys", "unit_of", "UNITS"]

#: units of the keys whose name does not carry one
UNITS = {
    "plant.num": "px per input unit x (rad/s)^k, highest power first",
    "plant.den": "(rad/s)^k, highest power first",
    "plant.direction": "image direction (x, y), px per plant output unit",
    "plant.input_limit": "input units",
    "sweep.exposures": "fractions of the period",
    "excitation.max_amplitude": "input units",
    "excitation.target_std": "relative",
    "excitation.snap_tol": "relative",
    "camera.read_noise": "e-",
    "camera.gain": "e-/ADU",
    "camera.full_well": "e-",
    "camera.bit_depth": "bits",
    "camera.dark_level": "ADU",
    "camera.height": "px",
    "camera.width": "px",
    "camera.peak_fraction": "of full scale",
    "fit.outlier_sigma": "noise stds",
    "fit.poor_fit_chi2": "reduced chi2",
    "report.tolerance_rel": "relative",
    "spots.sigma_variation": "relative",
    "spots.gain_variation": "relative",
    "dm.coupling": "at one pitch",
    "dm.gain": "px per input unit (nominal 1)",
    "dm.damping": "ratio",
    "dm.weak_gain": "of the nominal gain",
    "dm.input_limit": "input units",
    "wfs.min_illumination": "fraction of a subaperture",
    "wfs.sigma_variation": "relative",
    "dm_plan.budget_frames": "frames",
    "dm_plan.support_threshold": "relative",
    "dm_plan.ladder_levels": "levels",
    "dm_plan.ladder_frames": "frames per level",
    "dm_plan.ladder_reach": "of the largest command the sweep expects",
}
_SUFFIXES = (("_hz", "Hz"), ("_s", "s"), ("_px", "px"), ("_rad", "rad"), ("_deg", "deg"))


def unit_of(key: str) -> str:
    """The unit of the dotted config ``key`` (``"-"`` for none)."""
    if key in UNITS:
        return UNITS[key]
    name = key.rsplit(".", 1)[-1]
    return next((unit for suffix, unit in _SUFFIXES if name.endswith(suffix)), "-")


def config_keys(cfg) -> list[tuple[str, object, str]]:
    """``[(dotted key, value, unit)]`` of every leaf of the config dataclass ``cfg``, in the
    order of its sections."""

    def walk(obj, prefix):
        for f in fields(obj):
            value = getattr(obj, f.name)
            if is_dataclass(value):
                yield from walk(value, f"{prefix}{f.name}.")
            else:
                yield f"{prefix}{f.name}", value, unit_of(f"{prefix}{f.name}")

    return list(walk(cfg, ""))


def format_config_keys(cfg) -> str:
    """One line per key, ``key = value  # unit``, values as YAML writes them (``null``, lists)."""
    rows = [(k, json.dumps(v) if not isinstance(v, str) else v, u) for k, v, u in config_keys(cfg)]
    width = max(len(f"{k} = {v}") for k, v, _ in rows if len(f"{k} = {v}") <= 60)
    return "\n".join(f"{f'{k} = {v}':<{width}}  # {u}" if u != "-" else f"{k} = {v}" for k, v, u in rows) + "\n"
