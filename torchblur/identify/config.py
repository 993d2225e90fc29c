"""Configuration of ``torchblur identify``: frozen dataclasses loaded with OmegaConf.

A YAML file (``--config FILE``) and dotted overrides (``plant.num=[1,2]``) are merged onto
the built-in defaults; unknown keys and invalid values raise :class:`ConfigError` naming
the key, before any work starts. Units: Hz and seconds as the names say; the plant's
``num``/``den`` are continuous-time coefficients (highest power first) with the output in
pixels per input unit.
"""
from __future__ import annotations

import io
import re
import math
import os
from dataclasses import asdict, dataclass, field, fields, is_dataclass
from typing import Optional

from torchblur.errors import ConfigError
from torchblur.files import excerpt, key_excerpt, read_bounded

__all__ = ["IdentifyConfig", "load_config", "estimate_run", "check_limits", "check_dm_bounds", "dm_size_bounds", "LIMITS", "load_dataclass", "config_to_yaml", "validate", "validate_plant", "validate_camera",
           "validate_spots", "validate_excitation", "validate_dm", "validate_dm_model", "SpotsConfig", "PlantConfig",
           "DMConfig", "DMRegistrationConfig", "WFSConfig", "DMPlanConfig", "DM_PLAN_KINDS",
           "DEFAULT_PLANT", "RIG_KINDS", "EXCITATION_KINDS"]

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
    """The simulated mirror. SISO: ``num``/``den`` flat coefficient lists (highest power
    first), ``delay_s`` a number. A two-axis tip-tilt mirror (MIMO): ``num``/``den`` 2x2
    nested lists, ``num[i][j]`` the channel from input j to output i (i, j in x, y), and
    ``delay_s`` one number (shared) or a 2x2 nested list; the run then excites each input in
    turn and identifies the 2x2 response. ``direction`` (SISO): the simulated spot's image
    motion (x, y) px per plant output unit, e.g. ``[0.985, 0.174]`` for an actuator axis
    rotated 10 degrees in the camera's image. ``input_limit``: the simulated amplifier's input
    range, the largest |command| (input units, every input) it takes; a command beyond it is
    refused, and every plan keeps within it (``excitation.max_amplitude`` may only narrow it).
    ``slew_limit``: its slew-rate limit (input units per second; None: none), kept the same way
    (``excitation.max_slew`` may only narrow it)."""

    num: list = field(default_factory=lambda: list(DEFAULT_PLANT[0]))
    den: list = field(default_factory=lambda: list(DEFAULT_PLANT[1]))
    delay_s: object = 30e-6
    direction: list = field(default_factory=lambda: [1.0, 0.0])
    input_limit: float = 200.0  # = torchblur.rig.simulated.DEFAULT_INPUT_LIMIT: 8 px at 5 kHz on the default mirror takes ~126
    # The simulated amplifier's slew-rate limit, input units per second (|d command / dt|, a sine's amplitude * omega:
    # the current limit of a piezo amplifier, its full range only up to slew_limit / (2 pi input_limit) Hz); null: none.
    slew_limit: Optional[float] = None

    @property
    def is_mimo(self) -> bool:
        """True when ``num`` is nested (a 2x2 plant)."""
        return _nested(self.num)


@dataclass(frozen=True)
class SpotsConfig:
    """Many spots (a Shack-Hartmann sensor, see :mod:`torchblur.image.spots`). ``rows`` = 0 (the
    default): one spot, as without this section."""

    rows: int = 0
    cols: int = 0
    pitch_px: float = 32.0
    center_px: Optional[list] = None  # grid centre (x, y) px; null: the frame centre
    sigma_px: Optional[float] = None  # PSF std at the grid centre; null: camera.psf_sigma_px
    sigma_variation: float = 0.0
    elongation: float = 0.0
    gain_variation: float = 0.0
    rotation_rad: float = 0.0
    missing: list = field(default_factory=list)  # row-major indices of absent spots (simulation)
    crop_px: Optional[int] = None  # side of each spot's crop; null: floor(pitch_px)

    @property
    def enabled(self) -> bool:
        return int(self.rows) > 0

    def grid(self, camera=None):
        """The :class:`~torchblur.image.spots.SpotGrid` of this section (None when disabled)."""
        if not self.enabled:
            return None
        from torchblur.image.spots import SpotGrid

        sigma = self.sigma_px if self.sigma_px is not None else (camera.psf_sigma_px if camera is not None else 2.0)
        return SpotGrid(rows=int(self.rows), cols=int(self.cols), pitch_px=float(self.pitch_px),
                        center_px=None if self.center_px is None else tuple(float(v) for v in self.center_px),
                        sigma_px=float(sigma), sigma_variation=float(self.sigma_variation), elongation=float(self.elongation),
                        gain_variation=float(self.gain_variation), rotation_rad=float(self.rotation_rad),
                        missing=tuple(int(m) for m in self.missing))

    def crop_side(self) -> int:
        """Side (px) of each spot's crop."""
        return int(self.crop_px) if self.crop_px is not None else int(math.floor(float(self.pitch_px)))


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
    max_slew: Optional[float] = None  # input units/s: narrows the rig's slew limit (plant.slew_limit, SLEW?); never widens it
    # "sine": one frequency per point (the sweep); "multisine": the sweep's frequencies in groups of `tones`, each group
    # one multisine on a common grid with one designed image set (torchblur.identify.multisine).
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
    # The trigger-to-exposure latency: the simulated camera's (its truth); with latency_std_s set, also the
    # run's, given instead of scanned with laser pulses (a rig without pulse(): a camera whose latency is known).
    latency_s: float = 12e-6
    latency_std_s: Optional[float] = None
    jitter_s: float = 0.2e-6
    read_noise: float = 5.0
    gain: float = 1.0
    # Which gain the run uses (torchblur.identify.calibration.choose_gain): "auto" (default): the photon transfer
    # curve's (of the still frames, and of a ladder with ptc_frames) where it is within 1 % or camera.gain lies beyond
    # 3 of its stds, else camera.gain; "measure": always the measured one; "config": camera.gain (a warning beyond 3 stds).
    gain_from: str = "auto"
    ptc_frames: int = 0  # frames per exposure of a photon transfer ladder (8 exposures) for a precise gain; 0: none
    full_well: float = 20000.0
    bit_depth: int = 12
    dark_level: float = 100.0
    psf_sigma_px: float = 2.0
    height: int = 64
    width: int = 64
    peak_fraction: float = 0.5


AXIS_MODES = ("measure", "x", "y")
GAIN_FROM = ("auto", "measure", "config")


@dataclass(frozen=True)
class FitConfig:
    # One-axis, one-spot runs: the image direction of the actuator's motion. "measure" (default): tracked
    # during the calibration (torchblur.image.tracking.calibrate_axes at the sweep's first frequency); "x", "y",
    # or [x, y]. The response is the motion along that direction (the sign that points toward +x, or +y).
    axis: object = "measure"
    # The PSF every fit of the run uses (torchblur.image.psf_from_still on the still frames; per spot with
    # many spots). "auto" (default): the point-sampled Gaussian where it explains the averaged still to its
    # noise, else the measured kernel (many spots: the kernels of every spot when any spot's Gaussian fails);
    # "kernel" or "gaussian" forces one. The same on every route: sine sweep, multisine, direct model, many
    # spots (the DM command fits Gaussians: issue 23).
    psf: str = "auto"
    optimizer: str = "lm"
    loss: str = "l2"  # "l2", "l1" or "poisson", each weighted by the calibrated camera noise (linf: refused, no likelihood)
    fit_scale: bool = True
    fit_background: bool = False
    fit_gradient: bool = False  # remove a stray-light plane per exposure (fit_sinusoid's fit_gradient)
    outliers: str = "none"  # "reject": mask pixels whose residual exceeds outlier_sigma std (hot pixels, cosmic rays) and refit
    outlier_sigma: float = 5.0
    # Points per batched fit. The sweep hands every completed chunk to a background fit, so
    # fitting overlaps the acquisition; 0 fits all points in one batch after the sweep.
    chunk_points: int = 8
    # A point whose image fit has a reduced chi2 above this is flagged poor_fit: its stds are multiplied by
    # sqrt(reduced chi2) and it is left out of the transfer-function fit (docs/reliability.md, "Per-point flags").
    poor_fit_chi2: float = 1.5


@dataclass(frozen=True)
class ModelConfig:
    n_poles: Optional[int] = None
    n_zeros: Optional[int] = None
    max_order: int = 6
    fit_delay: bool = True
    # Direct identification (torchblur.sysid.direct): after the two-step model, fit its parameters
    # to every image at once; model.json then holds the direct model, model_two_step.json the other.
    direct: bool = False
    direct_form: str = "tf"  # "tf" (normalised poles/zeros) or "modal" (sum of modes)
    direct_max_iter: int = 100


@dataclass(frozen=True)
class ReportConfig:
    # The run's tolerance: the report states the frequency above which the timing terms alone (trigger jitter
    # per frame, averaged, and the latency's std) exceed tolerance_deg of phase, and flags those points timing.
    tolerance_deg: float = 1.0
    tolerance_rel: float = 0.01  # |H| relative: the report counts the points whose |H| std is within it
    # false: no figures (bode.png, residuals.png, ptc.png, dm/actuator_maps.png; benchmarks/bench_figures.py: their cost);
    # every number file (frf.*, model.json, report.txt, dm/*.csv/.npy/.json) is written as before.
    figures: bool = True


@dataclass(frozen=True)
class RigConfig:
    kind: str = "simulated"  # "simulated" (built-in) or "serial" (a controller on rig.port, a camera on rig.frames)
    port: Optional[str] = None  # serial: device path or pyserial URL (socket://HOST:PORT, spy://PATH?file=LOG)
    frames: Optional[str] = None  # serial: tcp://HOST:PORT (emulator) or package.module:ClassName (SDKCamera)
    timeout_s: float = 2.0  # serial: reply timeout
    retries: int = 2  # serial: how many times a failed point is redone


@dataclass(frozen=True)
class DMRegistrationConfig:
    """The SIMULATED mirror's registration on its sensor (:class:`torchblur.dm.registration.Registration`):
    ``shift_x``/``shift_y`` (actuator pitches), ``rotation_deg``, ``magnification`` and the true
    ``coupling`` (null: ``dm.coupling``). The run does not read it: it fits the registration to
    the measured D0 (a real mirror's is whatever it is)."""

    shift_x: float = 0.0
    shift_y: float = 0.0
    rotation_deg: float = 0.0
    magnification: float = 1.0
    coupling: Optional[float] = None


@dataclass(frozen=True)
class DMConfig:
    """A deformable mirror (:mod:`torchblur.dm.mirror`); the run is a DM run when ``n_across`` > 0.
    ``coupling``: an influence function's value one pitch away; ``mode_hz``, ``damping``,
    ``gain``, ``delay_s``: the nominal actuator; ``*_spread``: relative std (``delay_spread_s``:
    absolute, s) of the seeded spread; ``dead``/``weak``: actuator indices (weak: ``weak_gain``
    times the gain); ``actuator_table``: a CSV ``actuator,mode_hz,damping,gain,delay_s`` (path
    relative to the working directory) that sets those actuators; ``input_limit``: the largest
    command (null: none)."""

    n_across: int = 0
    coupling: float = 0.15
    mode_hz: float = 1000.0
    damping: float = 0.1
    gain: float = 1.0
    delay_s: float = 20e-6
    mode_spread: float = 0.0
    damping_spread: float = 0.0
    gain_spread: float = 0.0
    delay_spread_s: float = 0.0
    dead: list = field(default_factory=list)
    weak: list = field(default_factory=list)
    weak_gain: float = 0.3
    actuator_table: Optional[str] = None
    input_limit: Optional[float] = None
    registration: DMRegistrationConfig = field(default_factory=DMRegistrationConfig)

    @property
    def enabled(self) -> bool:
        """True for a DM run (``n_across`` > 0)."""
        return int(self.n_across) > 0


@dataclass(frozen=True)
class WFSConfig:
    """The Shack-Hartmann sensor of a DM run (:mod:`torchblur.dm.shack_hartmann`): ``n_across``
    subapertures across the pupil, ``pitch_px`` between spots, ``sigma_px`` PSF std (growing by
    ``sigma_variation`` to the pupil edge), ``slope_px`` px per unit wavefront slope,
    ``min_illumination`` of a valid subaperture, ``oversample`` integration points per side.
    The camera frame is ``n_across * pitch_px`` square (camera.height/width are not used)."""

    n_across: int = 10
    pitch_px: float = 16.0
    sigma_px: float = 1.5
    sigma_variation: float = 0.0
    slope_px: float = 1.0
    min_illumination: float = 0.5
    oversample: int = 32


@dataclass(frozen=True)
class DMPlanConfig:
    """The excitation plan of a DM run (:mod:`torchblur.dm.plans`): ``kind`` one of auto,
    one_at_a_time, sparse, hadamard; ``budget_frames`` the most sweep frames (the repeats per
    exposure are the most that fit, unless ``n_repeats`` is set); ``support_threshold``: the
    sparse plan's |G| threshold relative to the largest."""

    kind: str = "auto"
    budget_frames: Optional[int] = 20000
    n_repeats: Optional[int] = None
    support_threshold: float = 0.01


@dataclass(frozen=True)
class IdentifyConfig:
    plant: PlantConfig = field(default_factory=PlantConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    excitation: ExcitationConfig = field(default_factory=ExcitationConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    spots: SpotsConfig = field(default_factory=SpotsConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    dm: DMConfig = field(default_factory=DMConfig)
    wfs: WFSConfig = field(default_factory=WFSConfig)
    dm_plan: DMPlanConfig = field(default_factory=DMPlanConfig)
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
            raise ConfigError(f"{key_excerpt(prefix + str(k))}: unknown config key (known: {', '.join(prefix + n for n in names)})")
        default = names[k].default_factory() if names[k].default_factory is not field().default_factory else None  # type: ignore[misc]
        if is_dataclass(default):
            if not isinstance(v, dict):
                raise ConfigError(f"{prefix}{k}: expected a section (mapping), got {excerpt(v)}")
            kwargs[k] = _from_dict(type(default), v, prefix + k + ".")
        elif names[k].type in ("int", "Optional[int]") and isinstance(v, float) and v.is_integer() and abs(v) < 2**53:
            kwargs[k] = int(v)  # 1e3 written for an integer key: the integer it is
        else:
            kwargs[k] = v
    return cls(**kwargs)


def load_config(path: str | None = None, overrides: list[str] | None = None, *, trusted: bool = True,
                force: bool = False) -> IdentifyConfig:
    """Defaults, then the YAML file, then ``key=value`` overrides; validated, and the run's
    size checked against :data:`LIMITS` (:func:`estimate_run`) unless ``force``.

    ``trusted=False`` for a file from a recording: no interpolation (``${...}``) is allowed
    in it, so nothing outside the recording (an environment variable) is read.

    Raises:
        ConfigError: naming the key, for unknown keys, unparsable values, invalid values, or
            a run beyond the limits (with the estimate).
    """
    cfg = load_dataclass(IdentifyConfig, path, overrides, trusted=trusted)
    validate(cfg)
    if not force:
        check_limits(cfg)
    return cfg


MAX_CONFIG_BYTES = 1 << 20
MAX_LIST_ENTRIES = 1000


def _load_file(path: str, *, trusted: bool):
    """The OmegaConf of a YAML file: at most :data:`MAX_CONFIG_BYTES`, aliases expanded to
    at most OmegaConf's node limit (a YAML bomb or a recursive alias is refused), and, when
    not ``trusted``, no interpolation anywhere.

    Raises:
        ConfigError: naming the file.
    """
    import yaml
    from omegaconf import OmegaConf

    if not os.path.lexists(path):
        raise ConfigError(f"--config: file not found: {path}")
    data = read_bounded(path, MAX_CONFIG_BYTES, f"--config {path}", error=ConfigError)  # the opening rule (torchblur.files)
    try:
        file_cfg = OmegaConf.load(io.StringIO(data.decode("utf-8")))
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise ConfigError(f"--config {path}: not a usable YAML file ({str(exc).splitlines()[0][:120]})") from None
    if not OmegaConf.is_dict(file_cfg):
        raise ConfigError(f"--config {path}: expected a mapping of sections, got a {type(file_cfg).__name__}")
    _check_config_schema(file_cfg, path)
    if not trusted:
        _refuse_interpolation(OmegaConf.to_container(file_cfg, resolve=False), path)
    return file_cfg


def _refuse_interpolation(value, path: str, key: str = "") -> None:
    if isinstance(value, str) and "${" in value:
        raise ConfigError(f"{key or 'config'}: an interpolation ({excerpt(value[:60])}) in the recorded {path}; a recording's "
                          f"config is read literally, refused")
    if isinstance(value, dict):
        for k, v in value.items():
            _refuse_interpolation(v, path, f"{key}.{k}" if key else str(k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _refuse_interpolation(v, path, f"{key}[{i}]")


def _check_sizes(value, key: str = "") -> None:
    """Every list at most :data:`MAX_LIST_ENTRIES` long, nesting at most 8 deep."""
    if key.count(".") + key.count("[") > 8:
        raise ConfigError(f"{key}: nested more than 8 levels deep")
    if isinstance(value, list):
        if len(value) > MAX_LIST_ENTRIES:
            raise ConfigError(f"{key}: {len(value)} entries, more than {MAX_LIST_ENTRIES}")
        for i, v in enumerate(value):
            _check_sizes(v, f"{key}[{i}]")
    elif isinstance(value, dict):
        for k, v in value.items():
            _check_sizes(v, f"{key}.{k}" if key else str(k))


def load_dataclass(cls, path: str | None = None, overrides: list[str] | None = None, *, ignore_file_sections=(),
                   trusted: bool = True):
    """Defaults of the frozen dataclass ``cls``, then the YAML file (its top-level sections in
    ``ignore_file_sections`` skipped; ``trusted=False``: no interpolation in it), then
    ``key=value`` overrides; not validated.

    Raises:
        ConfigError: naming the key, for unknown keys and unparsable values.
    """
    import yaml
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    merged = OmegaConf.create(asdict(cls()))
    OmegaConf.set_struct(merged, True)
    try:
        if path is not None:
            file_cfg = _load_file(path, trusted=trusted)
            for k in ignore_file_sections:
                if k in file_cfg:
                    file_cfg.pop(k)
            merged = OmegaConf.merge(merged, file_cfg)
        for item in overrides or ():
            if "=" not in item:
                raise ConfigError(f"{item}: expected key=value")
            try:
                merged = OmegaConf.merge(merged, OmegaConf.from_dotlist([item]))
            except (yaml.YAMLError, RecursionError) as exc:
                raise ConfigError(f"{item.partition('=')[0]}: the value cannot be read ({str(exc).splitlines()[0][:100]})") from None
        data = OmegaConf.to_container(merged, resolve=True)
    except OmegaConfBaseException as exc:
        key = getattr(exc, "full_key", None) or getattr(exc, "key", None) or "config"
        raise ConfigError(f"{key_excerpt(key)}: {_clip_quotes(str(exc).splitlines()[0])}") from None
    except (RecursionError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        raise ConfigError(f"config: cannot be read ({type(exc).__name__}: {str(exc).splitlines()[0][:100]})") from None
    _check_sizes(data)
    return _from_dict(cls, data)


def _clip_quotes(text: str) -> str:
    """A third-party message about untrusted content with every quoted part cut to an excerpt."""
    return re.sub(r"'([^']*)'", lambda m: excerpt(m.group(1)), text)[:300]


#: the ``schema`` and ``schema_version`` a run's config.yaml starts with (:func:`config_to_yaml`);
#: versions read. A file without them (a config written by hand, or a run's config.yaml from before
#: they were written) reads as version 1.
CONFIG_SCHEMA = ("torchblur.config", (1,))


def config_to_yaml(cfg: IdentifyConfig) -> str:
    """The YAML of every key of ``cfg`` (a run's config.yaml), headed by ``schema`` and
    ``schema_version`` (:data:`CONFIG_SCHEMA`); :func:`load_config` reads it back."""
    from omegaconf import OmegaConf

    head = f"schema: {CONFIG_SCHEMA[0]}\nschema_version: {CONFIG_SCHEMA[1][-1]}\n"
    return head + OmegaConf.to_yaml(OmegaConf.create(asdict(cfg)))


def _check_config_schema(file_cfg, path: str) -> None:
    """Take ``schema`` / ``schema_version`` out of the loaded file ``file_cfg`` (in place); a
    file without them is version 1. ConfigError naming the key for another schema or a version
    this torchblur does not read (a newer one: say so)."""
    if "schema" not in file_cfg and "schema_version" not in file_cfg:
        return
    name, version = file_cfg.pop("schema", None), file_cfg.pop("schema_version", None)
    if name != CONFIG_SCHEMA[0]:
        raise ConfigError(f"schema: expected {CONFIG_SCHEMA[0]!r} in {path}, got {excerpt(name)}")
    if isinstance(version, bool) or version not in CONFIG_SCHEMA[1]:
        newer = " (written by a newer torchblur: upgrade to read it)" if isinstance(version, int) and version > CONFIG_SCHEMA[1][-1] else ""
        raise ConfigError(f"schema_version: unsupported version {excerpt(version)} in {path}{newer}; supported versions: "
                          f"{list(CONFIG_SCHEMA[1])}")


def _num(value, key, *, positive=False, nonnegative=False, integer=False, low=None, high=None):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key}: expected a number, got {excerpt(value)}")
    if integer and not isinstance(value, int):
        raise ConfigError(f"{key}: expected an integer, got {excerpt(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(f"{key}: expected a finite number, got {excerpt(value)}")
    if positive and v <= 0:
        raise ConfigError(f"{key}: expected a value > 0, got {excerpt(value)}")
    if nonnegative and v < 0:
        raise ConfigError(f"{key}: expected a value >= 0, got {excerpt(value)}")
    if low is not None and v < low:
        raise ConfigError(f"{key}: expected a value >= {low}, got {excerpt(value)}")
    if high is not None and v > high:
        raise ConfigError(f"{key}: expected a value <= {high}, got {excerpt(value)}")
    return v


def _short(value) -> str:
    if isinstance(value, str):
        return excerpt(value)
    r = excerpt(value, 80)
    return r if not r.endswith("...") else f"{r}({len(value) if hasattr(value, '__len__') else '?'} entries)"


def _flag(value, key) -> bool:
    if not isinstance(value, bool):
        raise ConfigError(f"{key}: expected true or false, got {excerpt(value)}")
    return value


def _coeffs(value, key) -> list[float]:
    if not isinstance(value, (list, tuple)) or not value or len(value) > 33:
        raise ConfigError(f"{key}: expected a list of 1 to 33 coefficients (highest power first), got {_short(value)}")
    return [_num(v, f"{key}[{i}]") for i, v in enumerate(value)]


def _pair(value, key: str, what: str) -> list[float]:
    """A nonzero pair of finite numbers (a direction)."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ConfigError(f"{key}: expected {what}, got {excerpt(value)}")
    v = [_num(x, f"{key}[{i}]") for i, x in enumerate(value)]
    if v == [0.0, 0.0]:
        raise ConfigError(f"{key}: expected a nonzero direction, got {excerpt(value)}")
    return v


def _nested(value) -> bool:
    return isinstance(value, (list, tuple)) and len(value) > 0 and isinstance(value[0], (list, tuple))


def _check_channel(num, den, key_num: str, key_den: str) -> None:
    import numpy as np

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
    _num(plant.input_limit, "plant.input_limit", positive=True)
    if plant.slew_limit is not None:
        _num(plant.slew_limit, "plant.slew_limit", positive=True)
    mimo_num, mimo_den = _nested(plant.num), _nested(plant.den)
    direction = _pair(plant.direction, "plant.direction", "[x, y] px per output unit")
    if not mimo_num and not mimo_den:
        _check_channel(plant.num, plant.den, "plant.num", "plant.den")
        _num(plant.delay_s, "plant.delay_s", nonnegative=True)
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
                _num(d[i][j], f"plant.delay_s[{i}][{j}]", nonnegative=True)
    else:
        _num(d, "plant.delay_s", nonnegative=True)


def validate_spots(sp: SpotsConfig, camera: CameraConfig | None = None) -> None:
    """Check the ``spots`` section; raise :class:`ConfigError` naming the key."""
    _num(sp.rows, "spots.rows", integer=True, low=0)
    if not sp.enabled:
        return
    _num(sp.cols, "spots.cols", integer=True, low=1)
    _num(sp.pitch_px, "spots.pitch_px", positive=True)
    if sp.center_px is not None:
        if not isinstance(sp.center_px, (list, tuple)) or len(sp.center_px) != 2:
            raise ConfigError(f"spots.center_px: expected null or [x, y] (px), got {excerpt(sp.center_px)}")
        for i, v in enumerate(sp.center_px):
            _num(v, f"spots.center_px[{i}]")
    if sp.sigma_px is not None:
        _num(sp.sigma_px, "spots.sigma_px", low=MIN_PSF_SIGMA_PX)
    for k in ("sigma_variation", "elongation"):
        _num(getattr(sp, k), f"spots.{k}", nonnegative=True)
    _num(sp.gain_variation, "spots.gain_variation", low=-0.99, high=0.99)
    _num(sp.rotation_rad, "spots.rotation_rad")
    if not isinstance(sp.missing, (list, tuple)):
        raise ConfigError(f"spots.missing: expected a list of grid indices, got {excerpt(sp.missing)}")
    n = int(sp.rows) * int(sp.cols)
    for i, m in enumerate(sp.missing):
        _num(m, f"spots.missing[{i}]", integer=True, low=0, high=n - 1)
    if len(set(int(m) for m in sp.missing)) >= n:
        raise ConfigError("spots.missing: every spot of the grid is missing")
    if sp.crop_px is not None:
        _num(sp.crop_px, "spots.crop_px", integer=True, low=8)
    if camera is not None:
        side = sp.crop_side()
        if side < 8:
            raise ConfigError(f"spots.pitch_px: a crop of floor(pitch_px) = {side} px is too small (at least 8; or set spots.crop_px)")
        if side > min(camera.height, camera.width):
            raise ConfigError(f"spots.crop_px: a crop of {side} px does not fit a {camera.height}x{camera.width} frame")


DM_PLAN_KINDS = ("auto", "one_at_a_time", "sparse", "hadamard")


def validate_dm_model(d: DMConfig, w: WFSConfig) -> None:
    """Check the ``dm`` and ``wfs`` sections (the mirror and its sensor: all the bench emulator's
    DM mode reads); raise :class:`ConfigError` naming the key."""
    _num(d.n_across, "dm.n_across", integer=True, low=0, high=64)
    if not d.enabled:
        return
    _num(d.coupling, "dm.coupling", positive=True, high=0.99)
    for k in ("mode_hz", "damping"):
        _num(getattr(d, k), f"dm.{k}", positive=True)
    for k in ("gain", "delay_s", "delay_spread_s", "weak_gain"):
        _num(getattr(d, k), f"dm.{k}", nonnegative=True)
    for k in ("mode_spread", "damping_spread", "gain_spread"):
        _num(getattr(d, k), f"dm.{k}", nonnegative=True, high=0.33)
    for k in ("dead", "weak"):
        v = getattr(d, k)
        if not isinstance(v, (list, tuple)):
            raise ConfigError(f"dm.{k}: expected a list of actuator indices, got {excerpt(v)}")
        for i, j in enumerate(v):
            _num(j, f"dm.{k}[{i}]", integer=True, low=0)
    if d.actuator_table is not None and (not isinstance(d.actuator_table, str) or not d.actuator_table.strip()):
        raise ConfigError(f"dm.actuator_table: expected a path to a CSV file or null, got {excerpt(d.actuator_table)}")
    if d.input_limit is not None:
        _num(d.input_limit, "dm.input_limit", positive=True)
    _validate_dm_registration(d.registration)
    _num(w.n_across, "wfs.n_across", integer=True, low=1, high=128)
    _num(w.pitch_px, "wfs.pitch_px", low=8)
    _num(w.sigma_px, "wfs.sigma_px", low=MIN_PSF_SIGMA_PX)
    _num(w.sigma_variation, "wfs.sigma_variation", nonnegative=True)
    _num(w.slope_px, "wfs.slope_px", positive=True)
    _num(w.min_illumination, "wfs.min_illumination", positive=True, high=1.0)
    _num(w.oversample, "wfs.oversample", integer=True, low=1, high=256)


def _validate_dm_registration(r: DMRegistrationConfig) -> None:
    """Check ``dm.registration`` (the simulated mirror's): shifts within 2 pitches, rotation within
    10 degrees, magnification in [0.8, 1.25], coupling null or in (0, 0.99]."""
    for k in ("shift_x", "shift_y"):
        _num(getattr(r, k), f"dm.registration.{k}", low=-2.0, high=2.0)
    _num(r.rotation_deg, "dm.registration.rotation_deg", low=-10.0, high=10.0)
    _num(r.magnification, "dm.registration.magnification", low=0.8, high=1.25)
    if r.coupling is not None:
        _num(r.coupling, "dm.registration.coupling", positive=True, high=0.99)


def validate_dm(cfg: IdentifyConfig) -> None:
    """Check the ``dm``, ``wfs`` and ``dm_plan`` sections of a DM run; raise :class:`ConfigError`
    naming the key (the actuator table itself is read, and checked, when the mirror is built)."""
    d, w, p = cfg.dm, cfg.wfs, cfg.dm_plan
    validate_dm_model(d, w)
    if not d.enabled:
        return
    if p.kind not in DM_PLAN_KINDS:
        raise ConfigError(f"dm_plan.kind: expected one of {DM_PLAN_KINDS}, got {excerpt(p.kind)}")
    if p.budget_frames is None and p.n_repeats is None:
        raise ConfigError("dm_plan.budget_frames: expected a frame budget, or set dm_plan.n_repeats")
    if p.budget_frames is not None:
        _num(p.budget_frames, "dm_plan.budget_frames", integer=True, low=1, high=LIMITS["frames"])
    if p.n_repeats is not None:
        _num(p.n_repeats, "dm_plan.n_repeats", integer=True, low=1)
    _num(p.support_threshold, "dm_plan.support_threshold", nonnegative=True, high=1.0)
    room = w.pitch_px / 2 - 3 * w.sigma_px * (1 + w.sigma_variation)
    if cfg.excitation.target_px > room:
        raise ConfigError(f"excitation.target_px: a DM spot motion of {cfg.excitation.target_px} px does not stay in its "
                          f"subaperture (room {room:.3g} px: wfs.pitch_px / 2 less 3 PSF sigmas)")


def validate_camera(c: CameraConfig) -> None:
    """Check the ``camera`` section; raise :class:`ConfigError` naming the key."""
    for k in ("frame_rate_hz", "max_exposure_s", "gain", "full_well", "psf_sigma_px", "peak_fraction"):
        _num(getattr(c, k), f"camera.{k}", positive=True)
    if c.psf_sigma_px < MIN_PSF_SIGMA_PX:
        raise ConfigError(f"camera.psf_sigma_px: a PSF of {c.psf_sigma_px} px std is not sampled by the pixels; expected at "
                          f"least {MIN_PSF_SIGMA_PX} px")
    for k in ("readout_s", "trigger_delay_s", "latency_s", "jitter_s", "read_noise", "dark_level"):
        _num(getattr(c, k), f"camera.{k}", nonnegative=True)
    if c.gain_from not in GAIN_FROM:
        raise ConfigError(f"camera.gain_from: expected one of {GAIN_FROM}, got {c.gain_from!r}")
    _num(c.ptc_frames, "camera.ptc_frames", integer=True, low=0, high=10000)
    if c.ptc_frames == 1:
        raise ConfigError("camera.ptc_frames: expected 0 (no ladder) or at least 2 frames per exposure (a pair), got 1")
    if c.latency_std_s is not None:
        _num(c.latency_std_s, "camera.latency_std_s", nonnegative=True)
    _num(c.bit_depth, "camera.bit_depth", integer=True, low=1, high=32)
    _num(c.height, "camera.height", integer=True, low=8)
    _num(c.width, "camera.width", integer=True, low=8)
    if c.peak_fraction > 1:
        raise ConfigError(f"camera.peak_fraction: expected a value in (0, 1], got {c.peak_fraction}")
    if c.dark_level >= 2 ** int(c.bit_depth) - 1:
        raise ConfigError(f"camera.dark_level: expected a value below the ADC's maximum 2**camera.bit_depth - 1 = "
                          f"{2 ** int(c.bit_depth) - 1} ADU (else every pixel is saturated), got {c.dark_level}")


def validate_rig(r: RigConfig) -> None:
    """Check the ``rig`` section; raise :class:`ConfigError` naming the key."""
    if r.kind not in RIG_KINDS:
        raise ConfigError(f"rig.kind: expected one of {RIG_KINDS}, got {excerpt(r.kind)}")
    for k in ("port", "frames"):
        v = getattr(r, k)
        if v is not None and (not isinstance(v, str) or not v.strip()):
            raise ConfigError(f"rig.{k}: expected a non-empty string, got {excerpt(v)}")
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
        elif f.startswith("pylon://"):  # a Basler camera (the pylon extra): its options checked here, opened later
            from torchblur.errors import ParameterError
            from torchblur.hardware.pylon import pylon_url_options

            try:
                pylon_url_options(f)
            except ParameterError as exc:
                raise ConfigError(f"rig.frames: {excerpt(f)}: {str(exc).removeprefix('url: ')}") from None
            ok = True
        elif f.startswith("aravis://"):  # a GenICam camera through Aravis (the aravis extra): options checked here
            from torchblur.errors import ParameterError
            from torchblur.hardware.aravis import aravis_url_options

            try:
                aravis_url_options(f)
            except ParameterError as exc:
                raise ConfigError(f"rig.frames: {f!r}: {str(exc).removeprefix('url: ')}") from None
            ok = True
        else:
            mod, sep, name = f.partition(":")
            ok = bool(sep and mod and name and "/" not in f)
        if not ok:
            raise ConfigError(f"rig.frames: expected tcp://HOST:PORT, pylon://[SERIAL][?trigger=...], aravis://[DEVICE][?...] "
                              f"or package.module:ClassName, got {excerpt(f)}")
    _num(r.timeout_s, "rig.timeout_s", positive=True)
    _num(r.retries, "rig.retries", integer=True, low=0, high=100)


def validate_excitation(x: ExcitationConfig) -> None:
    """Check the multisine keys of the ``excitation`` section; raise :class:`ConfigError` naming the key."""
    if x.kind not in EXCITATION_KINDS:
        raise ConfigError(f"excitation.kind: expected one of {EXCITATION_KINDS}, got {excerpt(x.kind)}")
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


def whole_periods(periods: float) -> bool:
    """Whether an exposure of ``periods`` periods (> 0) is a whole number of them (to 1e-9)."""
    return periods >= 1 - 1e-9 and abs(periods - round(periods)) <= 1e-9 * max(1.0, periods)


def validate_sweep(s: SweepConfig) -> None:
    """Check the ``sweep`` section; raise :class:`ConfigError` naming the key."""
    if s.freq_hz is not None:
        if not isinstance(s.freq_hz, (list, tuple)) or not s.freq_hz:
            raise ConfigError(f"sweep.freq_hz: expected a non-empty list of frequencies, got {excerpt(s.freq_hz)}")
        for i, f in enumerate(s.freq_hz):
            _num(f, f"sweep.freq_hz[{i}]", positive=True)
    else:
        _num(s.f_min_hz, "sweep.f_min_hz", positive=True)
        _num(s.f_max_hz, "sweep.f_max_hz", positive=True)
        _num(s.n, "sweep.n", integer=True, low=1)
        if s.f_max_hz < s.f_min_hz:
            raise ConfigError(f"sweep.f_max_hz: expected >= sweep.f_min_hz ({s.f_min_hz}), got {s.f_max_hz}")
    if not isinstance(s.exposures, (list, tuple)) or not s.exposures or len(s.exposures) > 16:
        raise ConfigError(f"sweep.exposures: expected a list of 1 to 16 fractions of the period, got {_short(s.exposures)}")
    for i, e in enumerate(s.exposures):
        _num(e, f"sweep.exposures[{i}]", positive=True)
        if whole_periods(e):
            raise ConfigError(f"sweep.exposures[{i}]: {e:g} is a whole number of periods: such an image does not depend on the "
                              f"phase (PHYSICS.md: the moments' start is undefined there); use a fraction such as 0.3 or 0.8")
    _num(s.trigger_phase_rad, "sweep.trigger_phase_rad")
    _num(s.images_per_point, "sweep.images_per_point", integer=True, low=1)
    if s.settle_s is not None:
        _num(s.settle_s, "sweep.settle_s", nonnegative=True)


def validate(cfg: IdentifyConfig) -> None:
    """Check every value; raise :class:`ConfigError` naming the key."""
    validate_plant(cfg.plant)
    s = cfg.sweep
    validate_sweep(s)
    _num(cfg.excitation.target_px, "excitation.target_px", positive=True)
    validate_spots(cfg.spots, cfg.camera)
    if cfg.spots.enabled:
        sigma = cfg.spots.sigma_px if cfg.spots.sigma_px is not None else cfg.camera.psf_sigma_px
        room = cfg.spots.crop_side() / 2 - 3 * float(sigma) * (1 + float(cfg.spots.sigma_variation)) * (1 + float(cfg.spots.elongation))
        if 1.33 * float(cfg.excitation.target_px) > room:
            raise ConfigError(f"excitation.target_px: a motion of up to 1.33 x {cfg.excitation.target_px} px does not stay in a "
                              f"{cfg.spots.crop_side()} px spot crop (room {room:.3g} px from the centre, 3 PSF sigmas kept); "
                              f"lower excitation.target_px or raise spots.pitch_px / spots.crop_px")
    if cfg.excitation.max_amplitude is not None:
        _num(cfg.excitation.max_amplitude, "excitation.max_amplitude", positive=True)
        if cfg.rig.kind == "simulated" and float(cfg.excitation.max_amplitude) > float(cfg.plant.input_limit):
            raise ConfigError(f"excitation.max_amplitude: {cfg.excitation.max_amplitude} is beyond the simulated plant's input "
                              f"range plant.input_limit = {cfg.plant.input_limit}; it may only narrow the range, not widen it")
    if cfg.excitation.max_slew is not None:
        _num(cfg.excitation.max_slew, "excitation.max_slew", positive=True)
        slew = cfg.plant.slew_limit
        if cfg.rig.kind == "simulated" and slew is not None and float(cfg.excitation.max_slew) > float(slew):
            raise ConfigError(f"excitation.max_slew: {cfg.excitation.max_slew} is beyond the simulated plant's slew limit "
                              f"plant.slew_limit = {slew}; it may only narrow the limit, not widen it")
    validate_excitation(cfg.excitation)
    c = cfg.camera
    validate_camera(c)
    f_min = min(s.freq_hz) if s.freq_hz is not None else s.f_min_hz  # (not the whole list: sweep.n may be huge)
    longest = max(s.exposures) / f_min
    if longest > c.max_exposure_s:
        raise ConfigError(f"sweep.exposures: the longest exposure ({max(s.exposures)} of the period at {f_min:g} Hz = "
                          f"{longest:g} s) exceeds camera.max_exposure_s = {c.max_exposure_s:g} s")
    from torchblur.fit.sinusoid import OPTIMIZERS
    from torchblur.losses import LIKELIHOOD_LOSSES, LOSSES

    if isinstance(cfg.fit.axis, str):
        if cfg.fit.axis not in AXIS_MODES:
            raise ConfigError(f"fit.axis: expected one of {AXIS_MODES} or a direction [x, y], got {excerpt(cfg.fit.axis)}")
    else:
        _pair(cfg.fit.axis, "fit.axis", f"one of {AXIS_MODES} or a direction [x, y]")
    if cfg.fit.axis != "measure" and (cfg.plant.is_mimo or cfg.spots.enabled):
        raise ConfigError("fit.axis: applies to one-axis, one-spot runs; this run has "
                          f"{'a 2x2 plant' if cfg.plant.is_mimo else 'many spots (spots.rows > 0)'}, which fits both image axes")
    validate_fit_psf(cfg)
    if cfg.fit.optimizer not in OPTIMIZERS:
        raise ConfigError(f"fit.optimizer: expected one of {OPTIMIZERS}, got {excerpt(cfg.fit.optimizer)}")
    if cfg.fit.loss not in LOSSES:
        raise ConfigError(f"fit.loss: expected one of {LOSSES}, got {excerpt(cfg.fit.loss)}")
    if cfg.fit.loss not in LIKELIHOOD_LOSSES:
        raise ConfigError(f"fit.loss: {excerpt(cfg.fit.loss)} is refused for an identification: it is no likelihood of the camera's noise, so its "
                          f"fit has no covariance and the response's stds would not hold; use one of {LIKELIHOOD_LOSSES} (l2, the default; "
                          f"l1 to be robust to outlier pixels, at 1.25x the std; poisson, the camera's shot and read noise exactly). "
                          f"fit_sinusoid(..., loss='linf', optimizer='adam' or 'lbfgs') still fits it outside a run")
    for k in ("fit_scale", "fit_background", "fit_gradient"):
        _flag(getattr(cfg.fit, k), f"fit.{k}")
    from torchblur.fit.sinusoid import OUTLIERS

    if cfg.fit.outliers not in OUTLIERS:
        raise ConfigError(f"fit.outliers: expected one of {OUTLIERS}, got {excerpt(cfg.fit.outliers)}")
    _num(cfg.fit.outlier_sigma, "fit.outlier_sigma", positive=True)
    _flag(cfg.model.fit_delay, "model.fit_delay")
    for k in ("n_poles", "n_zeros"):
        v = getattr(cfg.model, k)
        if v is not None:
            _num(v, f"model.{k}", integer=True, low=0)
    if cfg.model.n_zeros is not None and cfg.model.n_poles is not None and cfg.model.n_zeros > cfg.model.n_poles:
        raise ConfigError(f"model.n_zeros: expected at most model.n_poles = {cfg.model.n_poles} (a proper model), got {cfg.model.n_zeros}")
    _num(cfg.fit.chunk_points, "fit.chunk_points", integer=True, low=0)
    _num(cfg.model.max_order, "model.max_order", integer=True, low=1, high=16)
    for k in ("direct",):
        if not isinstance(getattr(cfg.model, k), bool):
            raise ConfigError(f"model.{k}: expected true or false, got {excerpt(getattr(cfg.model, k))}")
    from torchblur.sysid.direct import FORMS

    if cfg.model.direct_form not in FORMS:
        raise ConfigError(f"model.direct_form: expected one of {FORMS}, got {excerpt(cfg.model.direct_form)}")
    _num(cfg.model.direct_max_iter, "model.direct_max_iter", integer=True, low=1, high=10000)
    if cfg.excitation.kind == "multisine" and (cfg.plant.is_mimo or cfg.spots.enabled):
        raise ConfigError("excitation.kind: a multisine excitation drives one axis and fits one spot; this run has "
                          f"{'a 2x2 plant' if cfg.plant.is_mimo else 'many spots (spots.rows > 0)'}: use excitation.kind=sine")
    if cfg.model.direct and cfg.excitation.kind == "multisine":
        raise ConfigError("model.direct: the direct fit works on a sine sweep's images; set excitation.kind=sine or model.direct=false")
    if cfg.model.direct and (cfg.plant.is_mimo or cfg.spots.enabled):
        raise ConfigError("model.direct: the direct fit handles one axis and one spot; this run has "
                          f"{'a 2x2 plant' if cfg.plant.is_mimo else 'many spots (spots.rows > 0)'}: set model.direct=false")
    validate_loss_for_plan(cfg)
    validate_rig(cfg.rig)
    validate_report(cfg)
    validate_dm(cfg)
    _num(cfg.seed, "seed", integer=True, low=0, high=2**63 - 1)


def validate_loss_for_plan(cfg: IdentifyConfig) -> None:
    """``fit.loss`` other than l2 with ``excitation.kind=multisine``: refused. The multisine fit
    (and the direct model) is a weighted least squares only; nothing else of a multisine run
    uses ``fit.loss``, so l1 or poisson would be ignored without a word."""
    if cfg.excitation.kind == "multisine" and cfg.fit.loss != "l2":
        raise ConfigError(f"fit.loss: {excerpt(cfg.fit.loss)} is not applied by the multisine plan (excitation.kind=multisine): its fit "
                          f"is a least squares weighted by the camera's noise model (l2) only; set fit.loss=l2, or "
                          f"excitation.kind=sine to fit with {cfg.fit.loss}")


def validate_report(cfg: IdentifyConfig) -> None:
    """``fit.poor_fit_chi2`` (> 0), the ``report`` section's tolerances (> 0) and ``report.figures`` (true or false)."""
    _num(cfg.fit.poor_fit_chi2, "fit.poor_fit_chi2", positive=True)
    _num(cfg.report.tolerance_deg, "report.tolerance_deg", positive=True)
    _num(cfg.report.tolerance_rel, "report.tolerance_rel", positive=True)
    _flag(cfg.report.figures, "report.figures")


def validate_fit_psf(cfg) -> None:
    """``fit.psf``: one of :data:`torchblur.image.psf_from_still.KINDS` (every route fits with
    the PSF it chooses: one spot, many spots, multisine, the direct model)."""
    from torchblur.image.psf_from_still import KINDS as PSF_KINDS

    if not isinstance(cfg.fit.psf, str) or cfg.fit.psf not in PSF_KINDS:
        raise ConfigError(f"fit.psf: expected one of {PSF_KINDS}, got {excerpt(cfg.fit.psf)}")


MIN_PSF_SIGMA_PX = 0.1

# A run beyond any of these is refused at validation, with the estimate (--force to go on).
LIMITS = {"frames": 100_000, "memory_bytes": 8 * 2**30, "disk_bytes": 20 * 2**30, "bench_s": 24 * 3600.0}
_CALIBRATION_FRAMES = 100  # dark, saturation ladder, PSF, latency scan, axis (about)


# What the calibration stage takes besides its dark and still frames (torchblur.identify.calibration
# takes these from here, so that estimate_run counts what it takes).
SATURATION_STEPS = 9  # one still frame per exposure of the saturation ladder
LATENCY_SCAN = {"exposure_s": 200e-6, "pulse_width_s": 20e-6, "max_latency_s": 200e-6, "step_s": 2e-6, "repeats": 2}


def latency_scan_times(trigger_delay_s: float, *, exposure_s: float, pulse_width_s: float, max_latency_s: float,
                       step_s: float):
    """The pulse times ``[n]`` (s after the trigger) of the latency calibration's scan: from
    ``-pulse_width_s`` past ``max_latency_s + trigger_delay_s + exposure_s / 2`` in steps of
    ``step_s`` (:func:`torchblur.identify.calibration.calibrate_latency`)."""
    import numpy as np

    return np.arange(-pulse_width_s, max_latency_s + trigger_delay_s + exposure_s / 2, step_s)


def calibration_frames(cfg: IdentifyConfig, *, n_dark: int, n_still: int) -> int:
    """Frames the calibration takes without the axis tracking (a run with spots, a DM run):
    ``n_dark`` dark, the saturation ladder, ``n_still`` still and the latency scan (each pulse
    time :data:`LATENCY_SCAN` ``repeats`` times)."""
    scan = {k: v for k, v in LATENCY_SCAN.items() if k != "repeats"}
    n_pulse = 0 if cfg.camera.latency_std_s is not None else (
        len(latency_scan_times(float(cfg.camera.trigger_delay_s), **scan)) * LATENCY_SCAN["repeats"])
    n_ptc = 8 * int(cfg.camera.ptc_frames)  # torchblur.identify.calibration.PTC_STEPS exposures
    return int(n_dark) + SATURATION_STEPS + int(n_still) + n_pulse + n_ptc


# A DM run's geometry matrix evaluates every actuator's influence at oversample^2 points of every
# subaperture; bounded by dm.n_across^2 x wfs.n_across^2 x wfs.oversample^2 evaluations (closed form,
# nothing computed). 700 actuators on 40 x 40 subapertures (1.5e9 by the bound) took 80 s here.
GEOMETRY_EVALUATIONS = 4e9
_DM_DEFAULTS = {"dm.n_across": 8.0, "wfs.n_across": 10.0, "wfs.pitch_px": 16.0, "wfs.oversample": 32.0}


def _largest(cfg: IdentifyConfig, keys) -> str:
    """The key of ``keys`` (of :data:`_DM_DEFAULTS`) furthest above its usual value."""
    values = {"dm.n_across": cfg.dm.n_across, "wfs.n_across": cfg.wfs.n_across, "wfs.pitch_px": cfg.wfs.pitch_px,
              "wfs.oversample": cfg.wfs.oversample}
    return max(keys, key=lambda k: float(values[k]) / _DM_DEFAULTS[k])


def dm_size_bounds(cfg: IdentifyConfig) -> dict:
    """Closed-form bounds of a DM run's size from counts alone (no geometry, no plan; instant):
    ``frame_side`` px (``ceil(wfs.n_across * wfs.pitch_px)``), ``frames`` (the fewest sweep frames
    any plan takes: one pattern x frequencies x exposures x ``dm_plan.n_repeats``, or more than
    half of ``dm_plan.budget_frames``), ``memory_bytes`` and ``disk_bytes`` of those frames (as
    :func:`estimate_run` counts them) and ``geometry`` (the most influence evaluations of the
    geometry matrix: ``dm.n_across^2 wfs.n_across^2 wfs.oversample^2``), each with the ``key``
    that drives it."""
    s, w, p = cfg.sweep, cfg.wfs, cfg.dm_plan
    side = math.ceil(float(w.n_across) * float(w.pitch_px))
    n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
    per_pattern = n_freq * len(s.exposures)
    sweep_key = "sweep.freq_hz" if s.freq_hz is not None else "sweep.n"
    if p.n_repeats is not None:
        frames = per_pattern * int(p.n_repeats)
        frames_key = "dm_plan.n_repeats" if int(p.n_repeats) >= n_freq else sweep_key
    else:
        frames, frames_key = (int(p.budget_frames) + 1) // 2, "dm_plan.budget_frames"
        if per_pattern > frames:  # the sweep's own count dominates
            frames_key = sweep_key
    pixels = side * side
    return {"frame_side": side, "frame_key": _largest(cfg, ("wfs.n_across", "wfs.pitch_px")), "frames": frames,
            "frames_key": frames_key, "memory_bytes": 3 * 8 * frames * pixels, "disk_bytes": 2 * frames * pixels,
            "geometry": float(cfg.dm.n_across) ** 2 * float(w.n_across) ** 2 * float(w.oversample) ** 2,
            "geometry_key": _largest(cfg, ("dm.n_across", "wfs.n_across", "wfs.oversample"))}


def check_dm_bounds(cfg: IdentifyConfig) -> dict:
    """Refuse a DM run that :func:`dm_size_bounds` already shows beyond :data:`LIMITS` (or
    whose geometry would take more than :data:`GEOMETRY_EVALUATIONS`), before the geometry and
    the plan are computed; returns the bounds.

    Raises:
        ConfigError: starting with the key that makes the run large.
    """
    b = dm_size_bounds(cfg)
    tail = "refused before any work (--force to go on)"
    if b["frame_side"] > 65536 or b["frame_side"] ** 2 > 2**28:
        raise ConfigError(f"{b['frame_key']}: a {b['frame_side']} x {b['frame_side']} px sensor frame (wfs.n_across x "
                          f"wfs.pitch_px) is more than any camera delivers (2^28 pixels); {tail}")
    if b["frames"] > LIMITS["frames"]:
        raise ConfigError(f"{b['frames_key']}: the run is too large (at least {b['frames']:,} sweep frames; limit "
                          f"{LIMITS['frames']:,}); {tail}")
    for k in ("memory_bytes", "disk_bytes"):
        if b[k] > LIMITS[k]:
            raise ConfigError(f"{b['frame_key']}: the run is too large (at least {b['frames']:,} frames of "
                              f"{b['frame_side']} x {b['frame_side']} px: {_size(b[k])} of {k.split('_')[0]}; limit "
                              f"{_size(LIMITS[k])}); {tail}")
    if b["geometry"] > GEOMETRY_EVALUATIONS:
        raise ConfigError(f"{b['geometry_key']}: the mirror's geometry matrix is too large to compute (up to {b['geometry']:.3g} "
                          f"influence evaluations: dm.n_across^2 x wfs.n_across^2 x wfs.oversample^2; limit "
                          f"{GEOMETRY_EVALUATIONS:.3g}); {tail}")
    return b


def _estimate_dm(cfg: IdentifyConfig) -> dict:
    """:func:`estimate_run` of a DM run (``dm.n_across`` > 0): the plan's sweep frames
    (:func:`torchblur.dm.budget.dm_sweep_size`) and the DM calibration's, on the sensor's frame."""
    from torchblur.dm.budget import DM_DARK_FRAMES, dm_still_frames, dm_sweep_size

    size = dm_sweep_size(cfg)
    n_still = dm_still_frames(size["frames"], size["frame_shape"])
    frames = size["frames"] + calibration_frames(cfg, n_dark=DM_DARK_FRAMES, n_still=n_still)
    est = _estimate(cfg, frames, size["frame_shape"], n_drives=size["patterns"], repeats=size["repeats"])
    est["sweep_frames"] = size["frames"]
    return est


def _estimate(cfg: IdentifyConfig, frames: int, frame_px: tuple, *, n_drives: int, repeats: int) -> dict:
    """:func:`estimate_run`'s dict for ``frames`` of ``frame_px`` ``(H, W)``, the sweep driving
    ``n_drives`` inputs (or DM patterns) at every frequency, ``repeats`` frames per exposure."""
    s, c = cfg.sweep, cfg.camera
    pixels = int(frame_px[0]) * int(frame_px[1])
    bench = float("nan")
    if frames <= LIMITS["frames"]:
        import numpy as np

        f = np.asarray(cfg.frequencies_hz(), dtype=float)
        cycle = np.maximum(1.0 / c.frame_rate_hz, 1.0 / f)
        frame_s = sum(np.maximum(cycle, e / f + c.readout_s) for e in s.exposures) * int(repeats)
        bench = float(n_drives * np.sum(frame_s + (s.settle_s or 0.0) + 2.0 / f))
    return {"frames": frames, "memory_bytes": 3 * 8 * frames * pixels, "disk_bytes": 2 * frames * pixels,
            "bench_s": bench, "motion_px": 1.33 * float(cfg.excitation.target_px), "frame_px": (int(frame_px[0]), int(frame_px[1]))}


def estimate_run(cfg: IdentifyConfig) -> dict:
    """What a run will take, estimated from its config alone (no work): ``frames`` (one
    attempt per sweep point, calibration included), ``memory_bytes`` (the frames held as
    float64, raw and in electrons, with a model per frame), ``disk_bytes`` (the recording,
    16-bit pixels), ``bench_s`` (camera time: per point the settling and every frame at
    least a camera cycle and a period apart; only when ``frames`` is within
    :data:`LIMITS`, else NaN) and ``motion_px`` (the largest spot motion, 1.33 target_px).
    A DM run (``dm.n_across`` > 0) counts its plan's sweep frames (patterns x frequencies x
    exposures x repeats, also ``sweep_frames``) and its calibration's exactly, on the sensor's
    frame (:func:`_estimate_dm`)."""
    if cfg.dm.enabled:
        return _estimate_dm(cfg)
    s, c = cfg.sweep, cfg.camera
    n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
    n_inputs = 2 if cfg.plant.is_mimo else 1
    per_point = len(s.exposures) * int(s.images_per_point)
    frames = n_inputs * n_freq * per_point + _CALIBRATION_FRAMES
    return _estimate(cfg, frames, (c.height, c.width), n_drives=n_inputs, repeats=int(s.images_per_point))


def _size(b: float) -> str:
    return f"{b / 2**30:.3g} GiB" if b >= 2**30 else f"{b / 2**20:.3g} MiB"


def check_limits(cfg: IdentifyConfig) -> dict:
    """Refuse a run beyond :data:`LIMITS` (or whose spot motion exceeds the frame) with the
    estimate of :func:`estimate_run`, which it returns.

    Raises:
        ConfigError: starting with the key that makes the run large, naming the estimate.
    """
    if cfg.dm.enabled:
        check_dm_bounds(cfg)  # closed form, before the geometry and the plan that estimate_run computes
    est = estimate_run(cfg)
    s, c = cfg.sweep, cfg.camera
    bench = f"{est['bench_s'] / 3600:.3g} h" if math.isfinite(est["bench_s"]) else "not estimated (too many frames)"
    summary = (f"estimate: {est['frames']:,} frames, {_size(est['memory_bytes'])} of memory, {_size(est['disk_bytes'])} "
               f"on disk, bench time {bench}")
    over = [k for k in ("frames", "memory_bytes", "disk_bytes", "bench_s") if est[k] > LIMITS[k]]
    if over:
        n_freq = len(s.freq_hz) if s.freq_hz is not None else int(s.n)
        drivers = {"camera.height": int(c.height), "camera.width": int(c.width)} if over == ["memory_bytes"] or \
            int(c.height) * int(c.width) > 2**22 else {}
        drivers = drivers or {"sweep.freq_hz" if s.freq_hz is not None else "sweep.n": n_freq,
                              "sweep.images_per_point": int(s.images_per_point), "sweep.exposures": len(s.exposures)}
        key = max(drivers, key=drivers.get)
        if cfg.dm.enabled:  # the sensor's frame and the plan's frames, not camera.* or sweep.images_per_point
            b = dm_size_bounds(cfg)
            key = b["frame_key"] if over == ["memory_bytes"] or over == ["disk_bytes"] else b["frames_key"]
        shown = {"frames": f"{LIMITS['frames']:,} frames", "memory_bytes": f"memory {_size(LIMITS['memory_bytes'])}",
                 "disk_bytes": f"disk {_size(LIMITS['disk_bytes'])}", "bench_s": f"bench time {LIMITS['bench_s'] / 3600:g} h"}
        limits = ", ".join(shown[k] for k in over)
        raise ConfigError(f"{key}: the run is too large ({summary}; limits: {limits}); refused before any work "
                          f"(--force to go on)")
    if est["motion_px"] > max(est["frame_px"]):
        raise ConfigError(f"excitation.target_px: a spot motion of up to {est['motion_px']:.4g} px (1.33 x target_px) does not "
                          f"fit a {est['frame_px'][0]}x{est['frame_px'][1]} frame ({summary}); refused before any work "
                          f"(--force to go on)")
    return est

