"""torch's median along a dimension of stride 0 is garbage (torch 2.13, float64): torchblur's
medians go through torchblur._compat.median_along, and the statistics built on it hold on an
expanded (broadcast) input. torch's default CPU least squares (gelsy) is not reproducible:
torchblur._compat.lstsq_solution is, and multisine's centroid start built on it."""
import math
import random

import torch

from torchblur._compat import lstsq_solution, median_along
from torchblur.fit.multisine import _centroid_start
from torchblur.fit.robust import robust_scale
from torchblur.image.dark import robust_std


def test_median_along_an_expanded_dimension_is_the_median():
    x = torch.tensor([1.0, 5.0, 3.0], dtype=torch.float64)[:, None].expand(3, 6)  # stride 0 along the last dim
    assert x.stride(-1) == 0
    assert torch.equal(median_along(x), torch.tensor([1.0, 5.0, 3.0], dtype=torch.float64))
    assert torch.equal(median_along(x, keepdim=True), torch.tensor([[1.0], [5.0], [3.0]], dtype=torch.float64))
    y = torch.tensor([[2.0, float("nan"), 4.0, 9.0]], dtype=torch.float64).expand(3, 4)
    assert torch.equal(median_along(y, ignore_nan=True), torch.full((3,), 4.0, dtype=torch.float64))
    z = torch.arange(12.0, dtype=torch.float64).reshape(3, 4)
    assert torch.equal(median_along(z, 0), z.median(0).values)


def test_robust_spreads_of_a_broadcast_input_equal_the_contiguous_ones():
    """A level broadcast along the reduced dimension (stride 0 there): its median is the level and
    its spread 0 (torch's own median gave a denormal, so a spread of 1.48 x the level)."""
    level = torch.tensor([3.0, 7.0], dtype=torch.float64)[:, None].expand(2, 16)
    assert level.stride(-1) == 0
    assert torch.equal(robust_std(level, 1), torch.zeros(2, dtype=torch.float64))
    assert torch.equal(robust_std(level, 1), robust_std(level.contiguous(), 1))
    r = torch.tensor(2.0, dtype=torch.float64).expand(3, 1, 4, 4)  # residuals [n, E, H, W], all 2: a spread of 0
    used = torch.ones(3, 1, 4, 4, dtype=torch.bool)
    assert torch.equal(robust_scale(r, used), robust_scale(r.contiguous(), used))


def _churn(rng: random.Random, keep: list) -> None:
    """Change the allocator's state: buffers of random sizes filled with 1e300 kept or freed."""
    keep.append(torch.full((rng.randrange(1, 20000),), 1e300, dtype=torch.float64))
    if len(keep) > 40:
        keep.pop(rng.randrange(len(keep)))


def test_lstsq_solution_is_bitwise_reproducible_and_least_squares():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(2, 12, 6, dtype=torch.float64, generator=g)
    b = torch.randn(2, 12, 1, dtype=torch.float64, generator=g)
    rng, keep = random.Random(0), []
    first = lstsq_solution(a, b)
    for _ in range(300):  # torch.linalg.lstsq's default driver gave 8 distinct answers here
        _churn(rng, keep)
        assert torch.equal(lstsq_solution(a.clone(), b.clone()), first)
    normal = torch.linalg.solve(a.mT @ a, a.mT @ b)
    assert torch.allclose(first, normal, rtol=1e-12, atol=1e-12)
    # rank-deficient: the minimum-norm solution (a repeated column shares its coefficient)
    d = torch.cat([a[:, :, :1], a[:, :, :1]], -1)
    x = lstsq_solution(d, b)
    assert torch.allclose(x[:, 0], x[:, 1], rtol=1e-10, atol=1e-12)


def test_multisine_centroid_start_is_bitwise_reproducible():
    g = torch.Generator().manual_seed(1)
    E, N, H, W = 12, 3, 24, 24
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    shift = torch.randn(1, E, 1, 1, dtype=torch.float64, generator=g) * 2
    data = torch.exp(-((xx - 11.5 - shift) ** 2 + (yy - 11.5) ** 2) / 8) + 1e-3 * torch.rand(1, E, H, W, dtype=torch.float64, generator=g)
    rest, u = torch.tensor([[11.5, 11.5]], dtype=torch.float64), torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    start = torch.linspace(0, 0.9, E, dtype=torch.float64)[None]
    dur = torch.full((1, E), 0.05, dtype=torch.float64)
    omega = 2 * math.pi * torch.tensor([[1.0, 4.0, 16.0]], dtype=torch.float64)
    rng, keep = random.Random(1), []
    first = _centroid_start(data, rest, u, start, dur, omega, 0.05)
    assert bool(first[2].all()) and bool(torch.isfinite(first[0]).all())
    for _ in range(200):
        _churn(rng, keep)
        again = _centroid_start(data, rest, u, start, dur, omega, 0.05)
        assert all(torch.equal(p, q) for p, q in zip(first, again))
