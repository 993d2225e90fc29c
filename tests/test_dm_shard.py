"""Sharding DM spot problems over Dask distributed (issue 17): a local cluster of two worker
processes gives the local result; a failed shard is reported, not lost."""
from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from torchblur.identify.dm_shard import fit_sharded, shard_ranges
from torchblur.dm.spot_fit import crop_problems, fit_spot_problems
from torchblur.fit.status import NOT_CONVERGED

distributed = pytest.importorskip("distributed")
sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from test_dm_estimation import _sensor_case  # noqa: E402


def _failing_on_second_point(crops, psf, window, omega, **kw):
    """A shard function that fails for the shard holding 90 Hz (the second frequency)."""
    if bool((omega > 2 * np.pi * 60).any()):
        raise RuntimeError("injected failure")
    return fit_spot_problems(crops, psf, window, omega, **kw)


@pytest.fixture(scope="module")
def client():
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    cluster = distributed.LocalCluster(n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None,
                                       worker_dashboard_address=None)
    with distributed.Client(cluster) as c:
        yield c
    cluster.close()


def test_shard_ranges():
    assert shard_ranges(5, 2) == ((0, 2), (2, 4), (4, 5))
    assert shard_ranges(0, 3) == ()


def test_sharded_equals_local_and_a_failed_shard_is_reported(client):
    frames, offset, size, psf, win, omega, _, rn = _sensor_case(P=1)
    crops, in_frame = crop_problems(frames, offset, size)
    kw = dict(noise_std=rn, mask=in_frame[:, None])
    local = fit_spot_problems(crops, psf, win[None], omega, **kw)
    sharded = fit_sharded(crops, psf, win[None], omega, client=client, shard_points=1, **kw)
    assert sharded.ok and len(sharded.shards) == 2
    torch.testing.assert_close(sharded.fits.amplitude, local.amplitude, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(sharded.fits.covariance, local.covariance, rtol=1e-7, atol=1e-12)
    assert torch.equal(sharded.fits.status, local.status)
    bad = fit_sharded(crops, psf, win[None], omega, client=client, shard_points=1, fit_fn=_failing_on_second_point, **kw)
    assert [i for i, _ in bad.failed_shards] == [1] and "injected failure" in bad.failed_shards[0][1]
    assert bool((bad.fits.status[:, 1] == NOT_CONVERGED).all()) and bool(torch.isnan(bad.fits.amplitude[:, 1]).all())
    torch.testing.assert_close(bad.fits.amplitude[:, 0], local.amplitude[:, 0], rtol=1e-9, atol=1e-9)
    here = fit_sharded(crops, psf, win[None], omega, client=None, shard_points=1, **kw)
    torch.testing.assert_close(here.fits.amplitude, local.amplitude, rtol=1e-9, atol=1e-9)
