"""The checks of a config (:class:`~torchblur.config.schema.IdentifyConfig`): every value of
every section, and the rules between keys; each raises :class:`ConfigError` naming the key,
what was expected and what came.
"""
from __future__ import annotations

from dataclasses import fields
from urllib.parse import urlparse

import numpy as np
import torch

from torchblur.config.budget import LIMITS
from torchblur.config.camera_urls import aravis_url_options, pylon_url_options
from torchblur.config.schema import (AXIS_MODES, CameraConfig, DMConfig, ExcitationConfig, IdentifyConfig,
                                     PlantConfig, RigConfig, SpotsConfig, SweepConfig, WFSConfig, is_nested)
from torchblur.errors import ConfigError, ParameterError, check_real_scalar, excerpt
from torchblur.losses import LIKELIHOOD_LOSSES

__all__ = ["validate", "validate_plant", "validate_camera", "validate_spots", "validate_excitation", "validate_sweep",
           "validate_rig", "validate_dm", "validate_dm_model", "validate_fit", "validate_device", "validate_model", "validate_report",
           "validate_spot_room", "validate_drive_limits", "validate_exposure_time", "validate_plan_compatibility",
           "validate_loss_for_plan", "whole_periods", "check_number", "check_declared"]


def check_number(value, key: str, **bounds) -> float:
    """:func:`~torchblur.errors.check_real_scalar` of the config ``key`` (``bounds``: its keywords):
    a :class:`ConfigError` naming the key."""
    return check_real_scalar(value, key, error=ConfigError, **bounds)


def check_declared(section, prefix: str) -> None:
    """Every single-field check declared in the dataclass ``section``'s fields
    (:func:`torchblur.config.schema.key`), in field order; :class:`ConfigError` naming the key
    ``prefix.name`` (``name`` for the top level, ``prefix`` empty)."""
    for f in fields(section):
        rule = f.metadata.get("check")
        value, key = getattr(section, f.name), f"{prefix}.{f.name}" if prefix else f.name
        if rule is None or (value is None and rule.get("optional")):
            continue
        if "choice" in rule:
            if not isinstance(value, str) or value not in rule["choice"]:
                raise ConfigError(f"{key}: expected one of {tuple(rule['choice'])}, got {excerpt(value)}")
        elif rule.get("flag"):
            if not isinstance(value, bool):
                raise ConfigError(f"{key}: expected true or false, got {excerpt(value)}")
        elif rule.get("text"):
            if not isinstance(value, str) or not value.strip():
                raise ConfigError(f"{key}: expected {rule.get('what', 'a non-empty string')}, got {excerpt(value)}")
        elif "items" in rule:
            fewest, most = rule.get("length", (0, None))
            if not isinstance(value, (list, tuple)) or len(value) < fewest or (most is not None and len(value) > most):
                raise ConfigError(f"{key}: expected {rule['what']}, got {_short(value)}")
            for i, v in enumerate(value):
                check_number(v, f"{key}[{i}]", **rule["items"])
        else:
            check_number(value, key, **{k: v for k, v in rule.items() if k != "optional"})


def _short(value) -> str:
    if isinstance(value, str):
        return excerpt(value)
    r = excerpt(value, 80)
    return r if not r.endswith("...") else f"{r}({len(value) if hasattr(value, '__len__') else '?'} entries)"


def _coeffs(value, key) -> list[float]:
    if not isinstance(value, (list, tuple)) or not value or len(value) > 33:
        raise ConfigError(f"{key}: expected a list of 1 to 33 coefficients (highest power first), got {_short(value)}")
    return [check_number(v, f"{key}[{i}]") for i, v in enumerate(value)]


def _pair(value, key: str, what: str) -> list[float]:
    """A nonzero pair of finite numbers (a direction)."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ConfigError(f"{key}: expected {what}, got {excerpt(value)}")
    v = [check_number(x, f"{key}[{i}]") for i, x in enumerate(value)]
    if v == [0.0, 0.0]:
        raise ConfigError(f"{key}: expected a nonzero direction, got {excerpt(value)}")
    return v


def _check_channel(num, den, key_num: str, key_den: str) -> None:
    num = _coeffs(num, key_num)
    den = _coeffs(den, key_den)
    while len(num) > 1 and num[0] == 0:
        num = num[1:]
    if den[0] == 0:
        raise ConfigError(f"{key_den}: the leading coefficient must be non-zero")
    if len(num) > len(den):
        raise ConfigError(f"{key_num}: the plant must be proper (degree of num {len(num) - 1} > degree of den {len(den) - 1})")
    poles = np.roots(den)
    if len(poles) and (poles.real >= 0).any():
        raise ConfigError(f"{key_den}: the plant must be stable; poles with real part >= 0: {poles[poles.real >= 0]}")


def _check_2x2(value, key: str) -> None:
    """``value`` must be 2 rows of 2 non-empty coefficient lists."""
    shape = [len(r) if isinstance(r, (list, tuple)) else type(r).__name__ for r in value] if isinstance(value, (list, tuple)) else value
    if not isinstance(value, (list, tuple)) or len(value) != 2 or any(not isinstance(r, (list, tuple)) or len(r) != 2 for r in value):
        raise ConfigError(f"{key}: expected 2x2 nested lists ({key}[i][j]: output i from input j, i, j in x, y), got rows {shape}")
    for i in range(2):
        for j in range(2):
            if not isinstance(value[i][j], (list, tuple)):
                raise ConfigError(f"{key}[{i}][{j}]: expected a list of coefficients (highest power first), got {excerpt(value[i][j])}")


def validate_plant(plant: PlantConfig) -> None:
    """Check the ``plant`` section; raise :class:`ConfigError` naming the key. ``num``/``den``
    are flat lists (SISO) or both 2x2 nested lists (a tip-tilt mirror, ``num[i][j]``: output i
    from input j); ``delay_s`` is a number, or for a 2x2 plant a number or 2x2 nested list."""
    check_declared(plant, "plant")
    mimo_num, mimo_den = is_nested(plant.num), is_nested(plant.den)
    direction = _pair(plant.direction, "plant.direction", "[x, y] px per output unit")
    if not mimo_num and not mimo_den:
        _check_channel(plant.num, plant.den, "plant.num", "plant.den")
        check_number(plant.delay_s, "plant.delay_s", nonnegative=True)
        return
    if direction != [1.0, 0.0]:
        raise ConfigError(f"plant.direction: applies to a one-axis plant (a 2x2 plant's channels hold its directions), "
                          f"got {excerpt(plant.direction)}")
    if not mimo_num:
        raise ConfigError(f"plant.num: expected 2x2 nested lists like plant.den (a MIMO plant), got {excerpt(plant.num)}")
    if not mimo_den:
        raise ConfigError(f"plant.den: expected 2x2 nested lists like plant.num (a MIMO plant), got {excerpt(plant.den)}")
    _check_2x2(plant.num, "plant.num")
    _check_2x2(plant.den, "plant.den")
    for i in range(2):
        for j in range(2):
            _check_channel(plant.num[i][j], plant.den[i][j], f"plant.num[{i}][{j}]", f"plant.den[{i}][{j}]")
    d = plant.delay_s
    if isinstance(d, (list, tuple)):
        if len(d) != 2 or any(not isinstance(r, (list, tuple)) or len(r) != 2 for r in d):
            raise ConfigError(f"plant.delay_s: expected a number or 2x2 nested lists, got {excerpt(d)}")
        for i in range(2):
            for j in range(2):
                check_number(d[i][j], f"plant.delay_s[{i}][{j}]", nonnegative=True)
    else:
        check_number(d, "plant.delay_s", nonnegative=True)


def validate_spots(sp: SpotsConfig, camera: CameraConfig | None = None) -> None:
    """Check the ``spots`` section; raise :class:`ConfigError` naming the key."""
    check_number(sp.rows, "spots.rows", integer=True, low=0)  # the section's switch: the rest only when enabled
    if not sp.enabled:
        return
    check_declared(sp, "spots")
    n = int(sp.rows) * int(sp.cols)
    for i, m in enumerate(sp.missing):
        check_number(m, f"spots.missing[{i}]", integer=True, low=0, high=n - 1)
    if len(set(int(m) for m in sp.missing)) >= n:
        raise ConfigError("spots.missing: every spot of the grid is missing")
    if camera is not None:
        side = sp.crop_side()
        if side < 8:
            raise ConfigError(f"spots.pitch_px: a crop of floor(pitch_px) = {side} px is too small (at least 8; or set spots.crop_px)")
        if side > min(camera.height, camera.width):
            raise ConfigError(f"spots.crop_px: a crop of {side} px does not fit a {camera.height}x{camera.width} frame")


def validate_dm_model(d: DMConfig, w: WFSConfig) -> None:
    """Check the ``dm`` and ``wfs`` sections (the mirror and its sensor: all the bench emulator's
    DM mode reads); raise :class:`ConfigError` naming the key."""
    check_number(d.n_across, "dm.n_across", integer=True, low=0, high=64)  # the section's switch
    if not d.enabled:
        return
    check_declared(d, "dm")
    check_declared(d.registration, "dm.registration")
    check_declared(w, "wfs")


def validate_dm(cfg: IdentifyConfig) -> None:
    """Check the ``dm``, ``wfs`` and ``dm_plan`` sections of a DM run; raise :class:`ConfigError`
    naming the key (the actuator table itself is read, and checked, when the mirror is built)."""
    d, w, p = cfg.dm, cfg.wfs, cfg.dm_plan
    validate_dm_model(d, w)
    if not d.enabled:
        return
    check_declared(p, "dm_plan")
    if p.budget_frames is None and p.n_repeats is None:
        raise ConfigError("dm_plan.budget_frames: expected a frame budget, or set dm_plan.n_repeats")
    if p.budget_frames is not None:
        check_number(p.budget_frames, "dm_plan.budget_frames", integer=True, low=1, high=LIMITS["frames"])
    room = w.pitch_px / 2 - 3 * w.sigma_px * (1 + w.sigma_variation)
    if cfg.excitation.target_px > room:
        raise ConfigError(f"excitation.target_px: a DM spot motion of {cfg.excitation.target_px} px does not stay in its "
                          f"subaperture (room {room:.3g} px: wfs.pitch_px / 2 less 3 PSF sigmas)")


def validate_camera(c: CameraConfig) -> None:
    """Check the ``camera`` section; raise :class:`ConfigError` naming the key."""
    check_declared(c, "camera")
    if c.ptc_frames == 1:
        raise ConfigError("camera.ptc_frames: expected 0 (no ladder) or at least 2 frames per exposure (a pair), got 1")
    if c.dark_level >= 2 ** int(c.bit_depth) - 1:
        raise ConfigError(f"camera.dark_level: expected a value below the ADC's maximum 2**camera.bit_depth - 1 = "
                          f"{2 ** int(c.bit_depth) - 1} ADU (else every pixel is saturated), got {c.dark_level}")


def validate_rig(r: RigConfig) -> None:
    """Check the ``rig`` section; raise :class:`ConfigError` naming the key."""
    check_declared(r, "rig")
    if r.kind == "serial":
        if r.port is None:
            raise ConfigError("rig.port: required when rig.kind=serial (a device path such as /dev/ttyACM0 or a pyserial "
                              "URL such as socket://127.0.0.1:5000; the emulator prints it as 'serial')")
        if r.frames is None:
            raise ConfigError("rig.frames: required when rig.kind=serial (tcp://HOST:PORT of the emulator's camera, "
                              "or package.module:ClassName of an SDKCamera)")
    if r.frames is not None:
        f = r.frames
        ok = False
        if f.startswith("tcp://"):
            try:
                u = urlparse(f)
                ok = bool(u.hostname) and u.port is not None
            except ValueError:
                ok = False
        elif f.startswith(("pylon://", "aravis://")):  # a Basler or GenICam camera (the pylon, aravis extra): options checked here
            try:
                (pylon_url_options if f.startswith("pylon://") else aravis_url_options)(f)
            except ParameterError as exc:
                raise ConfigError(f"rig.frames: {excerpt(f)}: {str(exc).removeprefix('url: ')}") from None
            ok = True
        else:
            mod, sep, name = f.partition(":")
            ok = bool(sep and mod and name and "/" not in f)
        if not ok:
            raise ConfigError(f"rig.frames: expected tcp://HOST:PORT, pylon://[SERIAL][?trigger=...], aravis://[DEVICE][?...] "
                              f"or package.module:ClassName, got {excerpt(f)}")


def validate_excitation(x: ExcitationConfig) -> None:
    """Check the ``excitation`` section (``tones`` at most 15: with the base tone, the protocol's
    16); raise :class:`ConfigError` naming the key."""
    check_declared(x, "excitation")
    if x.snap_tol >= 0.5:
        raise ConfigError(f"excitation.snap_tol: expected a value in (0, 0.5), got {x.snap_tol}")


def whole_periods(periods: float) -> bool:
    """Whether an exposure of ``periods`` periods (> 0) is a whole number of them (to 1e-9)."""
    return periods >= 1 - 1e-9 and abs(periods - round(periods)) <= 1e-9 * max(1.0, periods)


def validate_sweep(s: SweepConfig) -> None:
    """Check the ``sweep`` section; raise :class:`ConfigError` naming the key."""
    if s.freq_hz is not None:
        if not isinstance(s.freq_hz, (list, tuple)) or not s.freq_hz:
            raise ConfigError(f"sweep.freq_hz: expected a non-empty list of frequencies, got {excerpt(s.freq_hz)}")
        for i, f in enumerate(s.freq_hz):
            check_number(f, f"sweep.freq_hz[{i}]", positive=True)
    else:
        check_number(s.f_min_hz, "sweep.f_min_hz", positive=True)
        check_number(s.f_max_hz, "sweep.f_max_hz", positive=True)
        check_number(s.n, "sweep.n", integer=True, low=1)
        if s.f_max_hz < s.f_min_hz:
            raise ConfigError(f"sweep.f_max_hz: expected >= sweep.f_min_hz ({s.f_min_hz}), got {s.f_max_hz}")
    if not isinstance(s.exposures, (list, tuple)) or not s.exposures or len(s.exposures) > 16:
        raise ConfigError(f"sweep.exposures: expected a list of 1 to 16 fractions of the period, got {_short(s.exposures)}")
    for i, e in enumerate(s.exposures):
        check_number(e, f"sweep.exposures[{i}]", positive=True)
        if whole_periods(e):
            raise ConfigError(f"sweep.exposures[{i}]: {e:g} is a whole number of periods: such an image does not depend on the "
                              f"phase (PHYSICS.md: the moments' start is undefined there); use a fraction such as 0.3 or 0.8")
    check_declared(s, "sweep")


def validate(cfg: IdentifyConfig) -> None:
    """Check every value, section by section, then the rules between keys; raise
    :class:`ConfigError` naming the key."""
    validate_plant(cfg.plant)
    validate_sweep(cfg.sweep)
    validate_excitation(cfg.excitation)
    validate_camera(cfg.camera)
    validate_spots(cfg.spots, cfg.camera)
    validate_spot_room(cfg)
    validate_drive_limits(cfg)
    validate_exposure_time(cfg)
    validate_fit(cfg)
    validate_model(cfg)
    validate_plan_compatibility(cfg)
    validate_loss_for_plan(cfg)
    validate_rig(cfg.rig)
    validate_report(cfg)
    validate_dm(cfg)
    check_declared(cfg, "")


def _two_axes(cfg: IdentifyConfig) -> str:
    """What makes a run fit both image axes (for a message): a 2x2 plant or many spots."""
    return "a 2x2 plant" if cfg.plant.is_mimo else "many spots (spots.rows > 0)"


def validate_spot_room(cfg: IdentifyConfig) -> None:
    """Many spots: the largest motion, 1.33 ``excitation.target_px``, stays in a spot's crop with
    3 PSF sigmas kept from its edge."""
    if not cfg.spots.enabled:
        return
    sp = cfg.spots
    sigma = sp.sigma_px if sp.sigma_px is not None else cfg.camera.psf_sigma_px
    room = sp.crop_side() / 2 - 3 * float(sigma) * (1 + float(sp.sigma_variation)) * (1 + float(sp.elongation))
    if 1.33 * float(cfg.excitation.target_px) > room:
        raise ConfigError(f"excitation.target_px: a motion of up to 1.33 x {cfg.excitation.target_px} px does not stay in a "
                          f"{sp.crop_side()} px spot crop (room {room:.3g} px from the centre, 3 PSF sigmas kept); "
                          f"lower excitation.target_px or raise spots.pitch_px / spots.crop_px")


def validate_drive_limits(cfg: IdentifyConfig) -> None:
    """``excitation.max_amplitude`` and ``excitation.max_slew`` may only narrow the simulated
    plant's ``plant.input_limit`` and ``plant.slew_limit``, never widen them."""
    x, plant = cfg.excitation, cfg.plant
    if cfg.rig.kind != "simulated":
        return
    if x.max_amplitude is not None and float(x.max_amplitude) > float(plant.input_limit):
        raise ConfigError(f"excitation.max_amplitude: {x.max_amplitude} is beyond the simulated plant's input "
                          f"range plant.input_limit = {plant.input_limit}; it may only narrow the range, not widen it")
    if x.max_slew is not None and plant.slew_limit is not None and float(x.max_slew) > float(plant.slew_limit):
        raise ConfigError(f"excitation.max_slew: {x.max_slew} is beyond the simulated plant's slew limit "
                          f"plant.slew_limit = {plant.slew_limit}; it may only narrow the limit, not widen it")


def validate_exposure_time(cfg: IdentifyConfig) -> None:
    """The longest exposure (the largest fraction of the period at the lowest frequency) within
    ``camera.max_exposure_s``."""
    s = cfg.sweep
    f_min = min(s.freq_hz) if s.freq_hz is not None else s.f_min_hz  # (not the whole list: sweep.n may be huge)
    longest = max(s.exposures) / f_min
    if longest > cfg.camera.max_exposure_s:
        raise ConfigError(f"sweep.exposures: the longest exposure ({max(s.exposures)} of the period at {f_min:g} Hz = "
                          f"{longest:g} s) exceeds camera.max_exposure_s = {cfg.camera.max_exposure_s:g} s")


def validate_fit(cfg: IdentifyConfig) -> None:
    """The ``fit`` section: its declared keys, ``fit.axis`` (a mode or a direction; one-axis,
    one-spot runs only) and ``fit.loss`` a likelihood of the camera's noise."""
    check_declared(cfg.fit, "fit")
    validate_device(cfg)
    if isinstance(cfg.fit.axis, str):
        if cfg.fit.axis not in AXIS_MODES:
            raise ConfigError(f"fit.axis: expected one of {AXIS_MODES} or a direction [x, y], got {excerpt(cfg.fit.axis)}")
    else:
        _pair(cfg.fit.axis, "fit.axis", f"one of {AXIS_MODES} or a direction [x, y]")
    if cfg.fit.axis != "measure" and (cfg.plant.is_mimo or cfg.spots.enabled):
        raise ConfigError(f"fit.axis: applies to one-axis, one-spot runs; this run has {_two_axes(cfg)}, which fits both image axes")
    if cfg.fit.loss not in LIKELIHOOD_LOSSES:
        raise ConfigError(f"fit.loss: {excerpt(cfg.fit.loss)} is refused for an identification: it is no likelihood of the camera's noise, so its "
                          f"fit has no covariance and the response's stds would not hold; use one of {LIKELIHOOD_LOSSES} (l2, the default; "
                          f"l1 to be robust to outlier pixels, at 1.25x the std; poisson, the camera's shot and read noise exactly). "
                          f"fit_sinusoid(..., loss='linf', optimizer='adam' or 'lbfgs') still fits it outside a run")


def validate_device(cfg: IdentifyConfig) -> None:
    """``fit.device``: a torch device that is here (cpu always; cuda or cuda:N with that GPU; mps
    where available), other than cpu only for a DM run (where its spot fits run)."""
    name = cfg.fit.device
    try:
        dev = torch.device(name) if isinstance(name, str) else None
    except RuntimeError:
        dev = None
    if dev is None:
        raise ConfigError(f"fit.device: expected a torch device such as cpu, cuda, cuda:1 or mps, got {excerpt(name)}")
    if dev.type == "cpu":
        return
    if not cfg.dm.enabled:
        raise ConfigError(f"fit.device: {name} applies to a DM run's spot fits (dm.n_across > 0); a sine or multisine run fits "
                          f"on the CPU: set fit.device=cpu")
    if dev.type == "cuda":
        here = torch.cuda.is_available() and (dev.index or 0) < torch.cuda.device_count()
    else:
        here = dev.type == "mps" and torch.backends.mps.is_available()
    if not here:
        raise ConfigError(f"fit.device: {name} is not available on this machine (torch sees {torch.cuda.device_count()} CUDA "
                          f"device(s)); set fit.device=cpu")


def validate_model(cfg: IdentifyConfig) -> None:
    """The ``model`` section: its declared keys, and at most as many zeros as poles."""
    m = cfg.model
    check_declared(m, "model")
    if m.n_zeros is not None and m.n_poles is not None and m.n_zeros > m.n_poles:
        raise ConfigError(f"model.n_zeros: expected at most model.n_poles = {m.n_poles} (a proper model), got {m.n_zeros}")


def validate_plan_compatibility(cfg: IdentifyConfig) -> None:
    """A multisine excitation and the direct model each drive one axis and fit one spot; the
    direct model fits a sine sweep's images."""
    two_axes = cfg.plant.is_mimo or cfg.spots.enabled
    if cfg.excitation.kind == "multisine" and two_axes:
        raise ConfigError(f"excitation.kind: a multisine excitation drives one axis and fits one spot; this run has "
                          f"{_two_axes(cfg)}: use excitation.kind=sine")
    if cfg.model.direct and cfg.excitation.kind == "multisine":
        raise ConfigError("model.direct: the direct fit works on a sine sweep's images; set excitation.kind=sine or model.direct=false")
    if cfg.model.direct and two_axes:
        raise ConfigError(f"model.direct: the direct fit handles one axis and one spot; this run has {_two_axes(cfg)}: "
                          f"set model.direct=false")


def validate_loss_for_plan(cfg: IdentifyConfig) -> None:
    """``fit.loss`` other than l2 with ``excitation.kind=multisine``: refused. The multisine fit
    (and the direct model) is a weighted least squares only; nothing else of a multisine run
    uses ``fit.loss``, so l1 or poisson would be ignored without a word."""
    if cfg.excitation.kind == "multisine" and cfg.fit.loss != "l2":
        raise ConfigError(f"fit.loss: {excerpt(cfg.fit.loss)} is not applied by the multisine plan (excitation.kind=multisine): its fit "
                          f"is a least squares weighted by the camera's noise model (l2) only; set fit.loss=l2, or "
                          f"excitation.kind=sine to fit with {cfg.fit.loss}")


def validate_report(cfg: IdentifyConfig) -> None:
    """The ``report`` section's declared keys (tolerances > 0, ``figures`` true or false)."""
    check_declared(cfg.report, "report")
