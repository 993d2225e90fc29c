"""Cost landscapes (issue 3, item 6): the data behind the paper's Fig. 2, 5, 6 and 7."""
import math

import pytest
import torch

import torchblur as tb
from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.fit.landscape import cost_landscape

F64 = torch.float64
H, W = 24, 32


def setup(fractions=(0.3, 0.8)):
    om = 2 * math.pi * 120.0
    psf = tb.GaussianPSF.from_axes(torch.tensor([15.5, 11.5], dtype=F64), torch.tensor(2.0, dtype=F64),
                                   torch.tensor(1.5, dtype=F64), torch.tensor(0.4, dtype=F64))
    te = torch.tensor(fractions, dtype=F64) * 2 * math.pi / om
    win = tb.ExposureWindow(torch.full_like(te, 0.7 / om), te)
    M, phi = 5.0, -0.6
    truth = tb.Sinusoid(torch.tensor([[M, 0.0]], dtype=F64), torch.tensor([[phi, phi]], dtype=F64), torch.tensor([om], dtype=F64))
    img = tb.render_blur(truth, psf, win, height=H, width=W)
    return img, psf, win, om, M, phi


def test_landscape_is_zero_at_the_truth_and_matches_a_direct_render():
    img, psf, win, om, M, phi = setup()
    amps = torch.tensor([4.0, M, 6.0], dtype=F64)
    phases = torch.tensor([-2.0, phi, 1.0, 2.5], dtype=F64)
    land = cost_landscape(img, psf, win, om, amps, phases, losses=("l2", "l1", "linf"), chunk=5)
    # zero at the truth up to the quadrature error (< 1e-7 of the peak; the grid's larger
    # motions get more nodes than the data's render)
    peak = float(img.abs().max())
    at_truth = {"l2": 1e-14 * float(img.square().sum()), "l1": 1e-7 * float(img.abs().sum()), "linf": 1e-7 * peak}
    for nm in ("l2", "l1", "linf"):
        c = land[nm]
        assert c.shape == (3, 4, 2)
        assert float(c[1, 1].abs().max()) < at_truth[nm]
        assert int(c.sum(-1).flatten().argmin()) == 1 * 4 + 1
    # one grid point by hand
    other = tb.Sinusoid(torch.tensor([[6.0, 0.0]], dtype=F64), torch.tensor([[2.5, 2.5]], dtype=F64), torch.tensor([om], dtype=F64))
    m = tb.render_blur(other, psf, win, height=H, width=W)
    torch.testing.assert_close(land["l2"][2, 3], (m - img).square().sum((-1, -2)).reshape(2), rtol=1e-8, atol=0)


def test_single_exposure_landscape_has_the_alias_minimum():
    img, psf, win, om, M, phi = setup(fractions=(0.3,))
    alias = float(tb.alias_phase(torch.tensor(phi, dtype=F64), torch.tensor(om, dtype=F64), win[0]))
    land = cost_landscape(img, psf, win, om, torch.tensor([M], dtype=F64), torch.tensor([phi, alias], dtype=F64))["l2"]
    assert float(land.abs().max()) < 1e-14 * float(img.square().sum())


@pytest.mark.parametrize("kw, exc, name", [
    (dict(images=torch.zeros(2, 3)), ShapeError, "images"),
    (dict(images=torch.zeros(2, H, W, dtype=torch.long)), InputTypeError, "images"),
    (dict(amplitude=torch.zeros(2, 2)), ShapeError, "amplitude"),
    (dict(phase=torch.tensor([float("nan")])), ParameterError, "phase"),
    (dict(omega=-1.0), ParameterError, "omega"),
    (dict(axis="z"), ParameterError, "axis"),
    (dict(losses=("l3",)), ParameterError, "losses"),
    (dict(weight=torch.ones(1, H, W)), ShapeError, "weight"),
    (dict(chunk=0), InputTypeError, "chunk"),
])
def test_landscape_bad_input(kw, exc, name):
    img, psf, win, om, M, phi = setup()
    args = dict(images=img, psf=psf, window=win, omega=om, amplitude=torch.tensor([M]), phase=torch.tensor([phi]))
    extra = {k: v for k, v in kw.items() if k not in args}
    args.update({k: v for k, v in kw.items() if k in args})
    with pytest.raises(exc, match=name):
        cost_landscape(args.pop("images"), args.pop("psf"), args.pop("window"), args.pop("omega"), args.pop("amplitude"),
                       args.pop("phase"), **extra)
