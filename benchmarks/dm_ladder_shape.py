"""A CANDIDATE measured and NOT landed: the DM ladder fit with the spot's shape given its own
command to FIRST order in it (issue 23, cause 2 of "Why the ladder's actuator stds fail on HCIPy's
frames" in docs/deformable_mirrors.md), measured against the run's
(:mod:`torchblur.dm.ladder_fit`, the shape's command exact) by
``benchmarks/bench_dm_spot_models.py --models fast,former,shape``: on noiseless HCIPy frames it
halves the former error at 2 kHz, but on noisy ones its stds do not hold on the spots whose
shape's command differs most from their motion's (the first order in ``w`` beyond its reach; the
docs give the figures). The functions that differ from ladder_fit's (the rest imported):
``_integrated_basis`` (second derivatives), ``_chains`` (the ``Dn^j Ds L`` blocks),
``_coefficients``, ``_report_jacobians``, ``_fit_chunk``, ``_store`` (ladder_fit's ``_chunk``,
``_model_jacobian``, ``_ladder_covariance``, ``_debias`` and ``_with_prior`` called with this
model's); a fallback to ``w = 0`` beyond :data:`SHAPE_REACH` (off; at 0.1 it held 26 of 80
problems at 2 kHz and gave the former error back).

The model (otherwise ladder_fit's):

Under a Hadamard pattern the surface under a lenslet is curved, so a real (diffraction) spot
changes shape as it moves; a shifted still (:func:`~torchblur.dm.spot_fit.fit_spot_problems`)
reads the change as motion. Here the spot's crop at time ``t`` of problem (pattern ``p``,
frequency ``f``, spot ``m``) is

    power * sum_j d(t)^j / j! Dn^j [L(u(t)) + w(t) (L'(u(t)) - Ds L(u(t)))],   j = 0..ORDER

- ``L(u)``: the static image (e-/s at laser power 1) of pattern ``p`` held at the scalar command
  ``u`` (every actuator ``j`` at ``u * pattern[j]``): a cubic spline in ``u`` per pixel through
  the ladder's levels (scipy's ``CubicSpline``, not-a-knot ends; beyond the ends its end cubics);
  ``Dn^j L`` its j-th derivatives along a shift of the image by ``n`` (Fourier, of each level's
  image, splined the same way, the spline being linear in the knot values);
- ``u(t) = gc cos(w t) + gs sin(w t)`` (the pattern's own response: the phasor ``G = gs + i gc``);
- ``w(t) = w_cos cos(w t) + w_sin sin(w t)``: the shape's own command less ``u``. To first order
  in ``w`` the bracket is the ladder's image at ``u + w`` moved back by ``s w`` (``L' = dL/du``,
  ``Ds`` the derivative along a shift by ``s``): the spot sits where ``u`` puts it and has the
  shape of ``u + w``. Where a pattern's actuators respond differently (above their modes) the
  curvature under a lenslet, which sets a spot's shape, follows another mix of actuators than
  its tilt, which sets its position; with the shape tied to ``u`` the fitted ``u`` was a
  compromise between the two, and the motions came out pulled toward the pattern's common
  command (``benchmarks/bench_dm_spot_models.py --models former,fast``). Where a spot barely
  changes shape (Gaussian spots), ``w`` is not seen: a prior ``w_cos, w_sin ~ N(0,``
  :data:`SHAPE_PRIOR` ``x`` the ladder's largest level ``)`` (two pseudo-data rows) keeps the LM
  and the covariance regular; the reported motion's covariance is marginal over ``w``. Its terms
  are carried to :data:`SHAPE_ORDER` in ``d``; the ladder's noise in ``Ds L`` and through ``s`` in
  ``Ds`` is left out (``w`` is small);
- ``d(t) = n_cos cos(w t) + n_sin sin(w t)``: a free motion (px) along ``n``, the unit normal of
  ``s`` (below), as the Taylor series of a shift to :data:`ORDER`. The actuators' differing
  dynamics move a spot off the ladder's path (near a resonance of the small simulated mirror by
  up to 1.2 px at 1.5 px of motion: to first order its responses were off by up to 15 stds; to
  fourth order a 1 px shift of a sigma-1.2 px spot is fitted within 0.06 %). Along the path
  ``u(t)`` (fitted per spot) carries the motion: a free motion there too would be the same image
  to first order (on a spot that only moves, exactly), a direction the data hardly see, and a
  free x and y motion gave the spot motions a bias of +0.35 std, the DC gains 1 % high;
- each exposure integrated by :data:`NODES` Gauss-Legendre nodes.

The model is linear in the ladder's images: an exposure is ``sum_jk c_jk(theta) Dn^j L_k`` (and ``Dn^j Ds L_k``), the coefficients from the spline's basis at the nodes, so the image and its analytic
Jacobian are one batched GEMM per problem; :func:`~torchblur.optim.levenberg_marquardt` fits the
six parameters. The reported motion per axis is the phasor ``s G + N n`` (``N = n_sin + i n_cos``; ``s = (s_x, s_y)``
the spot's static shift per unit ``u``: the slope at ``u = 0`` of the still's best shifts to the
levels' images, :func:`static_slope`, the convention of the fitted-shift truth), as amplitude and phase
with their covariance in :class:`~torchblur.dm.spot_fit.SpotFits`' order, so
:func:`~torchblur.dm.spot_fit.pattern_responses` turns it into ``Y`` unchanged.

Uncertainty: the data's part ``(J^T W J)^-1`` (with the noise given: unscaled, the reduced chi2
reported and :data:`~torchblur.fit.status.POOR_FIT_FLAG` above 1.5, as every fit here; without:
unweighted, the sandwich ``C J^T diag(r^2) J C`` of each pixel's residual, since shot noise
differs from pixel to pixel) plus the ladder's own noise, propagated to first
order through both the fit (``dtheta = -C J^T W dY/dL dL``, the implicit function theorem, as
:mod:`torchblur.fit.kernel_noise` does for a kernel) and ``s``, every ladder pixel independent
with its ``variance``. The still's noise (averaged over many more frames than a level) is left
out. The reduced chi2 weighs each pixel by the data's variance plus the model's from the ladder
(its ``L`` and ``Dn L`` terms: the higher orders' noise, as in the bias correction, is left out).

Shapes: P patterns, F frequencies, M spots, K levels, ``E*R`` exposures, ``h x w`` crop pixels;
positions and motions in px (x = column, y = row), times in s, ``omega`` rad/s.
"""
from __future__ import annotations

import math
from functools import partial

import torch

from torchblur.dm.ladder_fit import (LEFT_MAX, MAX_ITER, ORDER, PRIOR_ROWS, PatternLadder, _basis_at, _Chunk, _chunk, _debias,
                                     _flat_problems, _ladder_covariance, _model_jacobian, _nodes, _normal, _prefit_status, _Problems,
                                     _starts, _with_prior)
from torchblur.dm.spot_fit import SpotFits, chunk_size
from torchblur.errors import ShapeError, check_int
from torchblur.fit.status import MASKED, NO_MOTION, NOT_CONVERGED, OUT_OF_LADDER, SINGULAR, flag_poor_fit
from torchblur.optim import levenberg_marquardt


N_PAR = 6  #: (gc, gs, n_cos, n_sin, w_cos, w_sin): the command phasor, the free motion across the static shift, the shape's own command
SHAPE_ORDER = 2  #: the free motion's Taylor order in the shape's term ``w (L' - Ds L)`` (:func:`_coefficients`)
SHAPE_HELD = 256  #: flag: the problem refitted with ``w = 0`` (:data:`SHAPE_REACH`)
SHAPE_REACH = math.inf  #: ``|w| / |G|`` (phasors) beyond which the shape's first-order term is not trusted: refitted with ``w = 0``, :data:`SHAPE_HELD`
HELD_PRIOR = 1e-12  #: the prior std of ``w`` (of the ladder's largest level) that holds it at 0
SHAPE_PRIOR = 0.25  #: the prior std of the shape's command ``w`` (each of ``w_cos, w_sin``), of the ladder's largest level


def _integrated_basis(u, weights, knots, coef):
    """``[n, E, G0 + G1 + G2, K]``: ``sum_s weights[r][..., g, s] d^r B/du^r (u_s)`` for ``r = 0, 1, 2``
    (the basis and its first two derivatives) at nodes ``u [n, E, S]`` (``weights[r] [n, E, Gr, S]``;
    ``knots``, ``coef`` as :func:`_basis_at`). Each node's powers of its offset in its interval are placed in that
    interval's slots (``[S, 4 (K - 1)]``, zero elsewhere), the weights summed into the slots by one
    GEMM, then one product with the basis's coefficients: no ``[S, 4, K]`` per node."""
    n, K = knots.shape
    E, S = u.shape[1:]
    flat = u.reshape(n, -1)
    i = (torch.searchsorted(knots, flat.contiguous()) - 1).clamp(0, K - 2)
    d = (flat - torch.gather(knots, 1, i)).reshape(n, E, S, 1)
    one, zero = torch.ones_like(d), torch.zeros_like(d)
    slot = 4 * i.reshape(n, E, S, 1) + torch.arange(4, device=u.device)  # [n, E, S, 4]
    powers = ((d * d * d, d * d, d, one), (3 * d * d, 2 * d, one, zero), (6 * d, 2 * one, zero, zero))
    acc = []
    for w, pw in zip(weights, powers):
        Z = torch.zeros(n, E, S, 4 * (K - 1), dtype=u.dtype, device=u.device).scatter_(-1, slot, torch.cat(pw, -1))
        acc.append(w @ Z)  # [n, E, Gr, 4 (K - 1)]
    acc = torch.cat(acc, 2)
    return (acc.reshape(n, -1, 4 * (K - 1)) @ coef.reshape(n, 4 * (K - 1), K)).reshape(acc.shape[:3] + (K,))


def _chains():
    """The ladder's blocks: ``[top_0, top_1]``, ``Dn^j Ds^k L`` for ``j <= top_k`` (in that order)."""
    return [ORDER, SHAPE_ORDER]


def _coefficients(theta, prob: _Problems, ch: _Chunk, idx):
    """``(C [n, E, 1 + N_PAR, R + RW, K], u [n, E, S])``: the image (row 0) and its derivatives along
    the parameters (rows 1-6) of problems ``idx`` (of the chunk) as weights of the ladder's blocks
    (``Dn^j L``, ``j < R = ORDER + 1``, then ``Dn^j Ds L``, ``j < RW = SHAPE_ORDER + 1``) of every
    level, already integrated over each exposure's nodes (s). The module docstring's model:
    ``sum_j d^j / j! Dn^j [L(u) + w (L'(u) - Ds L(u))]`` (the ``w`` terms to ``j <= SHAPE_ORDER``),
    ``L' = dL/du`` the spline's derivative."""
    cw, sw, wq = _nodes(prob, ch.pf[idx])
    u = theta[:, 0, None, None] * cw + theta[:, 1, None, None] * sw
    d = theta[:, 2, None, None] * cw + theta[:, 3, None, None] * sw  # [n, E, S] px along n
    w = theta[:, 4, None, None] * cw + theta[:, 5, None, None] * sw  # [n, E, S] the shape's command minus u
    R, RW = ORDER + 1, SHAPE_ORDER + 1
    T = [wq * d ** j / math.factorial(j) for j in range(R)]  # the Taylor terms' weights d^j / j!
    terms = ([], [], [])  # per derivative order of the basis: (row, block, weight [n, E, S])
    for j in range(R):
        terms[0].append((0, j, T[j]))
        for r, c in ((1, cw), (2, sw)):
            terms[1].append((r, j, c * T[j]))
            if j:
                terms[0].append((r + 2, j, c * T[j - 1]))
        if j < RW:  # the shape's terms: on Dn^j L through L', on Dn^j Ds L through L
            terms[1].append((0, j, w * T[j]))
            terms[0].append((0, R + j, -w * T[j]))
            for r, c in ((1, cw), (2, sw)):
                terms[2].append((r, j, c * w * T[j]))
                terms[1].append((r, R + j, -c * w * T[j]))
                terms[1].append((r + 4, j, c * T[j]))
                terms[0].append((r + 4, R + j, -c * T[j]))
                if j:
                    terms[1].append((r + 2, j, c * w * T[j - 1]))
                    terms[0].append((r + 2, R + j, -c * w * T[j - 1]))
    out = _integrated_basis(u, [torch.stack([t[2] for t in g], 2) for g in terms], prob.knots[ch.pat[idx]], prob.coef[ch.pat[idx]])
    n, E, K = out.shape[0], out.shape[1], out.shape[-1]
    where = torch.tensor([r * (R + RW) + b for g in terms for r, b, _ in g], device=out.device)
    C = out.new_zeros(n, E, (N_PAR + 1) * (R + RW), K).index_add_(2, where, out)
    return C.reshape(n, E, N_PAR + 1, R + RW, K), u


def _report_jacobians(theta, slope):
    """``(amplitude [c, 2], phase [c, 2], H_theta [c, 4, 4], H_s [c, 4, 2])``: the motion per
    axis ``s_a G + n_a N`` (``N = n_sin + i n_cos``, ``n`` :func:`_normal`, held fixed: the
    fitted ``G`` takes up a turn of it to first order) as amplitude and phase, and its Jacobians
    along ``theta`` and ``s`` in the order (amplitude_x, phase_x, amplitude_y, phase_y)."""
    c = theta.shape[0]
    gc, gs = theta[:, 0], theta[:, 1]
    nrm = _normal(slope)
    re = slope * gs[:, None] + nrm * theta[:, 3, None]  # [c, 2]: Re of x and y
    im = slope * gc[:, None] + nrm * theta[:, 2, None]
    cart_t = torch.zeros(c, 4, N_PAR, dtype=theta.dtype, device=theta.device)  # rows Re_x, Im_x, Re_y, Im_y
    cart_s = torch.zeros(c, 4, 2, dtype=theta.dtype, device=theta.device)
    for a in range(2):
        cart_t[:, 2 * a, 1], cart_t[:, 2 * a, 3] = slope[:, a], nrm[:, a]
        cart_t[:, 2 * a + 1, 0], cart_t[:, 2 * a + 1, 2] = slope[:, a], nrm[:, a]
        cart_s[:, 2 * a, a], cart_s[:, 2 * a + 1, a] = gs, gc
    amp = torch.hypot(re, im)
    a2 = amp.square().clamp_min(torch.finfo(amp.dtype).tiny)
    polar = torch.zeros(c, 4, 4, dtype=theta.dtype, device=theta.device)
    for a in range(2):
        polar[:, 2 * a, 2 * a], polar[:, 2 * a, 2 * a + 1] = re[:, a] / a2[:, a].sqrt(), im[:, a] / a2[:, a].sqrt()
        polar[:, 2 * a + 1, 2 * a], polar[:, 2 * a + 1, 2 * a + 1] = -im[:, a] / a2[:, a], re[:, a] / a2[:, a]
    return amp, torch.atan2(im, re), polar @ cart_t, polar @ cart_s


def _fit_chunk(prob: _Problems, ch: _Chunk, theta0, prior: float):
    """Fit one chunk from ``theta0 [c, N_PAR]`` (ladder_fit's own start, :func:`~torchblur.dm.ladder_fit._starts`) with the shape prior ``prior`` (:data:`SHAPE_PRIOR` or :data:`HELD_PRIOR`):
    ``dict`` of ``[c]``-batched amplitude, phase, covariance, status, flags, reduced_chi2, reach (``|w| / |G|``)."""
    c = ch.rows.numel()
    E = prob.shape[3]
    data, W = prob.data[ch.rows].reshape(c, -1), prob.weight[ch.rows].reshape(c, -1)
    q = data.shape[1]
    sigma = prior * prob.knots.abs().amax(-1)[ch.pat]  # [c] the prior std of w_cos and w_sin
    data_x = torch.cat([data, data.new_zeros(c, PRIOR_ROWS)], -1)
    W_x = torch.cat([W, W.new_ones(c, PRIOR_ROWS)], -1)
    jac = _with_prior(prob, ch, sigma, model_jacobian=partial(_model_jacobian, coefficients=_coefficients))
    res = levenberg_marquardt(lambda th, i: jac(th, i)[0], theta0, data_x, weight=W_x, max_iter=MAX_ITER,
                              jacobian_fn=jac, gn_tol=1e-2)
    theta = res.theta
    all_c = torch.arange(c, device=theta.device)
    used = (W > 0).sum(-1).to(theta.dtype)
    dof = (used - N_PAR + PRIOR_ROWS).clamp_min(1)
    s2 = torch.ones(c, dtype=theta.dtype, device=theta.device) if prob.noise_given else ((data - jac(theta, all_c)[0][:, :q]).square() * W).sum(-1) / dof
    theta, model, J, Cw, info, left = _debias(theta, data_x, W_x, s2, prob, ch, jac, coefficients=_coefficients)
    model, Jp = model[:, :q], J[:, :q]
    r2 = (data - model).square()
    converged = res.converged | (left < LEFT_MAX ** 2)  # the LM's own test, or the step left is short (noiseless data too)
    amp, phase, H_t, H_s = _report_jacobians(theta, ch.slope)
    cov_l, var_model = _ladder_covariance(theta, prob, ch, Jp, W, Cw, H_t, H_s, coefficients=_coefficients, tops=_chains())
    if prob.noise_given:
        cov_d = Cw
    else:  # the sandwich with each pixel's own squared residual (the noise differs from pixel to pixel: shot noise), plus the prior's information
        WJ = (W * W * r2)[..., None] * Jp
        cov_d = Cw @ (Jp.transpose(1, 2) @ WJ + J[:, q:].transpose(1, 2) @ J[:, q:]) @ Cw
    cov = H_t @ cov_d @ H_t.transpose(1, 2) + cov_l
    chi2 = torch.full((c,), float("nan"), dtype=theta.dtype, device=theta.device)
    if prob.noise_given:
        sig2 = torch.where(W > 0, 1 / W.clamp_min(torch.finfo(W.dtype).tiny), torch.zeros_like(W)) + var_model.reshape(c, -1)
        chi2 = torch.where(W > 0, r2 / sig2, torch.zeros_like(r2)).sum(-1) / dof
    status = torch.zeros(c, dtype=torch.long, device=theta.device)
    status[~converged] = NOT_CONVERGED
    d = torch.diagonal(cov, dim1=-2, dim2=-1)
    status[(info != 0) | ~torch.isfinite(cov).flatten(1).all(-1) | (d <= 0).any(-1) | ~torch.isfinite(theta).all(-1)] = SINGULAR
    cw, sw, _ = _nodes(prob, ch.pf)
    u = theta[:, 0, None, None] * cw + theta[:, 1, None, None] * sw  # the command at the nodes, as in _coefficients
    flags = OUT_OF_LADDER * ((u.flatten(1).amin(-1) < prob.knots[ch.pat, 0]) | (u.flatten(1).amax(-1) > prob.knots[ch.pat, -1])).long()
    flags = flags | NO_MOTION * ((amp / d[:, ::2].clamp_min(0).sqrt() < 3).any(-1)).long()
    reach = theta[:, 4:].norm(dim=-1) / theta[:, :2].norm(dim=-1).clamp_min(torch.finfo(theta.dtype).tiny)  # |w| / |G|
    return dict(amplitude=amp, phase=phase, covariance=cov, status=status, flags=flag_poor_fit(flags, chi2), reduced_chi2=chi2, reach=reach)


def _store(out, rows, r):
    """Write a chunk's results ``r`` (:func:`_fit_chunk`) into ``out`` at ``rows`` (NaN estimates where status != 0; flags or-ed)."""
    ok = r["status"] == 0
    for key in ("amplitude", "phase", "covariance"):
        r[key][~ok] = float("nan")
    for key, v in r.items():
        if key != "reach":
            out[key][rows] = out[key][rows] | v if key == "flags" else v


def fit_ladder_problems(crops, ladder: PatternLadder, window, omega, amplitude, *, power, noise_std=None, mask=None, chunk=None,
                        device=None) -> SpotFits:
    """Fit every (pattern, frequency, spot) problem with the ladder's model (module docstring).

    Args:
        crops: ``[P, F, M, E*R, h, w]`` electrons (:func:`~torchblur.dm.spot_fit.crop_problems`);
            its floating dtype is the fit's (an integer one: float64).
        ladder: :class:`PatternLadder` of the same P patterns, M spots and crop.
        window: :class:`ExposureWindow` broadcastable to ``[P, F, E*R]`` (s).
        omega: ``[F]`` rad/s.
        amplitude: the command amplitude (input units) broadcastable to ``[P, F]``: the start
            where the centroids give none.
        power: the sweep frames' laser power relative to the ladder's, ``[F]`` or a number.
        noise_std: pixel noise std broadcastable to the crops (e.g. the camera noise of the
            expected signal), or None (unweighted, the covariance from each pixel's residual;
            ``reduced_chi2`` NaN).
        mask: bool broadcastable to the crops (False: excluded), or None.
        chunk: problems per chunk; None: :func:`~torchblur.dm.spot_fit.chunk_size` with the
            chunk's ``E*R + 3K`` planes per problem (the data and the ladder's three images per level).
        device: where to fit (None: the crops').

    Returns:
        :class:`~torchblur.dm.spot_fit.SpotFits` ``[P, F, M]`` (on ``device``): per axis the
        phasor ``s G + N n`` (module docstring) as amplitude (px) and phase (rad), the covariance of both axes
        with the ladder's noise, ``status`` (non-zero: NaN estimates), ``flags``
        (:data:`~torchblur.fit.status.OUT_OF_LADDER`, ``NO_MOTION``, ``MASKED``, ``POOR_FIT_FLAG``).
    """
    if not isinstance(crops, torch.Tensor):
        raise ShapeError(f"crops: expected a tensor [P, F, M, E*R, h, w], got {type(crops).__name__}")
    dev = torch.device(device) if device is not None else crops.device
    like = dict(dtype=crops.dtype if crops.is_floating_point() else torch.float64, device=dev)
    prob = _flat_problems(crops, ladder, window, omega, amplitude, power, noise_std, mask, like)
    P, F, M, E, h, w = prob.shape
    K = ladder.levels.shape[1]
    n = P * F * M
    b0 = _basis_at(torch.zeros(P, 1, **like), prob.knots, prob.coef)
    b0 = (b0[0][:, 0], b0[1][:, 0])  # [P, K] each: the basis and its derivative at u = 0
    chunk = chunk_size(2 * E + 4 * K, h, w, device=dev, dtype=like["dtype"]) if chunk is None else check_int(chunk, "chunk", low=1)
    status = _prefit_status(prob, ladder.still)
    nan = torch.full((n,), float("nan"), **like)
    out = dict(amplitude=nan[:, None].repeat(1, 2), phase=nan[:, None].repeat(1, 2), covariance=nan[:, None, None].repeat(1, 4, 4),
               status=status, flags=MASKED * (~prob.keep).flatten(1).any(-1).long(), reduced_chi2=nan.clone())
    todo = torch.nonzero(status == 0).reshape(-1)
    n_chunks = 0
    for i0 in range(0, todo.numel(), chunk):
        ch = _chunk(prob, ladder, todo[i0:i0 + chunk], like, tops=_chains())
        with torch.no_grad():
            theta0 = _starts(prob, ladder, ch.rows, b0, ch.rows.numel())[:, 0]  # each spot's own start (the pooled one not used here)
            r = _fit_chunk(prob, ch, theta0, SHAPE_PRIOR)
            _store(out, ch.rows, r)
            far = r["reach"] > SHAPE_REACH  # the shape's first-order term out of its reach: refitted with the shape held at u
            if bool(far.any()):
                ch = _chunk(prob, ladder, ch.rows[far], like, tops=_chains())
                r = _fit_chunk(prob, ch, theta0[far], HELD_PRIOR)
                r["flags"] = r["flags"] | SHAPE_HELD
                out["flags"][ch.rows] &= MASKED  # the first fit's flags replaced
                _store(out, ch.rows, r)
        n_chunks += 1
    return SpotFits(**{k: v.reshape((P, F, M) + tuple(v.shape[1:])) for k, v in out.items()}, n_chunks=n_chunks)

