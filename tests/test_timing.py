import pytest
import torch

import torchblur as tb
from torchblur.errors import ParameterError


def test_frame_windows_follow_the_sample_period():
    timing = tb.SensorTiming(acquisition_s=0.01, trigger_delay_s=2e-5, exposure_s=4e-3, readout_s=1e-3, sample_period_s=1 / 30)
    w = timing.windows(5)
    assert w.shape == (5,)
    assert w.start.dtype == torch.float64
    torch.testing.assert_close(w.start, 0.01002 + torch.arange(5, dtype=torch.float64) / 30)
    torch.testing.assert_close(w.duration, torch.full((5,), 4e-3, dtype=torch.float64))
    torch.testing.assert_close(w.end - w.start, w.duration)
    torch.testing.assert_close(w.center, w.start + 2e-3)
    assert timing.tcam_s == pytest.approx(0.01002)
    assert timing.frame_rate_hz == pytest.approx(30.0)


def test_sample_period_must_cover_delay_readout_and_exposure():
    with pytest.raises(ParameterError, match="sample_period_s"):
        tb.SensorTiming(acquisition_s=0.0, trigger_delay_s=1e-3, exposure_s=0.03, readout_s=0.01, sample_period_s=1 / 30)
    # exactly equal is allowed
    tb.SensorTiming(acquisition_s=0.0, trigger_delay_s=0.0, exposure_s=0.02, readout_s=0.01, sample_period_s=0.03)


def test_window_broadcasts_and_indexes():
    w = tb.ExposureWindow(torch.tensor([[0.0], [1.0]], dtype=torch.float64), torch.tensor([1e-3, 2e-3, 3e-3], dtype=torch.float64))
    assert w.shape == (2, 3)
    assert w[1, 2].start.item() == 1.0 and w[1, 2].duration.item() == pytest.approx(3e-3)


def test_window_is_differentiable():
    start = torch.tensor(0.1, dtype=torch.float64, requires_grad=True)
    dur = torch.tensor(0.2, dtype=torch.float64, requires_grad=True)
    (tb.ExposureWindow(start, dur).center * 2).backward()
    assert start.grad.item() == 2.0 and dur.grad.item() == 1.0


def BACKGROUND_JOB(out, started):
    """The fresh process of :func:`test_import_is_light`, run in the background by tests/background.py -> the finished process."""
    import sys

    from background import run

    code = ("import sys, torchblur; heavy = [m for m in ('kornia', 'scipy', 'matplotlib', 'control', 'serial', 'omegaconf', 'tifffile') "
            "if m in sys.modules]; print(','.join(heavy))")
    return run([sys.executable, "-c", code], started)


def test_import_is_light(background, request):
    done = background.get(request.module.__name__)  # import torchblur in a fresh process: which heavy modules came with it
    assert done.returncode == 0, done.stderr
    out = done.stdout.strip()
    assert out == "", f"import torchblur loaded heavy modules: {out}"
