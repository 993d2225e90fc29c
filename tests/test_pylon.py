"""PylonCamera against pylon's own camera emulation (PYLON_CAMEMU=1), serving torchblur-rendered
frames: hardware-trigger setup, exposure, frame counters mapped onto the controller's count.
Skipped where pypylon is not installed (the `pylon` extra)."""
import math
import os

import numpy as np
import pytest
import torch

os.environ.setdefault("PYLON_CAMEMU", "1")  # before pypylon is imported: one emulated camera
pytest.importorskip("pypylon")

import torchblur as tb  # noqa: E402
from torchblur.errors import ParameterError  # noqa: E402
from torchblur.hardware.errors import FrameTimeout, HardwareError  # noqa: E402
from pypylon import pylon  # noqa: E402
from torchblur.hardware.pylon import PylonCamera  # noqa: E402
from torchblur.hardware.serial_rig import open_frame_source  # noqa: E402

if not len(pylon.TlFactory.GetInstance().EnumerateDevices()):
    pytest.skip("pypylon finds no camera, not even the emulation", allow_module_level=True)

H, W = 24, 32
DARK_ADU = 100


def _rendered_frames(n: int) -> np.ndarray:
    """n frames [n, H, W] uint16 ADU of a spot on a sine, one phase each (torchblur's renderer)."""
    renderer = tb.BlurRenderer(height=H, width=W)
    psf = tb.GaussianPSF.isotropic(torch.tensor([16.0, 12.0], dtype=torch.float64), 1.8,
                                   amplitude=torch.tensor(2e6, dtype=torch.float64))
    omega = 2 * math.pi * 200.0
    phase = torch.linspace(0, 2 * math.pi, n + 1, dtype=torch.float64)[:-1, None].expand(n, 2)
    traj = tb.Sinusoid(torch.tensor([6.0, 2.0], dtype=torch.float64).expand(n, 2), phase, torch.tensor(omega, dtype=torch.float64))
    img = renderer(traj, psf, tb.ExposureWindow(torch.tensor(0.0, dtype=torch.float64), torch.tensor(2e-3, dtype=torch.float64)))
    return (DARK_ADU + img.clamp(0, 60000)).round().numpy().astype(np.uint16)


@pytest.fixture
def served(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    frames = _rendered_frames(5)
    for k, f in enumerate(frames):
        tifffile.imwrite(tmp_path / f"frame_{k:03d}.tiff", f)
    return frames, tmp_path


def _camera(image_dir, **kw):
    return PylonCamera(trigger_source="Software", pixel_format="Mono16", frame_shape=(H, W), image_files=image_dir, **kw)


def test_frames_counters_and_exposure(served):
    frames, folder = served
    cam = _camera(folder)
    try:
        assert cam.info.frame_shape == (H, W)
        assert "Emulation" in cam.info.name and cam.info.max_exposure_s > 0.01
        for first, count in ((1000, 5), (1005, 3)):  # two acquisitions: the counter mapping restarts with each
            cam.prepare(2.5e-3, count)
            cam.bind(first, count)
            for _ in range(count):
                cam.software_trigger()
            got = [cam.read(timeout_s=2.0) for _ in range(count)]
            assert [f.counter for f in got] == list(range(first, first + count))
            assert [f.meta["camera_counter"] for f in got] == list(range(count))
            for f in got:
                assert f.dtype == "uint16" and f.data.dtype == torch.float64 and tuple(f.data.shape) == (H, W)
                assert f.exposure_s == pytest.approx(2.5e-3, rel=1e-6)
                # the very pixels torchblur rendered, one of the served files
                assert any(np.array_equal(f.data.numpy(), ref) for ref in frames)
            if first == 1000:  # the files come in name order
                for f, ref in zip(got, frames):
                    np.testing.assert_array_equal(f.data.numpy(), ref)
    finally:
        cam.close()


def test_no_trigger_is_a_timeout(served):
    cam = _camera(served[1])
    try:
        cam.prepare(1e-3, 2)
        cam.bind(1, 2)
        with pytest.raises(FrameTimeout):
            cam.read(timeout_s=0.2)
    finally:
        cam.close()


def test_bad_exposure_and_arguments(served):
    cam = _camera(served[1])
    try:
        with pytest.raises(ParameterError, match="exposure_s"):
            cam.prepare(100.0, 1)
    finally:
        cam.close()
    with pytest.raises(ParameterError, match="buffers"):
        PylonCamera(buffers=0)
    with pytest.raises(HardwareError, match="serial"):
        PylonCamera("no-such-camera")


def test_url_and_config_string():
    cam = PylonCamera.from_url("pylon://0815-0000?trigger=Line1&readout_s=0.002")
    try:
        assert "0815-0000" in cam.info.name
        assert cam.info.readout_s == pytest.approx(0.002)  # the emulation reports no SensorReadoutTime
        assert cam.cam.TriggerSource.Value == "Line1" and cam.cam.TriggerMode.Value == "On"
        assert cam.cam.TriggerSelector.Value == "FrameStart"
    finally:
        cam.close()
    with pytest.raises(ParameterError, match="url"):
        PylonCamera.from_url("tcp://127.0.0.1:5000")
    with pytest.raises(ParameterError, match="unknown options"):
        PylonCamera.from_url("pylon://?gain=3")
    src = open_frame_source("torchblur.hardware.pylon:PylonCamera")  # rig.frames=torchblur.hardware.pylon:PylonCamera
    try:
        assert isinstance(src, PylonCamera) and src.info.frame_shape[0] > 0
    finally:
        src.close()
