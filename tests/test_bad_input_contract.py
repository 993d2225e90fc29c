"""The input contract of torchblur's public API (issue 8): read this before adding an entry point.

Two tables:

* ``BAD``: a bad input at a public entry point -> the exact exception class and the argument
  name its message must contain. Every error subclasses ``ValueError`` or ``TypeError``
  (``ShapeError``, ``ParameterError``, ``ConfigError`` / ``InputTypeError``), is raised by
  torchblur's own check (the last frame of the traceback is in ``torchblur/``, never deep in
  torch or numpy) and its message says what was expected and what came.
  ``tests/test_bad_input.py`` holds the renderer/PSF/trajectory/window cases written with
  issue 2; this table adds the rest and does not repeat them.
* ``DEGENERATE``: well-formed but degenerate data (a dark frame, a saturated frame, a spot
  outside the frame, no motion, ...). These are never raised: the fit flags the item in
  ``status`` / ``flags`` and the other items of the batch come out as if fitted alone.
"""
import math
import sys
import traceback
from pathlib import Path

import numpy as np
import pytest
import torch

import torchblur as tb
from torchblur.image import preprocess as pp
from torchblur.render.camera import CameraModel
from torchblur.config import load_config
from torchblur.design.windows import check_design, dual_exposure_windows
from torchblur.errors import ConfigError, InputTypeError, ParameterError, ShapeError
from torchblur.fit.sinusoid import fit_sinusoid
from torchblur.fit.status import MASKED, NO_MOTION, OUTLIERS_MASKED, PARTLY_OUT_OF_FRAME, SATURATED_MASKED
from torchblur.sysid.frequency_response import FrequencyResponse
from torchblur.sysid.tf_fit import fit_transfer_function
from torchblur.image.moments import image_moments
from torchblur.image.tracking import sine_from_centroids

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64
NAN = float("nan")
C = torch.tensor([10.0, 10.0], dtype=F64)
I2 = torch.eye(2, dtype=F64)
Z2 = torch.zeros(2, dtype=F64)
TRAJ = tb.Sinusoid(torch.tensor([3.0, 0.0], dtype=F64), Z2, 600.0)
PSF = tb.GaussianPSF(C, 4 * I2)
WIN = tb.ExposureWindow(0.0, 1e-3)
IMG = tb.render_blur(TRAJ, PSF, WIN, height=20, width=20)[None]  # [E=1, 20, 20]
RENDERER = tb.BlurRenderer(20, 20)
PRED = {"amplitude": torch.tensor([3.0, 0.0], dtype=F64), "phase": Z2}
FRF = FrequencyResponse(np.array([1.0, 2.0, 3.0]), np.array([1.0 + 0j, 0.5j, 0.1]))


def fit(images=IMG, psf=PSF, window=WIN, omega=600.0, **kw):
    return fit_sinusoid(images, psf, window, omega, **kw)


BAD = [
    # (case, callable, exception class, argument named in the message)
    # --- tensors that are not real numbers
    ("bool omega tensor", lambda: tb.Sinusoid(Z2, Z2, torch.tensor(True)), InputTypeError, "omega"),
    ("bool amplitude tensor", lambda: tb.Sinusoid(torch.tensor([True, False]), Z2, 1.0), InputTypeError, "amplitude"),
    ("bool numpy covariance", lambda: tb.GaussianPSF(C, np.eye(2, dtype=bool)), InputTypeError, "cov"),
    ("bool exposure duration", lambda: tb.ExposureWindow(0.0, torch.tensor(True)), InputTypeError, "duration"),
    ("bool kernel image", lambda: tb.KernelPSF(torch.ones(4, 4, dtype=torch.bool)), InputTypeError, "image"),
    ("complex omega", lambda: tb.Sinusoid(Z2, Z2, torch.tensor(1 + 1j)), InputTypeError, "omega"),
    ("complex kernel", lambda: tb.KernelPSF(torch.ones(4, 4, dtype=torch.complex64)), InputTypeError, "image"),
    ("string window start", lambda: tb.ExposureWindow("now", 1.0), InputTypeError, "start"),
    ("None PSF centre", lambda: tb.GaussianPSF(None, I2), InputTypeError, "center"),
    ("wrap_phase of a string", lambda: tb.wrap_phase("pi"), InputTypeError, "phase"),
    ("wrap_phase of a complex tensor", lambda: tb.wrap_phase(torch.tensor(1j)), InputTypeError, "phase"),
    # --- impossible values
    ("negative PSF amplitude", lambda: tb.GaussianPSF(C, I2, amplitude=-1.0), ParameterError, "amplitude"),
    ("from_axes minor sigma zero", lambda: tb.GaussianPSF.from_axes(C, 2.0, 0.0, 0.1), ParameterError, "sigma_minor"),
    ("from_axes NaN angle", lambda: tb.GaussianPSF.from_axes(C, 2.0, 1.0, NAN), ParameterError, "angle"),
    ("kernel without light", lambda: tb.KernelPSF(torch.zeros(4, 4)), ParameterError, "image"),
    ("kernel of negative light", lambda: tb.KernelPSF(-torch.ones(4, 4)), ParameterError, "image"),
    ("empty kernel", lambda: tb.KernelPSF(torch.zeros(0, 4)), ShapeError, "image"),
    ("Inf exposure", lambda: tb.ExposureWindow(0.0, float("inf")), ParameterError, "duration"),
    ("Inf omega", lambda: tb.Sinusoid(Z2, Z2, float("inf")), ParameterError, "omega"),
    ("NaN timing", lambda: tb.SensorTiming(NAN, 0.0, 0.01, 0.01, 1 / 30), ParameterError, "acquisition_s"),
    ("multisine NaN amplitude", lambda: tb.Multisine(torch.full((3, 2), NAN), torch.zeros(3, 2), torch.ones(3)), ParameterError, "amplitude"),
    ("spline times do not match values", lambda: tb.SplineTrajectory(torch.tensor([0.0, 1.0, 2.0]), torch.zeros(2, 2)), ShapeError, "times"),
    # --- renderer
    ("render empty batch", lambda: tb.render_blur(tb.Sinusoid(torch.zeros(0, 2), torch.zeros(0, 2), 1.0), PSF, WIN, height=8, width=8),
     ShapeError, "trajectory"),
    ("render settings of wrong type", lambda: tb.render_blur(TRAJ, PSF, WIN, height=8, width=8, settings="fast"), InputTypeError, "settings"),
    ("render float height", lambda: tb.render_blur(TRAJ, PSF, WIN, height=8.0, width=8), ParameterError, "height"),
    ("render window of wrong type", lambda: tb.render_blur(TRAJ, PSF, (0.0, 1e-3), height=8, width=8), InputTypeError, "window"),
    ("RenderSettings max_nodes negative", lambda: tb.RenderSettings(max_nodes=-1), ParameterError, "max_nodes"),
    ("BlurRenderer module: PSF None", lambda: tb.BlurRenderer(8, 8)(TRAJ, None, WIN), InputTypeError, "psf"),
    ("alias_phase window of wrong type", lambda: tb.alias_phase(0.1, 1.0, (0.0, 1e-3)), InputTypeError, "window"),
    ("check_design window of wrong type", lambda: check_design(10.0, "window"), InputTypeError, "window"),
    ("dual_exposure_windows fraction NaN", lambda: dual_exposure_windows(10.0, fractions=(NAN, 0.5)), ParameterError, "fractions"),
    ("image_moments integer image", lambda: image_moments(torch.zeros(5, 5, dtype=torch.int32)), InputTypeError, "images"),
    ("image_moments 1-D image", lambda: image_moments(torch.zeros(5)), ShapeError, "images"),
    # --- fitter
    # integer images (a camera's counts) are promoted, not refused: tests/test_fit_entry.py
    ("fit complex images", lambda: fit(IMG.to(torch.complex128)), InputTypeError, "images"),
    ("fit bool images", lambda: fit(IMG > 0.1), InputTypeError, "images"),
    ("fit images without an exposure axis", lambda: fit(IMG[0]), ShapeError, "images"),
    ("fit empty batch", lambda: fit(torch.zeros(0, 1, 20, 20, dtype=F64)), ShapeError, "images"),
    ("fit NaN images", lambda: fit(IMG * NAN), ParameterError, "images"),
    ("fit bool omega", lambda: fit(omega=torch.tensor(True)), InputTypeError, "omega"),
    ("fit omega zero", lambda: fit(omega=0.0), ParameterError, "omega"),
    ("fit omega batch mismatch", lambda: fit(IMG.expand(3, 1, 20, 20), omega=torch.full((4,), 600.0)), ShapeError, "omega"),
    ("fit window batch mismatch", lambda: fit(IMG.expand(3, 1, 20, 20), window=tb.ExposureWindow(torch.zeros(3, dtype=F64), 1e-3)),
     ShapeError, "window"),
    ("fit max_iter zero", lambda: fit(max_iter=0), ParameterError, "max_iter"),
    ("fit max_iter string", lambda: fit(max_iter="10"), ParameterError, "max_iter"),
    ("fit tol NaN", lambda: fit(tol=NAN), ParameterError, "tol"),
    ("fit tol negative", lambda: fit(tol=-1.0), ParameterError, "tol"),
    ("fit render_settings string", lambda: fit(render_settings="fast"), InputTypeError, "render_settings"),
    ("fit fit_scale string", lambda: fit(fit_scale="yes"), InputTypeError, "fit_scale"),
    ("fit unknown outliers mode", lambda: fit(outliers="clip"), ParameterError, "outliers"),
    ("fit outlier_sigma zero", lambda: fit(outliers="reject", outlier_sigma=0.0), ParameterError, "outlier_sigma"),
    ("fit outliers with normalize", lambda: fit(outliers="reject", normalize=True), ParameterError, "outliers"),
    ("fit saturation_level NaN", lambda: fit(saturation_level=NAN), ParameterError, "saturation_level"),
    ("fit saturation_level batch mismatch", lambda: fit(IMG.expand(3, 1, 20, 20), saturation_level=torch.ones(2)), ShapeError,
     "saturation_level"),
    ("fit float mask", lambda: fit(mask=torch.ones(1, 20, 20)), InputTypeError, "mask"),
    ("fit noise_std negative", lambda: fit(noise_std=-1.0), ParameterError, "noise_std"),
    # --- measurement-consistency loss
    ("consistency complex observed", lambda: tb.BlurConsistencyLoss(RENDERER, PSF, WIN)(PRED, IMG.to(torch.complex128)), InputTypeError,
     "observed"),
    ("consistency normalize string", lambda: tb.BlurConsistencyLoss(RENDERER, PSF, WIN, normalize="yes"), InputTypeError, "normalize"),
    ("consistency NaN observed", lambda: tb.BlurConsistencyLoss(RENDERER, PSF, WIN, omega=600.0)(PRED, IMG * NAN), ParameterError, "observed"),
    # --- camera
    ("camera dark level above the ADC range", lambda: CameraModel(dark_level_adu=5000.0, bit_depth=12), ParameterError, "dark_level_adu"),
    ("camera NaN frames to electrons", lambda: CameraModel().to_electrons(torch.full((2, 2), NAN)), ParameterError, "frames_adu"),
    ("camera NaN frames saturation mask", lambda: CameraModel().saturated_mask(torch.full((2, 2), NAN)), ParameterError, "frames_adu"),
    ("camera bool expected electrons", lambda: CameraModel().expose(torch.ones(4, 4, dtype=torch.bool)), InputTypeError, "expected_e"),
    # --- preprocessing
    ("dark_frame bool frames", lambda: pp.dark_frame(torch.zeros(3, 4, 4, dtype=torch.bool)), InputTypeError, "frames"),
    ("dark_frame one frame", lambda: pp.dark_frame(torch.zeros(1, 4, 4)), ShapeError, "frames"),
    ("subtract_dark without a DarkFrame", lambda: pp.subtract_dark(torch.zeros(4, 4), "dark"), InputTypeError, "dark"),
    ("crop centre NaN", lambda: pp.crop(torch.zeros(8, 8), torch.tensor([NAN, 4.0]), (4, 4)), ParameterError, "center_xy"),
    ("saturation_curve length mismatch", lambda: pp.saturation_curve(torch.ones(5), torch.ones(4)), ShapeError, "exposures_s"),
    # --- frequency response, tracking and model fit
    ("FrequencyResponse decreasing omega", lambda: FrequencyResponse(np.array([3.0, 2.0, 1.0]), np.ones(3, complex)), ParameterError, "omega"),
    ("FrequencyResponse bool omega", lambda: FrequencyResponse(np.array([True, True]), np.ones(2, complex)), InputTypeError, "omega"),
    ("fit_transfer_function of a string", lambda: fit_transfer_function("frf"), InputTypeError, "frf"),
    ("fit_transfer_function stable string", lambda: fit_transfer_function(FRF, stable="no"), InputTypeError, "stable"),
    ("sine_from_centroids omega zero", lambda: sine_from_centroids(np.zeros(5), 0.0, np.arange(5.0), np.full(5, 0.1)), ParameterError, "omega"),
    ("sine_from_centroids scalar duration", lambda: sine_from_centroids(np.zeros(5), 1.0, np.arange(5.0), 0.1), ShapeError, "duration_s"),
    ("sine_from_centroids NaN offsets", lambda: sine_from_centroids(np.full(5, NAN), 1.0, np.arange(5.0), np.full(5, 0.1)), ParameterError,
     "offset_px"),
    # --- pipeline entry and configuration
    ("identify with a path instead of a config", lambda: __import__("torchblur.identify.run", fromlist=["identify"]).identify("cfg.yaml"),
     InputTypeError, "cfg"),
    ("identify with a rig of wrong type", lambda: __import__("torchblur.identify.run", fromlist=["identify"]).identify(
        load_config(None, ["sweep.n=2"]), rig="bench", progress=False), InputTypeError, "rig"),
    ("config boolean that is not", lambda: load_config(None, ["fit.fit_scale=maybe"]), ConfigError, "fit.fit_scale"),
    ("config model.fit_delay number", lambda: load_config(None, ["model.fit_delay=3"]), ConfigError, "model.fit_delay"),
    ("config linf with lm", lambda: load_config(None, ["fit.loss=linf"]), ConfigError, "fit.loss"),
    ("config dark level above the ADC", lambda: load_config(None, ["camera.dark_level=5000"]), ConfigError, "camera.dark_level"),
    ("config more zeros than poles", lambda: load_config(None, ["model.n_poles=2", "model.n_zeros=3"]), ConfigError, "model.n_zeros"),
    # --- counts (errors.check_int): a non-integer is a wrong type, an integer out of range a wrong value
    ("candidate_windows float n_offsets", lambda: _fisher().candidate_windows(0.01, max_exposure_s=0.01, n_offsets=4.0), InputTypeError,
     "n_offsets"),
    ("candidate_windows zero n_offsets", lambda: _fisher().candidate_windows(0.01, max_exposure_s=0.01, n_offsets=0), ParameterError,
     "n_offsets"),
    ("design_acquisition float max_images", lambda: _design(max_images=16.0), InputTypeError, "max_images"),
    ("design_acquisition string n_images", lambda: _design(n_images="4"), InputTypeError, "n_images"),
    ("design_acquisition zero n_images", lambda: _design(n_images=0), ParameterError, "n_images"),
    ("Plant.to_control float pade_order", lambda: _plant().to_control(pade_order=2.5), InputTypeError, "pade_order"),
    ("Plant.to_control zero pade_order", lambda: _plant().to_control(pade_order=0), ParameterError, "pade_order"),
    ("splat float height", lambda: _splat(8.0, 8), InputTypeError, "height"),
    ("splat zero width", lambda: _splat(8, 0), ParameterError, "width"),
    ("SensorTiming.windows float n_frames", lambda: tb.SensorTiming(0.0, 0.0, 0.01, 0.01, 1 / 30).windows(3.0), InputTypeError, "n_frames"),
    ("SimulatedRig float seed", lambda: _rig(seed=1.5), InputTypeError, "seed"),
    ("SimulatedRig negative seed", lambda: _rig(seed=-1), ParameterError, "seed"),
]


def _fisher():
    from torchblur.design import fisher

    return fisher


def _design(**kw):
    return _fisher().design_acquisition([3.0], [600.0], PSF, period_s=2 * math.pi / 600, max_exposure_s=0.01, frame_shape=(16, 16),
                                        read_noise_e=2.0, **kw)


def _plant():
    from torchblur.systems.lti import Plant

    return Plant(num=(1.0,), den=(1e-3, 1.0), delay_s=40e-6)


def _splat(height, width):
    from torchblur.render.splat import gaussian_splat_with_jacobian

    z = torch.zeros(4, dtype=F64)
    return gaussian_splat_with_jacobian(z, z, torch.zeros(4, 1, dtype=F64), torch.zeros(4, 1, dtype=F64), z + 0.25,
                                        torch.tensor(0.3, dtype=F64), torch.tensor(0.0, dtype=F64), torch.tensor(0.3, dtype=F64), height, width)


def _rig(**kw):
    from torchblur.rig import SimulatedRig

    return SimulatedRig(plant=_plant(), camera=CameraModel(), **kw)


def _raised_in_torchblur(exc: BaseException) -> bool:
    frames = traceback.extract_tb(exc.__traceback__)
    return "torchblur" in Path(frames[-1].filename).parts


@pytest.mark.parametrize("case,fn,exc,name", BAD, ids=[b[0] for b in BAD])
def test_bad_input_raises_the_contracted_error(case, fn, exc, name):
    with pytest.raises(exc) as info:
        fn()
    assert type(info.value) is exc
    assert name in str(info.value), str(info.value)
    assert isinstance(info.value, (ValueError, TypeError))
    assert _raised_in_torchblur(info.value), "raised deep inside a dependency, not by torchblur's own check"
    assert "expected" in str(info.value) or exc is ConfigError or "must" in str(info.value) or "needs" in str(info.value)


def test_the_contract_is_large_and_its_cases_distinct():
    assert len({b[0] for b in BAD}) == len(BAD)
    beyond_fitter = [b for b in BAD if not b[0].startswith("fit ")]
    assert len(beyond_fitter) >= 30


def BACKGROUND_JOB(tmp_path, started):
    """``torchblur identify --out TMP/o fit.fit_background=perhaps`` in a fresh process, run in the background by
    tests/background.py -> the finished process."""
    from background import run

    return run([sys.executable, "-m", "torchblur.cli", "identify", "--out", str(tmp_path / "o"), "fit.fit_background=perhaps"],
               started, cwd=ROOT)


def test_cli_bad_key_is_one_line_exit_2(background, request):
    out = background.get(request.module.__name__)
    assert out.returncode == 2
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "fit.fit_background" in lines[0] and "Traceback" not in out.stderr


# ----------------------------------------------------------------------------- degenerate data: flagged, never raised

H, W = 24, 32
N_DEG = 6


def _batch():
    """Six dual-exposure items of a spot moving along x (seeded), 1% noise."""
    g = torch.Generator().manual_seed(11)
    om = 2 * math.pi * (80 + 500 * torch.rand(N_DEG, generator=g, dtype=F64))
    M = 3 + 2 * torch.rand(N_DEG, generator=g, dtype=F64)
    phi = (2 * torch.rand(N_DEG, generator=g, dtype=F64) - 1) * math.pi
    win = dual_exposure_windows(om, fractions=(0.3, 0.8), trigger_phase=1.0)
    psf = tb.GaussianPSF.isotropic(torch.tensor([15.5, 11.5], dtype=F64).expand(N_DEG, 2), torch.full((N_DEG,), 1.8, dtype=F64))
    amp = torch.stack([M, torch.zeros_like(M)], -1)
    clean = tb.render_blur(tb.Sinusoid(amp[:, None], torch.stack([phi, phi], -1)[:, None], om[:, None]),
                           tb.GaussianPSF(psf.center[:, None], psf.cov[:, None]), win, height=H, width=W)
    sigma = 0.01 * clean.amax((-1, -2, -3))
    noise = sigma[:, None, None, None] * torch.randn(clean.shape, generator=g, dtype=F64)
    return clean, noise, sigma, psf, win, om, M, phi


def _still(psf, win, om, k):
    return tb.render_blur(tb.Sinusoid(Z2, Z2, om[k]), psf[k], win[k], height=H, width=W)


DEGENERATE = [
    # (case, how item 0 of the batch is spoilt, fit options, expected status, flag bits that must be set)
    ("all dark", lambda c, n, s, p, w, o: (n[0], p), {}, 1, 0),
    ("all saturated", lambda c, n, s, p, w, o: (torch.full_like(c[0], 2.0) * c[0].max(), p), {"saturation_level": "peak"}, 5, SATURATED_MASKED),
    ("spot outside the frame", lambda c, n, s, p, w, o: (c[0] + n[0], tb.GaussianPSF(
        torch.cat([torch.tensor([[300.0, 300.0]], dtype=F64), p.center[1:]]), p.cov)), {}, 3, 0),
    ("no motion", lambda c, n, s, p, w, o: (_still(p, w, o, 0) + n[0], p), {}, 0, NO_MOTION),
    ("spot partly out of frame", None, {}, 0, PARTLY_OUT_OF_FRAME),
    ("every pixel masked", lambda c, n, s, p, w, o: (c[0] + n[0], p), {"mask": "none"}, 5, MASKED),
    ("saturated core", lambda c, n, s, p, w, o: (torch.minimum(c[0] + n[0], 0.7 * c[0].max()), p), {"saturation_level": "0.7"}, 0,
     SATURATED_MASKED),
    ("a cosmic-ray hit", "ray", {"outliers": "reject"}, 0, OUTLIERS_MASKED),
]


@pytest.mark.parametrize("case,spoil,opts,status,flag", DEGENERATE, ids=[d[0] for d in DEGENERATE])
def test_degenerate_item_is_flagged_and_does_not_touch_the_batch(case, spoil, opts, status, flag):
    clean, noise, sigma, psf, win, om, M, phi = _batch()
    images = clean + noise
    if spoil is None:  # rest position 2 px from the left edge: the streak leaves the frame
        psf = tb.GaussianPSF(torch.cat([torch.tensor([[2.0, 11.5]], dtype=F64), psf.center[1:]]), psf.cov)
        first = tb.render_blur(tb.Sinusoid(torch.stack([M[0], M[0].new_zeros(())])[None], torch.stack([phi[0], phi[0]])[None], om[0]),
                               psf[0], win[0], height=H, width=W)
        images[0] = first + noise[0]
    elif spoil == "ray":
        images[0, 1, 12, 20] += 30 * clean[0].max()
    else:
        images[0], psf = spoil(clean, noise, sigma, psf, win, om)
    kw = dict(noise_std=sigma)
    if "saturation_level" in opts:  # item 0 clips at the level, the others never
        level = clean[0].max() * (1.0 if opts["saturation_level"] == "peak" else 0.7)
        kw["saturation_level"] = torch.cat([level[None], torch.full((N_DEG - 1,), 1e9, dtype=F64)])
    if opts.get("mask") == "none":
        m = torch.ones(images.shape, dtype=torch.bool)
        m[0] = False
        kw["mask"] = m
    if "outliers" in opts:
        kw["outliers"] = opts["outliers"]
    res = fit_sinusoid(images, psf, win, om, **kw)
    assert int(res.status[0]) == status
    assert int(res.flags[0]) & flag == flag
    if status in (1, 3, 5):
        assert torch.isnan(res.amplitude[0]) and torch.isnan(res.phase[0])
    # The other items: fitted as if alone, unflagged.
    alone = fit_sinusoid(images[1:], psf[1:], win[1:], om[1:], noise_std=sigma[1:])
    torch.testing.assert_close(res.amplitude[1:], alone.amplitude, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(res.phase[1:], alone.phase, rtol=1e-6, atol=1e-9)
    assert (res.status[1:] == 0).all() and (res.flags[1:] & ~MASKED == 0).all()
    if status == 0:
        ok = ((res.amplitude[0] - M[0]).abs() < 4 * res.amplitude_std[0]) | bool(flag == NO_MOTION)
        assert ok


def test_robust_fit_config_keys_default_to_todays_behaviour():
    cfg = load_config()
    assert (cfg.fit.outliers, cfg.fit.outlier_sigma, cfg.fit.fit_gradient) == ("none", 5.0, False)
    cfg = load_config(None, ["fit.outliers=reject", "fit.outlier_sigma=6", "fit.fit_gradient=true"])
    assert (cfg.fit.outliers, cfg.fit.outlier_sigma, cfg.fit.fit_gradient) == ("reject", 6, True)
    for bad, key in ((["fit.outliers=clip"], "fit.outliers"), (["fit.outlier_sigma=0"], "fit.outlier_sigma"),
                     (["fit.fit_gradient=sometimes"], "fit.fit_gradient")):
        with pytest.raises(ConfigError) as info:
            load_config(None, bad)
        assert str(info.value).startswith(key)


def test_check_type_names_the_argument_what_was_expected_and_what_came():
    from torchblur.errors import check_type

    w = tb.ExposureWindow(torch.tensor([0.0]), torch.tensor([1e-3]))
    assert check_type(w, "window", tb.ExposureWindow, "an ExposureWindow") is w
    assert check_type(2.0, "x", (int, float), "a number") == 2.0
    with pytest.raises(InputTypeError, match=r"^window: expected an ExposureWindow, got list$"):
        check_type([0.0], "window", tb.ExposureWindow, "an ExposureWindow")
