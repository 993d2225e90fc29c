"""Fits of the sweep's points while the sweep runs: :class:`ChunkFitter` fits completed
points in chunks on a background thread; :func:`concat_fits` and :func:`squeeze_problems`
put the chunks' :class:`~torchblur.fit.sinusoid.SinusoidFit` together."""
from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields as dc_fields

import torch

from torchblur.fit.sinusoid import SinusoidFit

__all__ = ["ChunkFitter", "concat_fits", "squeeze_problems"]


class ChunkFitter:
    """Fits completed sweep points in chunks of ``chunk`` points on a background thread, so
    fitting overlaps the acquisition of the next points (``chunk`` 0: everything at the end,
    in the calling thread). Chunk boundaries depend only on the point index, so the result
    does not depend on timing."""

    def __init__(self, chunk: int, fit_fn):
        self.chunk, self.fit_fn = int(chunk), fit_fn
        self.pending: list[int] = []
        self.jobs: list = []
        self.busy_s = 0.0
        self.spans: list[tuple[float, float]] = []  # (start, end) of each chunk's fit, perf_counter seconds
        self._lock = threading.Lock()
        self._time = time.perf_counter
        self._exec = None
        if self.chunk > 0:
            self._exec = ThreadPoolExecutor(max_workers=1, thread_name_prefix="torchblur-fit")

    def _timed(self, idx):
        t0 = self._time()
        try:
            return self.fit_fn(idx)
        finally:
            with self._lock:
                self.busy_s += self._time() - t0
                self.spans.append((t0, self._time()))

    def add(self, k: int) -> None:
        self.pending.append(k)
        if self.chunk > 0 and len(self.pending) >= self.chunk:
            idx, self.pending = self.pending, []
            self.jobs.append((idx, self._exec.submit(self._timed, idx)))

    def finish(self):
        """Fit what is left and return ``[(point indices, SinusoidFit), ...]`` in order."""
        if self.pending:
            idx, self.pending = self.pending, []
            self.jobs.append((idx, _Done(self._timed(idx))))
        out = [(idx, job.result()) for idx, job in self.jobs]
        self.close()
        return out

    def close(self):
        if self._exec is not None:
            self._exec.shutdown(wait=False, cancel_futures=True)
            self._exec = None


class _Done:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


def concat_fits(parts):
    """One SinusoidFit from per-chunk fits (batch dims first), in point order."""
    if len(parts) == 1:
        return parts[0]
    kw = {}
    for f in dc_fields(SinusoidFit):
        vals = [getattr(p, f.name) for p in parts]
        if isinstance(vals[0], torch.Tensor):
            kw[f.name] = torch.cat(vals, 0)
        elif f.name == "extras":
            kw[f.name] = {"chunks": [dict(v) for v in vals]}
        else:
            kw[f.name] = vals[0]
    return SinusoidFit(**kw)


def squeeze_problems(fit):
    """A SinusoidFit of batch ``[n, 1]`` as batch ``[n]`` (one problem per point)."""
    kw = {}
    for f in dc_fields(SinusoidFit):
        v = getattr(fit, f.name)
        kw[f.name] = v.squeeze(1) if isinstance(v, torch.Tensor) and v.dim() >= 2 and v.shape[1] == 1 else v
    return SinusoidFit(**kw)
