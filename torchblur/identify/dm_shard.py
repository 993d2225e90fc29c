"""Spot problems sharded over a Dask distributed cluster: re-fitting many recorded sweeps, or a
mirror too big for one machine.

The problems of a sweep (:mod:`torchblur.dm.spot_fit`) are independent, so the points
``(pattern, frequency)`` are cut into contiguous shards of ``shard_points`` points (all the
spots of a point stay together), each shard is one task on the cluster
(:func:`fit_spot_problems` on the worker, chunked by the worker's own free memory), and the
results are gathered back in order. A shard that raises (a worker lost, an error in its data) is
reported in :attr:`ShardedFits.failed_shards` with its message and its problems get NaN
estimates and status :data:`~torchblur.fit.status.NOT_CONVERGED`; the other shards are kept.

Dask distributed is an optional extra: ``pip install "torchblur[cluster]"`` (or
``pip install "dask[distributed]"``). Any ``distributed.Client`` works: a ``LocalCluster``, an
SSH, SLURM (dask-jobqueue) or Kubernetes cluster; ``client=None`` runs the same shards here,
one after the other (the reference).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from torchblur.dm.spot_fit import SpotFits, fit_spot_problems
from torchblur.errors import InputTypeError, ShapeError, check_int
from torchblur.fit.status import NOT_CONVERGED
from torchblur.render.psf import GaussianPSF
from torchblur.render.window import ExposureWindow

__all__ = ["ShardedFits", "fit_sharded", "shard_ranges"]


@dataclass(frozen=True)
class ShardedFits:
    """The gathered fits, batch ``[P, F, M]`` (:class:`SpotFits`), and the shards.

    Attributes:
        fits: the fits of every problem, in the input's order.
        shards: ``[(first point, end point)]`` over the ``P*F`` points (row-major in (p, f)).
        failed_shards: ``[(shard index, message)]`` of the shards that raised.
    """

    fits: SpotFits
    shards: tuple
    failed_shards: tuple

    @property
    def ok(self) -> bool:
        return not self.failed_shards


def shard_ranges(n_points: int, shard_points: int) -> tuple:
    """``((start, end), ...)`` cutting ``n_points`` into contiguous shards of ``shard_points``."""
    n = check_int(n_points, "n_points", low=0)
    k = check_int(shard_points, "shard_points", low=1)
    return tuple((i, min(n, i + k)) for i in range(0, n, k))


def _fit_shard(crops, center, cov, amplitude, start, duration, omega, noise_std, mask, options, fit_fn):
    """One shard on a worker: points ``[b]`` as a ``[1, b, M, ...]`` sweep."""
    return fit_fn(crops, GaussianPSF(center, cov, amplitude), ExposureWindow(start, duration), omega, noise_std=noise_std,
                  mask=mask, **options)


def _shard_args(crops, psf, window, omega, noise_std, mask, a: int, b: int):
    """The arguments of the shard of points ``a:b`` (``[1, b - a, ...]``)."""
    P, F, M, ER, h, w = crops.shape
    pts = crops.reshape(P * F, M, ER, h, w)[a:b][None]

    def per_point(x, tail):
        if x is None:
            return None
        x = torch.as_tensor(x, device=crops.device)
        return x.expand((P, F) + tail).reshape((P * F,) + tail)[a:b][None]

    om = torch.as_tensor(omega, dtype=crops.dtype, device=crops.device).expand(P, F).reshape(-1)[a:b]
    cen = psf.center.expand(M, 2) if psf.center.dim() <= 2 else per_point(psf.center, (M, 2))
    cv = psf.cov.expand(M, 2, 2) if psf.cov.dim() <= 3 else per_point(psf.cov, (M, 2, 2))
    amp = psf.amplitude.expand(M) if psf.amplitude.dim() <= 1 else per_point(psf.amplitude, (M,))
    st = per_point(window.start, (ER,))
    du = per_point(window.duration, (ER,))
    ns = per_point(noise_std, (M, ER, h, w)) if isinstance(noise_std, torch.Tensor) and noise_std.dim() > 0 else noise_std
    mk = per_point(mask, (M, ER, h, w)) if mask is not None else None
    return pts, cen, cv, amp, st, du, om, ns, mk


def _failed(b: int, M: int, like: torch.Tensor) -> SpotFits:
    nan = torch.full((1, b, M), float("nan"), dtype=like.dtype, device=like.device)
    return SpotFits(amplitude=nan[..., None].repeat(1, 1, 1, 2), phase=nan[..., None].repeat(1, 1, 1, 2),
                    covariance=nan[..., None, None].repeat(1, 1, 1, 4, 4),
                    status=torch.full((1, b, M), NOT_CONVERGED, dtype=torch.long, device=like.device),
                    flags=torch.zeros((1, b, M), dtype=torch.long, device=like.device), reduced_chi2=nan, n_chunks=0)


def _gather(parts, P: int, F: int) -> SpotFits:
    cat = {k: torch.cat([getattr(p, k)[0] for p in parts], 0) for k in ("amplitude", "phase", "covariance", "status", "flags",
                                                                            "reduced_chi2")}
    shaped = {k: v.reshape((P, F) + tuple(v.shape[1:])) for k, v in cat.items()}
    return SpotFits(**shaped, n_chunks=sum(p.n_chunks for p in parts))


def fit_sharded(crops, psf, window, omega, *, client=None, shard_points: int = 16, noise_std=None, mask=None,
                fit_fn=fit_spot_problems, **fit_options) -> ShardedFits:
    """:func:`~torchblur.dm.spot_fit.fit_spot_problems` of a sweep, sharded over ``client``.

    Args:
        crops, psf, window, omega, noise_std, mask, **fit_options: as for
            :func:`~torchblur.dm.spot_fit.fit_spot_problems` (``crops`` ``[P, F, M, E*R, h, w]``,
            ``psf`` batch ``[M]``, ``window`` broadcastable to ``[P, F, E*R]``, ``omega`` ``[F]``).
        client: a ``distributed.Client``, or None (the shards run here, in order).
        shard_points: points (pattern, frequency) per shard, >= 1.
        fit_fn: the function a shard runs (``fit_spot_problems``; a test may inject a failure).

    Returns:
        :class:`ShardedFits`: batch ``[P, F, M]``, equal to the unsharded fit where every shard
        succeeded (each problem is fitted independently of its batch).
    """
    if not isinstance(crops, torch.Tensor) or crops.dim() != 6:
        raise ShapeError(f"crops: expected a tensor [P, F, M, E*R, h, w], got {getattr(crops, 'shape', type(crops).__name__)}")
    if not isinstance(window, ExposureWindow):
        raise InputTypeError(f"window: expected an ExposureWindow, got {type(window).__name__}")
    P, F, M = crops.shape[:3]
    shards = shard_ranges(P * F, shard_points)
    args = [_shard_args(crops, psf, window, omega, noise_std, mask, a, b) for a, b in shards]
    if client is None:
        results = []
        for a in args:
            try:
                results.append(_fit_shard(*a, fit_options, fit_fn))
            except Exception as e:  # noqa: BLE001 - a shard's failure is reported, not raised
                results.append(e)
    else:
        _check_client(client)
        futures = [client.submit(_fit_shard, *a, fit_options, fit_fn, pure=False) for a in args]
        results = [_result_of(f) for f in futures]  # in order; a failed shard gives its exception
    parts, failed = [], []
    for i, ((a, b), r) in enumerate(zip(shards, results)):
        if isinstance(r, BaseException):
            failed.append((i, f"{type(r).__name__}: {r}"))
            r = _failed(b - a, M, crops)
        parts.append(r)
    return ShardedFits(fits=_gather(parts, P, F), shards=shards, failed_shards=tuple(failed))


def _result_of(future):
    """The shard's SpotFits, or the exception it raised."""
    try:
        return future.result()
    except Exception as e:  # noqa: BLE001
        return e


def _check_client(client) -> None:
    try:
        import distributed
    except ImportError as e:
        raise ImportError("fit_sharded: a client needs Dask distributed: pip install 'torchblur[cluster]'") from e
    if not isinstance(client, distributed.Client):
        raise InputTypeError(f"client: expected a distributed.Client or None, got {type(client).__name__}")
