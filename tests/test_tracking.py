"""Frame-by-frame tracking below the camera's Nyquist rate, and the axes calibration."""
import math

import numpy as np
import pytest
import torch

from torchblur.render.camera import CameraModel
from torchblur.systems.lti import Plant
from torchblur.image.preprocess import dark_frame
from torchblur.rig.simulated import SimulatedRig
from torchblur.image.tracking import calibrate_axes, sine_from_centroids, track_sine

WN = 2 * math.pi * 420.0


def make_rig(direction=(1.0, 0.0), seed=0):
    plant = Plant((20.0 * WN * WN,), (1.0, 2 * 0.12 * WN, WN * WN), 30e-6)
    cam = CameraModel(read_noise_e=5.0, full_well_e=20000.0, bit_depth=16)
    return SimulatedRig(plant=plant, camera=cam, frame_shape=(48, 48), psf_sigma_px=2.0, direction=direction, latency_s=0.0,
                        jitter_s=0.0, peak_e_per_s=2e6, seed=seed)


def test_linear_fit_is_exact_on_window_averages():
    om = 2 * math.pi * 7.0
    M, phi = 3.3, -0.7
    te = np.full(9, 0.004)
    t0 = np.linspace(0, 1 / 7.0, 9, endpoint=False)
    p = om * te
    c = om * (t0 + te / 2)
    y = M * (2 * np.sin(p / 2) / p) * np.sin(c + phi)
    r = sine_from_centroids(y, om, t0, te)
    assert abs(r.amplitude - M) < 1e-12 and abs(math.remainder(r.phase - phi, 2 * math.pi)) < 1e-12


def test_tracking_agrees_with_the_truth_and_the_blur_fit():
    rig = make_rig()
    dark = dark_frame(rig.dark(n=8, exposure_s=0.01).frames.to(torch.float64))
    f, A = 5.0, 0.4
    tr = track_sine(rig, freq_hz=f, amplitude=A, rest_px=rig.psf.center, dark=dark, n_frames=16, power=20.0)
    H = rig.truth(f)
    assert abs(tr.amplitude / A - abs(H)) < 5 * tr.amplitude_std / A + 1e-3 * abs(H)
    assert abs(math.remainder(tr.phase - np.angle(H), 2 * math.pi)) < 5 * tr.phase_std + 1e-3
    # the blur fit on the same rig at the same frequency
    from torchblur.fit.sinusoid import fit_sinusoid
    from torchblur.image.preprocess import subtract_dark
    from torchblur.render.psf import GaussianPSF
    from torchblur.render.window import ExposureWindow

    te = [0.3 / f, 0.8 / f]
    cap = rig.sine(freq_hz=f, amplitude=A, exposures_s=te, trigger_offset_s=0.05 / f, n_repeats=1, power=0.03)  # below full well
    img = subtract_dark(cap.frames.to(torch.float64), dark)[:, 0]
    psf = GaussianPSF(rig.psf.center, rig.psf.cov, rig.psf.amplitude * 0.03)
    win = ExposureWindow(torch.full((2,), 0.05 / f, dtype=torch.float64), torch.tensor(te, dtype=torch.float64))
    fit = fit_sinusoid(img, psf, win, 2 * math.pi * f, noise_std=torch.sqrt(25 + img.clamp_min(0)))
    assert abs(float(fit.amplitude) - tr.amplitude) < 5 * math.hypot(float(fit.amplitude_std), tr.amplitude_std)
    assert abs(math.remainder(float(fit.phase) - tr.phase, 2 * math.pi)) < 5 * math.hypot(float(fit.phase_std), tr.phase_std)


@pytest.mark.parametrize("angle_deg", [-35.0])
def test_axes_calibration_recovers_rotation_sign_and_scale(angle_deg):
    a = math.radians(angle_deg)
    rig = make_rig(direction=(math.cos(a), math.sin(a)), seed=2)
    dark = dark_frame(rig.dark(n=8, exposure_s=0.01).frames.to(torch.float64))
    cal = calibrate_axes(rig, freq_hz=3.0, amplitude=0.3, rest_px=rig.psf.center, dark=dark, power=20.0)
    assert abs(math.remainder(cal.angle_rad - a, 2 * math.pi)) < max(5 * cal.angle_std_rad, 2e-3)
    assert abs(cal.px_per_unit - abs(rig.truth(3.0))) < 5 * cal.px_per_unit_std + 2e-3 * 20
