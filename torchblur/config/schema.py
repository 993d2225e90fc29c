"""The settings of ``torchblur identify``: frozen dataclasses, one per section of the config,
with their defaults (:mod:`torchblur.config.load` reads a YAML file and overrides into them,
:mod:`torchblur.config.checks` validates them). Units: Hz and seconds as the names say; the
plant's ``num``/``den`` are continuous-time coefficients (highest power first) with the output
in pixels per input unit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

from torchblur.losses import LOSSES
from torchblur.fit.sinusoid import OPTIMIZERS, OUTLIERS
from torchblur.image.psf_from_still import KINDS as PSF_KINDS
from torchblur.image.spots import SpotGrid
from torchblur.sysid.direct import FORMS

__all__ = ["IdentifyConfig", "PlantConfig", "SweepConfig", "ExcitationConfig", "CameraConfig", "FitConfig", "ModelConfig",
           "ReportConfig", "RigConfig", "SpotsConfig", "DMConfig", "DMRegistrationConfig", "WFSConfig", "DMPlanConfig",
           "DEFAULT_PLANT", "RIG_KINDS", "EXCITATION_KINDS", "AXIS_MODES", "GAIN_FROM", "DM_PLAN_KINDS", "DM_SPOT_MODELS", "MIN_PSF_SIGMA_PX",
           "is_nested", "key"]

RIG_KINDS = ("simulated", "serial")
EXCITATION_KINDS = ("sine", "multisine")
AXIS_MODES = ("measure", "x", "y")
GAIN_FROM = ("auto", "measure", "config")
DM_PLAN_KINDS = ("auto", "one_at_a_time", "sparse", "hadamard")
DM_SPOT_MODELS = ("auto", "shifted", "ladder")
MIN_PSF_SIGMA_PX = 0.1  #: px: a narrower PSF is not sampled by the pixels


def key(default=None, *, factory=None, **check):
    """A field with its ``default`` (or ``factory``) and its declared single-field ``check``
    (:func:`torchblur.config.checks.check_declared` applies it): a number with the bounds of
    :func:`~torchblur.errors.check_real_scalar` (``positive``, ``nonnegative``, ``integer``,
    ``low``, ``high``; none: any finite number), ``choice`` (one of), ``flag`` (true or false),
    ``text`` (a non-empty string), ``items`` (a list of numbers, each with those bounds; ``length``
    ``(fewest, most)``), and ``optional`` (null allowed); ``what``: the message's expected words."""
    if factory is not None:
        return field(default_factory=factory, metadata={"check": check})
    return field(default=default, metadata={"check": check})


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
    # torchblur.rig.simulated.DEFAULT_INPUT_LIMIT, the same: 8 px at 5 kHz on the default mirror takes ~126
    input_limit: float = key(200.0, positive=True)
    # The simulated amplifier's slew-rate limit, input units per second (|d command / dt|, a sine's amplitude * omega:
    # the current limit of a piezo amplifier, its full range only up to slew_limit / (2 pi input_limit) Hz); null: none.
    slew_limit: Optional[float] = key(None, optional=True, positive=True)

    @property
    def is_mimo(self) -> bool:
        """True when ``num`` is nested (a 2x2 plant)."""
        return is_nested(self.num)


@dataclass(frozen=True)
class SpotsConfig:
    """Many spots (a Shack-Hartmann sensor, see :mod:`torchblur.image.spots`). ``rows`` = 0 (the
    default): one spot, as without this section."""

    rows: int = 0
    cols: int = key(0, integer=True, low=1)
    pitch_px: float = key(32.0, positive=True)
    # grid centre (x, y) px; null: the frame centre
    center_px: Optional[list] = key(None, optional=True, items={}, length=(2, 2), what="null or [x, y] (px)")
    sigma_px: Optional[float] = key(None, optional=True, low=MIN_PSF_SIGMA_PX)  # PSF std at the grid centre; null: camera.psf_sigma_px
    sigma_variation: float = key(0.0, nonnegative=True)
    elongation: float = key(0.0, nonnegative=True)
    gain_variation: float = key(0.0, low=-0.99, high=0.99)
    rotation_rad: float = key(0.0)
    # row-major indices of absent spots (simulation)
    missing: list = key(factory=list, items={"integer": True, "low": 0}, what="a list of grid indices")
    crop_px: Optional[int] = key(None, optional=True, integer=True, low=8)  # side of each spot's crop; null: floor(pitch_px)

    @property
    def enabled(self) -> bool:
        return int(self.rows) > 0

    def grid(self, camera=None):
        """The :class:`~torchblur.image.spots.SpotGrid` of this section (None when disabled)."""
        if not self.enabled:
            return None
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
    trigger_phase_rad: float = key(math.pi / 2)
    images_per_point: int = key(2, integer=True, low=1)
    settle_s: Optional[float] = key(None, optional=True, nonnegative=True)


@dataclass(frozen=True)
class ExcitationConfig:
    target_px: float = key(8.0, positive=True)
    max_amplitude: Optional[float] = key(None, optional=True, positive=True)
    # input units/s: narrows the rig's slew limit (plant.slew_limit, SLEW?); never widens it
    max_slew: Optional[float] = key(None, optional=True, positive=True)
    # "sine": one frequency per point (the sweep); "multisine": the sweep's frequencies in groups of `tones`, each group
    # one multisine on a common grid with one designed image set (torchblur.identify.multisine).
    kind: str = key("sine", choice=EXCITATION_KINDS)
    tones: int = key(3, integer=True, low=1, high=15)
    # multisine: output amplitude of each tone (px); default 0.75 target_px
    tone_px: Optional[float] = key(None, optional=True, positive=True)
    # multisine: images per group; None: the design's size for target_std
    images: Optional[int] = key(None, optional=True, integer=True, low=2, high=1000)
    max_images: int = key(12, integer=True, low=2, high=1000)  # multisine: most images per group when `images` is None
    target_std: float = key(2e-3, positive=True)  # multisine: predicted std of every |H| (relative) and phase (rad) the design aims at
    snap_tol: float = key(0.05, positive=True)  # multisine: largest relative move of a frequency onto the group's common grid


@dataclass(frozen=True)
class CameraConfig:
    frame_rate_hz: float = key(30.0, positive=True)
    max_exposure_s: float = key(1.0, positive=True)
    readout_s: float = key(1e-3, nonnegative=True)
    trigger_delay_s: float = key(0.0, nonnegative=True)
    # The trigger-to-exposure latency: the simulated camera's (its truth); with latency_std_s set, also the
    # run's, given instead of scanned with laser pulses (a rig without pulse(): a camera whose latency is known).
    latency_s: float = key(12e-6, nonnegative=True)
    latency_std_s: Optional[float] = key(None, optional=True, nonnegative=True)
    jitter_s: float = key(0.2e-6, nonnegative=True)
    read_noise: float = key(5.0, nonnegative=True)
    gain: float = key(1.0, positive=True)
    # Which gain the run uses: "auto", "measure" (the photon transfer curve's) or "config" (camera.gain); the rule:
    # torchblur.identify.calibration.choose_gain
    gain_from: str = key("auto", choice=GAIN_FROM)
    # frames per exposure of a photon transfer ladder (8 exposures) for a precise gain; 0: none
    ptc_frames: int = key(0, integer=True, low=0, high=10000)
    full_well: float = key(20000.0, positive=True)
    bit_depth: int = key(12, integer=True, low=1, high=32)
    dark_level: float = key(100.0, nonnegative=True)
    psf_sigma_px: float = key(2.0, low=MIN_PSF_SIGMA_PX)
    height: int = key(64, integer=True, low=8)
    width: int = key(64, integer=True, low=8)
    peak_fraction: float = key(0.5, positive=True, high=1.0)


@dataclass(frozen=True)
class FitConfig:
    # One-axis, one-spot runs: the image direction of the actuator's motion. "measure" (default): tracked
    # during the calibration (torchblur.image.tracking.calibrate_axes at the sweep's first frequency); "x", "y",
    # or [x, y]. The response is the motion along that direction (the sign that points toward +x, or +y).
    axis: object = "measure"
    # The PSF every fit of the run uses: "auto" (the Gaussian where it explains the still frames to their noise,
    # else the measured kernel), "kernel" or "gaussian"; the rule: docs/measured_psf.md, "The rule, once for every route"
    psf: str = key("auto", choice=PSF_KINDS)
    optimizer: str = key("lm", choice=OPTIMIZERS)
    # "l2", "l1" or "poisson", each weighted by the calibrated camera noise (linf: refused, no likelihood)
    loss: str = key("l2", choice=LOSSES)
    fit_scale: bool = key(True, flag=True)
    fit_background: bool = key(False, flag=True)
    fit_gradient: bool = key(False, flag=True)  # remove a stray-light plane per exposure (fit_sinusoid's fit_gradient)
    # "reject": mask pixels whose residual exceeds outlier_sigma std (hot pixels, cosmic rays) and refit
    outliers: str = key("none", choice=OUTLIERS)
    outlier_sigma: float = key(5.0, positive=True)
    # Points per batched fit. The sweep hands every completed chunk to a background fit, so
    # fitting overlaps the acquisition; 0 fits all points in one batch after the sweep.
    chunk_points: int = key(8, integer=True, low=0)
    # A point whose image fit has a reduced chi2 above this is flagged poor_fit: its stds are multiplied by
    # sqrt(reduced chi2) and it is left out of the transfer-function fit (docs/reliability.md, "Per-point flags").
    poor_fit_chi2: float = key(1.5, positive=True)
    # Where a DM run's spot fits run (a torch device: cpu, cuda, cuda:1, mps): every frequency's crops and
    # PSFs go there, its fits come back to the CPU. A device that is not here is refused, and so is any
    # other than cpu for a sine or multisine run (its fits run on the CPU).
    device: str = "cpu"


@dataclass(frozen=True)
class ModelConfig:
    n_poles: Optional[int] = key(None, optional=True, integer=True, low=0)
    n_zeros: Optional[int] = key(None, optional=True, integer=True, low=0)
    max_order: int = key(6, integer=True, low=1, high=16)
    fit_delay: bool = key(True, flag=True)
    # Direct identification (torchblur.sysid.direct): after the two-step model, fit its parameters
    # to every image at once; model.json then holds the direct model, model_two_step.json the other.
    direct: bool = key(False, flag=True)
    direct_form: str = key("tf", choice=FORMS)  # "tf" (normalised poles/zeros) or "modal" (sum of modes)
    direct_max_iter: int = key(100, integer=True, low=1, high=10000)


@dataclass(frozen=True)
class ReportConfig:
    # The run's tolerance: the report states the frequency above which the timing terms alone (trigger jitter
    # per frame, averaged, and the latency's std) exceed tolerance_deg of phase, and flags those points timing.
    tolerance_deg: float = key(1.0, positive=True)
    tolerance_rel: float = key(0.01, positive=True)  # |H| relative: the report counts the points whose |H| std is within it
    # false: no figures (bode.png, residuals.png, ptc.png, dm/actuator_maps.png; benchmarks/bench_figures.py: their cost);
    # every number file (frf.*, model.json, report.txt, dm/*.csv/.npy/.json) is written as before.
    figures: bool = key(True, flag=True)


@dataclass(frozen=True)
class RigConfig:
    kind: str = key("simulated", choice=RIG_KINDS)  # "simulated" (built-in) or "serial" (a controller on rig.port, a camera on rig.frames)
    # serial: device path or pyserial URL (socket://HOST:PORT, spy://PATH?file=LOG)
    port: Optional[str] = key(None, optional=True, text=True)
    # serial: tcp://HOST:PORT (emulator) or package.module:ClassName (SDKCamera)
    frames: Optional[str] = key(None, optional=True, text=True)
    timeout_s: float = key(2.0, positive=True)  # serial: reply timeout
    retries: int = key(2, integer=True, low=0, high=100)  # serial: how many times a failed point is redone


@dataclass(frozen=True)
class DMRegistrationConfig:
    """The SIMULATED mirror's registration on its sensor (:class:`torchblur.dm.registration.Registration`):
    ``shift_x``/``shift_y`` (actuator pitches), ``rotation_deg``, ``magnification`` and the true
    ``coupling`` (null: ``dm.coupling``). The run does not read it: it fits the registration to
    the measured D0 (a real mirror's is whatever it is)."""

    shift_x: float = key(0.0, low=-2.0, high=2.0)
    shift_y: float = key(0.0, low=-2.0, high=2.0)
    rotation_deg: float = key(0.0, low=-10.0, high=10.0)
    magnification: float = key(1.0, low=0.8, high=1.25)
    coupling: Optional[float] = key(None, optional=True, positive=True, high=0.99)


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
    coupling: float = key(0.15, positive=True, high=0.99)
    mode_hz: float = key(1000.0, positive=True)
    damping: float = key(0.1, positive=True)
    gain: float = key(1.0, nonnegative=True)
    delay_s: float = key(20e-6, nonnegative=True)
    mode_spread: float = key(0.0, nonnegative=True, high=0.33)
    damping_spread: float = key(0.0, nonnegative=True, high=0.33)
    gain_spread: float = key(0.0, nonnegative=True, high=0.33)
    delay_spread_s: float = key(0.0, nonnegative=True)
    dead: list = key(factory=list, items={"integer": True, "low": 0}, what="a list of actuator indices")
    weak: list = key(factory=list, items={"integer": True, "low": 0}, what="a list of actuator indices")
    weak_gain: float = key(0.3, nonnegative=True)
    actuator_table: Optional[str] = key(None, optional=True, text=True, what="a path to a CSV file or null")
    input_limit: Optional[float] = key(None, optional=True, positive=True)
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

    n_across: int = key(10, integer=True, low=1, high=128)
    pitch_px: float = key(16.0, low=8)
    sigma_px: float = key(1.5, low=MIN_PSF_SIGMA_PX)
    sigma_variation: float = key(0.0, nonnegative=True)
    slope_px: float = key(1.0, positive=True)
    min_illumination: float = key(0.5, positive=True, high=1.0)
    oversample: int = key(32, integer=True, low=1, high=256)


@dataclass(frozen=True)
class DMPlanConfig:
    """The excitation plan of a DM run (:mod:`torchblur.dm.plans`): ``kind`` one of auto,
    one_at_a_time, sparse, hadamard (auto: the fewest frames at equal accuracy, but sparse, seen
    at ``SPARSE_MARGIN`` x ``support_threshold``, in place of hadamard where the spots take the
    ladder: :class:`torchblur.identify.dm_plan.DMPlan`); ``budget_frames`` the most sweep frames (the repeats per
    exposure are the most that fit, unless ``n_repeats`` is set); ``support_threshold``: the
    sparse plan's |G| threshold relative to the largest. The spots' model in the sweep's fits,
    ``spot_model``: ``shifted`` (each spot's still, shifted by its motion), ``ladder`` (each
    pattern's static images held at ``ladder_levels`` levels, ``ladder_frames`` frames each,
    spanning +-``ladder_reach`` x the largest command the sweep expects of the pattern:
    ``excitation.target_px`` over its static motion, within the input range; the rig needs
    ``pattern_ladder``) or ``auto`` (the two end levels first, ``LADDER_TEST_FRAMES`` frames each:
    the ladder only where a shifted still does not explain every spot's static image within its
    noise). ``ladder_frames`` 32: the held images' noise enters the ladder fit's results and stds
    (on the small simulated mirror: benchmarks/bench_dm_ladder_frames.py, docs/deformable_mirrors.md
    "The ladder fit for the run")."""

    kind: str = key("auto", choice=DM_PLAN_KINDS)
    budget_frames: Optional[int] = 20000
    n_repeats: Optional[int] = key(None, optional=True, integer=True, low=1)
    support_threshold: float = key(0.01, nonnegative=True, high=1.0)
    spot_model: str = key("auto", choice=DM_SPOT_MODELS)
    ladder_levels: int = key(13, integer=True, low=4, high=257)
    ladder_frames: int = key(32, integer=True, low=1, high=4096)
    ladder_reach: float = key(1.3, positive=True, high=10.0)


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
    seed: int = key(0, integer=True, low=0, high=2**63 - 1)

    def frequencies_hz(self) -> list[float]:
        """The sweep's frequencies (Hz), increasing."""
        s = self.sweep
        if s.freq_hz is not None:
            return sorted(float(f) for f in s.freq_hz)
        if s.n == 1:
            return [float(s.f_min_hz)]
        r = (s.f_max_hz / s.f_min_hz) ** (1 / (s.n - 1))
        return [float(s.f_min_hz * r**k) for k in range(s.n)]


def is_nested(value) -> bool:
    """Whether ``value`` is a list of lists (a 2x2 plant's ``num``, ``den`` or ``delay_s``)."""
    return isinstance(value, (list, tuple)) and len(value) > 0 and isinstance(value[0], (list, tuple))
