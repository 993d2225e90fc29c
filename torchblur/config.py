"""Configuration of ``torchblur identify``: frozen dataclasses loaded with OmegaConf.

A YAML file (``--config FILE``) and dotted overrides (``plant.num=[1,2]``) are merged onto
the built-in defaults; unknown keys and invalid values raise :class:`ConfigError` naming
the key, before any work starts. Units: Hz and seconds as the names say; the plant's
``num``/``den`` are continuous-time coefficients (highest power first) with the output in
pixels per input unit.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Optional

from .errors import ConfigError

__all__ = ["IdentifyConfig", "load_config", "load_dataclass", "config_to_yaml", "validate", "validate_plant", "validate_camera",
           "validate_excitation", "DEFAULT_PLANT", "RIG_KINDS", "EXCITATION_KINDS"]

RIG_KINDS = ("simulated", "serial")


def _default_plant() -> tuple[list, list]:
    """One axis of a tip-tilt fast steering mirror under closed-loop control: a lightly
    damped resonance at 420 Hz, a current-loop pole at 2.5 kHz, 20 px per input unit."""
    wn, zeta, wp, gain = 2 * math.pi * 420.0, 0.12, 2 * math.pi * 2500.0, 20.0
    num = [gain * wn * wn * wp]
    den = [1.0, 2 * zeta * wn + wp, wn * wn + 2 * zeta * wn * wp, wn * wn * wp]
    return num, den


DEFAULT_PLANT = _default_plant()


@dataclass(frozen=True)
class PlantConfig:
    num: list = field(default_factory=lambda: list(DEFAULT_PLANT[0]))
    den: list = field(default_factory=lambda: list(DEFAULT_PLANT[1]))
    delay_s: float = 30e-6


@dataclass(frozen=True)
class SweepConfig:
    f_min_hz: float = 1.0
    f_max_hz: float = 1000.0
    n: int = 30
    freq_hz: Optional[list] = None
    exposures: list = field(default_factory=lambda: [0.3, 0.8])
    trigger_phase_rad: float = math.pi / 2
    images_per_point: int = 2
    settle_s: Optional[float] = None


EXCITATION_KINDS = ("sine", "multisine")


@dataclass(frozen=True)
class ExcitationConfig:
    target_px: float = 8.0
    max_amplitude: Optional[float] = None
    # "sine": one frequency per point (the sweep); "multisine": the sweep's frequencies in groups of `tones`, each group
    # one multisine on a common grid with one designed image set (torchblur.identify_multisine).
    kind: str = "sine"
    tones: int = 3
    tone_px: Optional[float] = None  # multisine: output amplitude of each tone (px); default 0.75 target_px
    images: Optional[int] = None  # multisine: images per group; None: the design's size for target_std
    max_images: int = 12  # multisine: most images per group when `images` is None
    target_std: float = 2e-3  # multisine: predicted std of every |H| (relative) and phase (rad) the design aims at
    snap_tol: float = 0.05  # multisine: largest relative move of a frequency onto the group's common grid


@dataclass(frozen=True)
class CameraConfig:
    frame_rate_hz: float = 30.0
    max_exposure_s: float = 1.0
    readout_s: float = 1e-3
    trigger_delay_s: float = 0.0
    latency_s: float = 12e-6
    jitter_s: float = 0.2e-6
    read_noise: float = 5.0
    gain: float = 1.0
    full_well: float = 20000.0
    bit_depth: int = 12
    dark_level: float = 100.0
    psf_sigma_px: float = 2.0
    height: int = 64
    width: int = 64
    peak_fraction: float = 0.5


@dataclass(frozen=True)
class FitConfig:
    optimizer: str = "lm"
    loss: str = "l2"
    fit_scale: bool = True
    fit_background: bool = False
    # Points per batched fit. The sweep hands every completed chunk to a background fit, so
    # fitting overlaps the acquisition; 0 fits all points in one batch after the sweep.
    chunk_points: int = 8


@dataclass(frozen=True)
class ModelConfig:
    n_poles: Optional[int] = None
    n_zeros: Optional[int] = None
    max_order: int = 6
    fit_delay: bool = True


@dataclass(frozen=True)
class RigConfig:
    kind: str = "simulated"  # "simulated" (built-in) or "serial" (a controller on rig.port, a camera on rig.frames)
    port: Optional[str] = None  # serial: device path or pyserial URL (socket://HOST:PORT, spy://PATH?file=LOG)
    frames: Optional[str] = None  # serial: tcp://HOST:PORT (emulator) or package.module:ClassName (SDKCamera)
    timeout_s: float = 2.0  # serial: reply timeout
    retries: int = 2  # serial: how many times a failed point is redone


@dataclass(frozen=True)
class IdentifyConfig:
    plant: PlantConfig = field(default_factory=PlantConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    seed: int = 0

    def frequencies_hz(self) -> list[float]:
        """The sweep's frequencies (Hz), increasing."""
        s = self.sweep
        if s.freq_hz is not None:
            return sorted(float(f) for f in s.freq_hz)
        if s.n == 1:
            return [float(s.f_min_hz)]
        r = (s.f_max_hz / s.f_min_hz) ** (1 / (s.n - 1))
        return [float(s.f_min_hz * r**k) for k in range(s.n)]


def _from_dict(cls, data: dict, prefix: str = ""):
    kwargs = {}
    names = {f.name: f for f in fields(cls)}
    for k, v in data.items():
        if k not in names:
            raise ConfigError(f"{prefix}{k}: unknown config key (known: {', '.join(prefix + n for n in names)})")
        default = names[k].default_factory() if names[k].default_factory is not field().default_factory else None  # type: ignore[misc]
        if is_dataclass(default):
            if not isinstance(v, dict):
                raise ConfigError(f"{prefix}{k}: expected a section (mapping), got {v!r}")
            kwargs[k] = _from_dict(type(default), v, prefix + k + ".")
        else:
            kwargs[k] = v
    return cls(**kwargs)


def load_config(path: str | None = None, overrides: list[str] | None = None) -> IdentifyConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides; validated.

    Raises:
        ConfigError: naming the key, for unknown keys, unparsable values or invalid values.
    """
    cfg = load_dataclass(IdentifyConfig, path, overrides)
    validate(cfg)
    return cfg


def load_dataclass(cls, path: str | None = None, overrides: list[str] | None = None, *, ignore_file_sections=()):
    """Defaults of the frozen dataclass ``cls``, then the YAML file (its top-level sections in
    ``ignore_file_sections`` skipped), then ``key=value`` overrides; not validated.

    Raises:
        ConfigError: naming the key, for unknown keys and unparsable values.
    """
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    merged = OmegaConf.create(asdict(cls()))
    OmegaConf.set_struct(merged, True)
    try:
        if path is not None:
            try:
                file_cfg = OmegaConf.load(path)
            except FileNotFoundError:
                raise ConfigError(f"--config: file not found: {path}") from None
            for k in ignore_file_sections:
                if k in file_cfg:
                    file_cfg.pop(k)
            merged = OmegaConf.merge(merged, file_cfg)
        if overrides:
            for item in overrides:
                if "=" not in item:
                    raise ConfigError(f"{item}: expected key=value")
            merged = OmegaConf.merge(merged, OmegaConf.from_dotlist(list(overrides)))
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or getattr(exc, "key", None) or "config"
        raise ConfigError(f"{key}: {str(exc).splitlines()[0]}") from None
    data = OmegaConf.to_container(merged, resolve=True)
    return _from_dict(cls, data)


def config_to_yaml(cfg: IdentifyConfig) -> str:
    from omegaconf import OmegaConf

    return OmegaConf.to_yaml(OmegaConf.create(asdict(cfg)))


def _num(value, key, *, positive=False, nonnegative=False, integer=False, low=None, high=None):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key}: expected a number, got {value!r}")
    if integer and int(value) != value:
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{key}: expected a finite number, got {value!r}")
    if positive and v <= 0:
        raise ConfigError(f"{key}: expected a value > 0, got {value!r}")
    if nonnegative and v < 0:
        raise ConfigError(f"{key}: expected a value >= 0, got {value!r}")
    if low is not None and v < low:
        raise ConfigError(f"{key}: expected a value >= {low}, got {value!r}")
    if high is not None and v > high:
        raise ConfigError(f"{key}: expected a value <= {high}, got {value!r}")
    return v


def _coeffs(value, key) -> list[float]:
    if not isinstance(value, (list, tuple)) or not value:
        raise ConfigError(f"{key}: expected a non-empty list of coefficients (highest power first), got {value!r}")
    return [_num(v, f"{key}[{i}]") for i, v in enumerate(value)]


def validate_plant(plant: PlantConfig) -> None:
    """Check the ``plant`` section; raise :class:`ConfigError` naming the key."""
    import numpy as np

    num = _coeffs(plant.num, "plant.num")
    den = _coeffs(plant.den, "plant.den")
    while len(num) > 1 and num[0] == 0:
        num = num[1:]
    if den[0] == 0:
        raise ConfigError("plant.den: the leading coefficient must be non-zero")
    if len(num) > len(den):
        raise ConfigError(f"plant.num: the plant must be proper (degree of num {len(num) - 1} > degree of den {len(den) - 1})")
    poles = np.roots(den)
    if len(poles) and (poles.real >= 0).any():
        raise ConfigError(f"plant.den: the plant must be stable; poles with real part >= 0: {poles[poles.real >= 0]}")
    _num(plant.delay_s, "plant.delay_s", nonnegative=True)


def validate_camera(c: CameraConfig) -> None:
    """Check the ``camera`` section; raise :class:`ConfigError` naming the key."""
    for k in ("frame_rate_hz", "max_exposure_s", "gain", "full_well", "psf_sigma_px", "peak_fraction"):
        _num(getattr(c, k), f"camera.{k}", positive=True)
    for k in ("readout_s", "trigger_delay_s", "latency_s", "jitter_s", "read_noise", "dark_level"):
        _num(getattr(c, k), f"camera.{k}", nonnegative=True)
    _num(c.bit_depth, "camera.bit_depth", integer=True, low=1, high=32)
    _num(c.height, "camera.height", integer=True, low=8)
    _num(c.width, "camera.width", integer=True, low=8)
    if c.peak_fraction > 1:
        raise ConfigError(f"camera.peak_fraction: expected a value in (0, 1], got {c.peak_fraction}")


def validate_rig(r: RigConfig) -> None:
    """Check the ``rig`` section; raise :class:`ConfigError` naming the key."""
    if r.kind not in RIG_KINDS:
        raise ConfigError(f"rig.kind: expected one of {RIG_KINDS}, got {r.kind!r}")
    for k in ("port", "frames"):
        v = getattr(r, k)
        if v is not None and (not isinstance(v, str) or not v.strip()):
            raise ConfigError(f"rig.{k}: expected a non-empty string, got {v!r}")
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
            from urllib.parse import urlparse

            try:
                u = urlparse(f)
                ok = bool(u.hostname) and u.port is not None
            except ValueError:
                ok = False
        else:
            mod, sep, name = f.partition(":")
            ok = bool(sep and mod and name and "/" not in f)
        if not ok:
            raise ConfigError(f"rig.frames: expected tcp://HOST:PORT or package.module:ClassName, got {f!r}")
    _num(r.timeout_s, "rig.timeout_s", positive=True)
    _num(r.retries, "rig.retries", integer=True, low=0, high=100)


def validate_excitation(x: ExcitationConfig) -> None:
    """Check the multisine keys of the ``excitation`` section; raise :class:`ConfigError` naming the key."""
    if x.kind not in EXCITATION_KINDS:
        raise ConfigError(f"excitation.kind: expected one of {EXCITATION_KINDS}, got {x.kind!r}")
    _num(x.tones, "excitation.tones", integer=True, low=1, high=15)  # 15 + the base tone = the protocol's 16
    if x.tone_px is not None:
        _num(x.tone_px, "excitation.tone_px", positive=True)
    _num(x.max_images, "excitation.max_images", integer=True, low=2, high=1000)
    if x.images is not None:
        _num(x.images, "excitation.images", integer=True, low=2, high=1000)
    _num(x.target_std, "excitation.target_std", positive=True)
    _num(x.snap_tol, "excitation.snap_tol", positive=True)
    if x.snap_tol >= 0.5:
        raise ConfigError(f"excitation.snap_tol: expected a value in (0, 0.5), got {x.snap_tol}")


def validate(cfg: IdentifyConfig) -> None:
    """Check every value; raise :class:`ConfigError` naming the key."""
    validate_plant(cfg.plant)
    s = cfg.sweep
    if s.freq_hz is not None:
        if not isinstance(s.freq_hz, (list, tuple)) or not s.freq_hz:
            raise ConfigError(f"sweep.freq_hz: expected a non-empty list of frequencies, got {s.freq_hz!r}")
        for i, f in enumerate(s.freq_hz):
            _num(f, f"sweep.freq_hz[{i}]", positive=True)
    else:
        _num(s.f_min_hz, "sweep.f_min_hz", positive=True)
        _num(s.f_max_hz, "sweep.f_max_hz", positive=True)
        _num(s.n, "sweep.n", integer=True, low=1)
        if s.f_max_hz < s.f_min_hz:
            raise ConfigError(f"sweep.f_max_hz: expected >= sweep.f_min_hz ({s.f_min_hz}), got {s.f_max_hz}")
    if not isinstance(s.exposures, (list, tuple)) or not s.exposures:
        raise ConfigError(f"sweep.exposures: expected a non-empty list of fractions of the period, got {s.exposures!r}")
    for i, e in enumerate(s.exposures):
        _num(e, f"sweep.exposures[{i}]", positive=True)
    _num(s.trigger_phase_rad, "sweep.trigger_phase_rad")
    _num(s.images_per_point, "sweep.images_per_point", integer=True, low=1)
    if s.settle_s is not None:
        _num(s.settle_s, "sweep.settle_s", nonnegative=True)
    _num(cfg.excitation.target_px, "excitation.target_px", positive=True)
    if cfg.excitation.max_amplitude is not None:
        _num(cfg.excitation.max_amplitude, "excitation.max_amplitude", positive=True)
    validate_excitation(cfg.excitation)
    c = cfg.camera
    validate_camera(c)
    f_min = min(cfg.frequencies_hz())
    longest = max(s.exposures) / f_min
    if longest > c.max_exposure_s:
        raise ConfigError(f"sweep.exposures: the longest exposure ({max(s.exposures)} of the period at {f_min:g} Hz = "
                          f"{longest:g} s) exceeds camera.max_exposure_s = {c.max_exposure_s:g} s")
    from .fit import OPTIMIZERS
    from .losses import LOSSES

    if cfg.fit.optimizer not in OPTIMIZERS:
        raise ConfigError(f"fit.optimizer: expected one of {OPTIMIZERS}, got {cfg.fit.optimizer!r}")
    if cfg.fit.loss not in LOSSES:
        raise ConfigError(f"fit.loss: expected one of {LOSSES}, got {cfg.fit.loss!r}")
    for k in ("n_poles", "n_zeros"):
        v = getattr(cfg.model, k)
        if v is not None:
            _num(v, f"model.{k}", integer=True, low=0)
    _num(cfg.fit.chunk_points, "fit.chunk_points", integer=True, low=0)
    _num(cfg.model.max_order, "model.max_order", integer=True, low=1, high=16)
    validate_rig(cfg.rig)
    _num(cfg.seed, "seed", integer=True, low=0)

