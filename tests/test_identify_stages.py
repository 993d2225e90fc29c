"""The pieces the identification's stages share: the one camera noise model, the sweep's
window builder, the FRF CSV writer with the CLI's stamp columns, and the chunked fitter."""
import csv
import math

import numpy as np
import pytest
import torch

from torchblur.design.windows import dual_exposure_windows
from torchblur.identify.fitting import ChunkFitter
from torchblur.identify.sweep import point_windows
from torchblur.render.camera import camera_noise_std
from torchblur.sysid.frequency_response import FrequencyResponse

F64 = torch.float64


def test_camera_noise_std_is_read_and_shot_noise():
    e = torch.tensor([-4.0, 0.0, 16.0, 91.0], dtype=F64)
    np.testing.assert_allclose(camera_noise_std(e, 3.0).numpy(), [3.0, 3.0, 5.0, 10.0], rtol=1e-15)
    assert camera_noise_std(16.0, 3.0) == 5.0 and camera_noise_std(-1.0, 2.0) == 2.0
    assert camera_noise_std(e.float(), 3.0).dtype == torch.float32


@pytest.mark.parametrize("freq_hz, phase", [(1.0, math.pi / 2), (437.3, 0.3), (1000.0, 6.0)])
def test_point_windows_are_the_dual_exposure_design_on_the_rig_clock(freq_hz, phase):
    fr, td, lat = [0.3, 0.8], 5e-6, 31e-6
    offset, win = point_windows(freq_hz, fr, phase, td, lat)
    period = 1 / freq_hz
    design = dual_exposure_windows(torch.tensor(2 * math.pi * freq_hz, dtype=F64), fractions=fr, trigger_phase=phase)
    assert 0 <= offset < period
    torch.testing.assert_close(win.duration, design.duration, rtol=0, atol=0)
    torch.testing.assert_close(win.start, torch.full((2,), offset + td + lat, dtype=F64), rtol=0, atol=0)
    # the same phase of the sine as the design's start (a whole number of periods later)
    k = (win.start - design.start) / period
    torch.testing.assert_close(k, k.round(), rtol=0, atol=1e-9)


def test_to_csv_extra_columns_are_the_clis_stamp(tmp_path):
    om = 2 * np.pi * np.array([1.0, 10.0, 100.0])
    resp = np.array([1.0 + 0j, np.exp(-1j * np.pi) * 0.5, np.exp(1j * (np.pi - 1e-16)) * 0.1])
    cov = np.tile(np.diag([1e-4, 1e-2]), (3, 1, 1))
    frf = FrequencyResponse(om, resp, cov=cov)
    frf.to_csv(tmp_path / "plain.csv")
    frf.to_csv(tmp_path / "stamped.csv", extra_columns={"torchblur_version": "9.9", "seed": 7})
    plain = list(csv.reader(open(tmp_path / "plain.csv", newline="")))
    stamped = list(csv.reader(open(tmp_path / "stamped.csv", newline="")))
    assert stamped[0] == plain[0] + ["torchblur_version", "seed"]
    assert [r[:-2] for r in stamped[1:]] == plain[1:] and all(r[-2:] == ["9.9", "7"] for r in stamped[1:])
    assert all(-180 < float(r[2]) <= 180 for r in stamped[1:])
    back = FrequencyResponse.from_csv(tmp_path / "stamped.csv")
    np.testing.assert_allclose(back.magnitude, frf.magnitude, rtol=1e-15)


@pytest.mark.parametrize("chunk", [0, 1, 2, 5])
def test_chunk_fitter_returns_every_point_once_in_order(chunk):
    fitter = ChunkFitter(chunk, lambda idx: [10 * j for j in idx])
    for k in range(7):
        fitter.add(k)
    parts = fitter.finish()
    assert [j for idx, _ in parts for j in idx] == list(range(7))
    assert [v for _, out in parts for v in out] == [10 * j for j in range(7)]
    if chunk:
        assert all(len(idx) == chunk for idx, _ in parts[:-1])
