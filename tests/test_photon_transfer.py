"""Issue 28: the photon transfer curve (EMVA 1288 style) and the gain a run uses. Frames from the
camera model (torchblur.render.camera.CameraModel: Poisson shot noise, Gaussian read noise, rounding,
clipping), a flat ramp and a still spot; seeded, small frames."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from torchblur.errors import ConfigError, ParameterError, ShapeError
from torchblur.image.dark import dark_frame
from torchblur.image.photon_transfer import PhotonTransfer, photon_transfer, photon_transfer_figure
from torchblur.render.camera import CameraModel


def _camera(gain, bit_depth=12):
    return CameraModel(dark_level_adu=100.0, read_noise_e=5.0, gain_e_per_adu=gain, full_well_e=20000.0, bit_depth=bit_depth)


def _frames(cam, expected_e, n, seed):
    g = torch.Generator().manual_seed(seed)
    return cam.expose(torch.as_tensor(expected_e, dtype=torch.float64).expand((n,) + tuple(expected_e.shape)).clone(), generator=g)


def _spot(peak_e, size=24, sigma=2.0):
    y, x = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij")
    return peak_e * torch.exp(-((x - size / 2) ** 2 + (y - size / 2) ** 2) / (2 * sigma ** 2))


@pytest.mark.parametrize("gain", [0.7, 2.5])
def test_a_ladder_of_flat_ramps_recovers_gain_read_noise_and_dark_level(gain):
    """Ramps from dark to past the ADC's end, 6 steps of 8 frames: gain and read noise within 4 of
    their stds of the camera's, those stds small (< 1.5 % and 2 %), the linear range ending below
    saturation, the clipped pixels left out."""
    cam = _camera(gain)
    ramp = torch.linspace(0.0, 4500.0 * gain, 24 * 24, dtype=torch.float64).reshape(24, 24)  # up to 4500 ADU: past 4095
    steps = [_frames(cam, ramp * s, 8, seed=k) for k, s in enumerate(np.linspace(0.2, 1.0, 6))]
    dark = _frames(cam, torch.zeros(24, 24, dtype=torch.float64), 64, seed=99)
    p = photon_transfer(steps, dark, saturation_adu=cam.saturation_adu)
    assert abs(p.gain_e_per_adu - gain) < 4 * p.gain_std and p.relative_gain_std < 0.015
    assert abs(p.read_noise_e - 5.0) < 4 * p.read_noise_std_e and p.read_noise_std_e / 5.0 < 0.02
    assert abs(p.dark_level_adu - 100.0) < 4 * p.dark_level_std_adu + 1e-9
    assert p.quantization_adu2 == pytest.approx(1 / 12) and p.linear.all()
    assert p.linear_max_adu < cam.saturation_adu - 100.0
    assert 0.5 < p.reduced_chi2 < 1.6
    assert abs(p.gain_z(gain)) < 4 and p.gain_z(2 * gain) > 20


def test_a_still_spot_alone_gives_a_gain_with_an_honest_std():
    """16 frames of a still spot (its pixels span dark to its peak): the std is honest over 6 seeds
    (rms z 0.5-1.6, no |z| above 4), a few % wide."""
    cam = _camera(1.5)
    z = []
    for s in range(6):
        p = photon_transfer(_frames(cam, _spot(4000.0), 16, seed=s), _frames(cam, torch.zeros(24, 24, dtype=torch.float64), 32, seed=50 + s),
                            saturation_adu=cam.saturation_adu)
        z.append(p.gain_z(1.5) * -1)
        assert 0.01 < p.relative_gain_std < 0.1
    z = np.asarray(z)
    assert np.abs(z).max() < 4 and 0.5 < math.sqrt(np.mean(z ** 2)) < 1.6


def test_bad_input_is_refused_by_name():
    cam = _camera(1.0)
    dark = _frames(cam, torch.zeros(8, 8, dtype=torch.float64), 4, seed=0)
    bright = _frames(cam, torch.full((8, 8), 1000.0, dtype=torch.float64), 4, seed=1)
    with pytest.raises(ShapeError, match=r"^steps\[0\]: expected \[N, H, W\] with N >= 2"):
        photon_transfer([bright[:1]], dark)
    with pytest.raises(ShapeError, match="^dark:"):
        photon_transfer([bright], dark[:, :4])
    with pytest.raises(ParameterError, match="^steps: 0 bin"):
        photon_transfer([dark[:2]], dark)  # no light: no slope


def test_the_figure_is_written_and_reads_back(tmp_path):
    """The curve's PNG (the CLI writes it as ptc.png beside bode.png) reads back as an image."""
    import matplotlib.image

    from torchblur.identify.outputs import write_ptc_figure
    from torchblur.config import load_config

    cam = _camera(2.0)
    p = photon_transfer([_frames(cam, _spot(6000.0), 8, seed=3)], _frames(cam, torch.zeros(24, 24, dtype=torch.float64), 16, seed=4),
                        saturation_adu=cam.saturation_adu)
    fig = photon_transfer_figure(p, configured_gain=4.0)
    assert len(fig.axes) == 1 and len(fig.axes[0].lines) >= 3
    res = type("R", (), {"ptc": p})()
    write_ptc_figure(load_config(None, []), res, tmp_path, "stamp")
    img = matplotlib.image.imread(tmp_path / "ptc.png")
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100 and float(img[..., :3].std()) > 0.01


def _ptc(gain, std):
    cam = _camera(gain)
    p = photon_transfer([_frames(cam, _spot(4000.0), 4, seed=0)], _frames(cam, torch.zeros(24, 24, dtype=torch.float64), 8, seed=1))
    return dataclasses.replace(p, gain_e_per_adu=gain, gain_std=std)


def test_choose_gain_auto_measure_config():
    from torchblur.identify.calibration import choose_gain

    precise, rough = _ptc(2.0, 0.01), _ptc(2.0, 0.1)
    assert isinstance(precise, PhotonTransfer)
    assert choose_gain(precise, 2.02, "auto")[:2] == (2.0, "photon transfer")  # within 1 %: the measured gain
    assert choose_gain(rough, 2.1, "auto")[:2] == (2.1, "camera.gain")  # imprecise and consistent: the configured gain
    gain, source, line = choose_gain(rough, 4.0, "auto")  # 20 stds off: the measured gain, with a warning
    assert (gain, source) == (2.0, "photon transfer") and line.startswith("gain: warning: camera.gain 4") and "+20.0 stds" in line
    gain, source, line = choose_gain(rough, 4.0, "config")
    assert (gain, source) == (4.0, "camera.gain") and "warning" in line and "0.707 times the true error's" in line
    assert choose_gain(rough, 2.1, "measure")[:2] == (2.0, "photon transfer")
    assert choose_gain(None, 3.0, "auto")[:2] == (3.0, "camera.gain")


def test_calibration_measures_a_gain_that_is_not_the_configs():
    """The simulated camera at 2 e-/ADU, the config saying 4: calibrate measures it (still frames and an
    8-step ladder), uses it with a warning naming camera.gain, and records where it came from (camera.gain_from=config:
    test_choose_gain_auto_measure_config); the ladder's frames are counted in the estimate."""
    from torchblur.identify.calibration import calibrate
    from torchblur.identify.record import collect_log
    from torchblur.config import calibration_frames, load_config
    from torchblur.rig.factory import build_simulated_rig

    base = ["camera.height=32", "camera.width=32", "sweep.freq_hz=[50]", "fit.axis=x", "camera.latency_std_s=1e-7", "seed=2"]
    rig_cfg = load_config(None, base + ["camera.gain=2"])
    cfg = load_config(None, base + ["camera.gain=4", "camera.ptc_frames=8"])
    with collect_log() as log:
        cal = calibrate(cfg, build_simulated_rig(rig_cfg), n_dark=32, n_still=8)
    assert cal.gain_source == "photon transfer" and cal.ptc.n_steps == 9
    assert abs(cal.gain - 2.0) < 4 * cal.ptc.gain_std and cal.ptc.relative_gain_std < 0.05
    assert any(m.startswith("gain: warning: camera.gain 4 e-/ADU is") for m in log)
    assert cal.noise.gain_e_per_adu == cal.gain
    assert calibration_frames(cfg, n_dark=32, n_still=8) - calibration_frames(load_config(None, base), n_dark=32, n_still=8) == 64
    with pytest.raises(ConfigError, match="^camera.gain_from"):
        load_config(None, base + ["camera.gain_from=datasheet"])
    with pytest.raises(ConfigError, match="^camera.ptc_frames"):
        load_config(None, base + ["camera.ptc_frames=1"])


def test_an_outside_recording_uses_the_gain_its_still_frames_measure(tmp_path):
    """recording.yaml says 4 e-/ADU, the frames are of a 2 e-/ADU camera: torchblur fit's calibration
    measures the gain from the still frames and uses it, naming recording.yaml's value in the warning."""
    from outside_folder import write_outside

    from torchblur.hardware.outside import read_outside_recording
    from torchblur.identify.outside import outside_calibration, outside_config
    from torchblur.identify.record import collect_log

    cam = _camera(2.0, bit_depth=16)
    still = _frames(cam, _spot(8000.0), 16, seed=5).numpy().astype(np.uint16)
    dark = _frames(cam, torch.zeros(24, 24, dtype=torch.float64), 64, seed=6).numpy().astype(np.uint16)
    sweep = _frames(cam, _spot(8000.0), 4, seed=7).numpy().astype(np.uint16)  # own frames: copies of the stills are refused
    pts = [dict(freq_hz=50.0, amplitude=0.5, R=2, frames=sweep, start_s=[1e-3] * 4, duration_s=[2e-3, 2e-3, 5e-3, 5e-3])]
    folder = write_outside(tmp_path / "rec", dark=dark, still=still, still_exposure_s=1e-3, points=pts,
                           camera=dict(gain_e_per_adu=4.0, latency_std_s=0.0))
    rec = read_outside_recording(folder)
    with collect_log() as log:
        cal = outside_calibration(rec, outside_config(rec))
    assert cal.gain_source == "photon transfer" and abs(cal.gain - 2.0) < 4 * cal.ptc.gain_std
    assert any(m.startswith("gain: warning: recording.yaml gain_e_per_adu 4") for m in log)
    cfg = outside_config(rec, ["camera.gain_from=config"])
    assert outside_calibration(rec, cfg).gain == 4.0
