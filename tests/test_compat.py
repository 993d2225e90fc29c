"""torch's median along a dimension of stride 0 is garbage (torch 2.13, float64): torchblur's
medians go through torchblur._compat.median_along, and the statistics built on it hold on an
expanded (broadcast) input."""
import torch

from torchblur._compat import median_along
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
