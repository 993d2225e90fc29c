"""benchmarks/bench_dm_hcipy.py's pull figures (issue 23): a pull planted in synthetic pattern responses
is read back at the spot level, and the actuators' pull left once it is taken out is ~0; the mode line's
slope reads a planted shrink of the modes toward their mean."""
from __future__ import annotations

import os
import re
import sys
from types import SimpleNamespace

import numpy as np
import scipy.linalg

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "benchmarks"))

import bench_dm_hcipy as bench  # noqa: E402


class _Dyn:
    def __init__(self, rng, N):
        self.mode_hz = 1000.0 * (1 + 0.05 * rng.standard_normal(N))
        self.damping = np.full(N, 0.1)
        self.gain = np.ones(N)
        self.dead = np.zeros(N, dtype=bool)

    def response(self, f):
        s = 2j * np.pi * np.asarray(f, dtype=float)[..., None]
        w = 2 * np.pi * self.mode_hz
        return (self.gain * w ** 2 / (s ** 2 + 2 * self.damping * w * s + w ** 2))[..., :]


def test_a_planted_pull_is_read_back_at_the_spot_and_actuator_level():
    rng = np.random.default_rng(0)
    N, S2, freqs, b0 = 12, 40, np.array([10.0, 1500.0]), -0.03 - 0.01j
    P = scipy.linalg.hadamard(16)[:, :N].astype(float)
    G = rng.normal(size=(S2, N))
    dyn = _Dyn(rng, N)
    Y = np.zeros((16, S2, len(freqs)), dtype=complex)
    for k, f in enumerate(freqs):
        H = dyn.response(f)
        Yt, Yc = (P * H[None]) @ G.T, (P * np.full(N, H.mean())[None]) @ G.T
        Y[:, :, k] = Yt + b0 * (Yt - Yc)
    cov = np.broadcast_to(np.eye(2) * 1e-6, Y.shape + (2, 2)).copy()
    res = SimpleNamespace(plan=SimpleNamespace(patterns=P, support=None), Y=Y, Y_cov=cov, freq_hz=freqs,
                          D_cov=np.broadcast_to(np.eye(2) * 1e-6, (S2, N, len(freqs), 2, 2)).copy(), G=G)
    lines = bench.spot_pull_lines(res, {"shift_slopes": G}, dyn)
    b = complex(*map(float, re.search(r"b ([+-][\d.]+) ([+-][\d.]+)i over", lines[1]).groups()))
    left = complex(*map(float, re.search(r"taken out ([+-][\d.]+) ([+-][\d.]+)i", lines[1]).groups()))
    assert abs(b - b0) < 1e-3 and abs(left) < 1e-3, lines


def test_the_mode_line_reads_a_shrink_toward_the_mean():
    rng = np.random.default_rng(1)
    dyn = _Dyn(rng, 30)
    mean = dyn.mode_hz.mean()
    est = dyn.mode_hz * (1 - 0.05 * (dyn.mode_hz / mean - 1))  # every mode's relative deviation shrunk by 5 %
    res = SimpleNamespace(actuators=SimpleNamespace(mode_hz=est, mode_hz_std=np.full(30, 0.5)))
    line = bench.mode_pull_line(res, dyn)
    slope = float(re.search(r"slope ([+-][\d.]+)", line).group(1))
    assert abs(slope + 0.05) < 2e-3 and line.endswith("with the slope taken out 0.00"), line


def test_the_demultiplexing_chi2_reads_consistent_and_planted_inconsistent_responses():
    """``demux_chi2``: pattern responses of one ``D`` with noise of their stated covariance give chi2/dof
    about 1 (Hadamard: 16 patterns, 12 unknowns per row); a gain planted on one pattern raises it at its
    frequency only; a plan without redundant patterns (one at a time) gives NaN. ``lost_entries_line``
    counts the NaN entries of ``D`` and names the driven patterns lost on the item with the most."""
    from torchblur.dm.demux import demultiplex

    rng = np.random.default_rng(4)
    N, S2, F = 12, 40, 2
    P = scipy.linalg.hadamard(16)[:, :N].astype(float)
    D = rng.normal(size=(S2, N, F)) + 1j * rng.normal(size=(S2, N, F))
    sd = 1e-2
    Y = np.einsum("pn,snf->psf", P, D) + sd * (rng.normal(size=(16, S2, F)) + 1j * rng.normal(size=(16, S2, F)))
    Y[3, :, 1] *= 1.05  # one pattern's gain off at the second frequency
    cov = np.broadcast_to(np.eye(2) * sd ** 2, Y.shape + (2, 2)).copy()
    plan = SimpleNamespace(patterns=P, support=np.ones((S2, N), dtype=bool))
    De, Dc = demultiplex(Y, cov, P)
    chi2 = bench.demux_chi2(SimpleNamespace(plan=plan, Y=Y, Y_cov=cov, D=De))
    assert abs(chi2[0] - 1) < 0.15 and chi2[1] > 10, chi2
    eye = SimpleNamespace(patterns=np.eye(N), support=np.ones((S2, N), dtype=bool))
    Y1 = np.einsum("pn,snf->psf", np.eye(N), D)
    cov1 = np.broadcast_to(np.eye(2) * sd ** 2, Y1.shape + (2, 2)).copy()
    assert np.isnan(bench.demux_chi2(SimpleNamespace(plan=eye, Y=Y1, Y_cov=cov1, D=demultiplex(Y1, cov1, np.eye(N))[0]))).all()
    Y1[5, 7, 0] = np.nan  # one lost fit of a pattern of its own: one entry of D
    res = SimpleNamespace(plan=SimpleNamespace(patterns=np.eye(N), support=np.ones((S2, N), dtype=bool)), Y=Y1,
                          D=demultiplex(Y1, cov1, np.eye(N))[0], freq_hz=np.array([10.0, 20.0]))
    assert bench.lost_entries_line(res) == ("D entries the failed spot fits left undetermined: 1 on 1 (slope row, frequency) items, "
                                            "at most 1 of 12 on one (row 7 at 10 Hz, patterns 5 lost there)")
