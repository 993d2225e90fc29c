"""A Gaussian splat together with its derivatives with respect to parameters that move the nodes.

A fitter whose parameters ``theta`` move the spot's quadrature nodes needs the rendered image
and ``d image / d theta_k``. Forward-mode AD through the renderer costs about three renders
per parameter; :func:`gaussian_splat_with_jacobian` reuses the exponentials of one tiled splat
(the tile size rule, symmetric split of the exponent, float64 upcast and clamping of
:func:`torchblur.render.blur._gaussian_tiled`) for the image and all ``Q`` derivatives.

Derivation. In a tile with centre ``(Xc, Yc)`` and local coordinates ``X, Y`` the exponent of
node ``s`` is ``E_s = f_s(X) + g_s(Y) - B X Y`` with ``a_s = px_s - Xc``, ``b_s = py_s - Yc``,
``z1 = A a + B b``, ``z2 = B a + C b``, ``f = -A/2 X^2 + z1 X - q/4``, ``g = -C/2 Y^2 + z2 Y - q/4``,
so ``dE_s/dpx_s = (A X + B Y) - z1_s`` and ``dE_s/dpy_s = (B X + C Y) - z2_s``. Collected per
parameter,

    dE_s/dtheta_k = X alpha_sk + Y beta_sk - gamma_sk,
    alpha = A dpx + B dpy,  beta = B dpx + C dpy,  gamma = z1 dpx + z2 dpy  (gamma per tile).

``Y`` does not depend on the node, so it multiplies after the sum over nodes; ``X`` rides on
the column factor:

    image = exp(-B X Y) * sum_s (w_s exp(g_s(Y))) exp(f_s(X)),
    jac_k = exp(-B X Y) * [ Y * sum_s (w beta_k)_s exp(g_s) exp(f_s)
                            + sum_s exp(g_s) (w (X alpha_k - gamma_k))_s exp(f_s) ].

That is ``1 + 2 Q`` GEMMs (instead of ``1 + 4 Q`` with the px and py terms kept apart) that
share the row factor ``exp(g)``: one matmul ``exp(g)^T @ R``, batched over frames and tiles,
with the column-factor variants ``R = exp(f) * [w, w beta_k, w (X alpha_k - gamma_k)]`` stacked
along a dimension in front of the tile's columns (``[S, (1 + 2Q) * Tw]``). The variants go on the
narrower of the two tile sides (the problem is transposed when tiles are wider than tall).

The work is done in chunks of frames (tens of MB of temporaries each): outside the matmul the
splat is limited by memory traffic, and chunks keep it near the cache and the memory bounded.
"""
from __future__ import annotations

import functools
import math

import torch

from torchblur.errors import InputTypeError, ParameterError, ShapeError
from torchblur.render.blur import _exp_budget, _exp_floor, _tile_grid

__all__ = ["gaussian_splat_with_jacobian", "sine_blur_with_jacobian", "window_nodes"]

# Temporaries of one chunk of frames. Cache-sized chunks (~8 MB) were no faster than this on an
# idle 2-core machine, and many small ops are far slower when the cores are shared.
_CHUNK_BYTES = 32e6


def gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, height, width):
    """Gaussian splat (point-sampled pixels) and its Jacobian with respect to node-moving parameters.

    Args:
        px, py: node positions (px) ``[..., S]`` (x = column j, y = row i).
        dpx, dpy: their derivatives with respect to ``Q`` parameters ``[..., S, Q]``.
        w: node weights ``[..., S]`` (quadrature weight * duration * PSF amplitude).
        A, B, C: precision entries ``[...]`` (``cov^-1 = [[A, B], [B, C]]``).
        height, width: frame size H, W in pixels.

    Returns:
        ``(image [..., H, W], jac [..., Q, H, W])`` with
        ``image[..., i, j] = sum_s w_s exp(-q(u, v) / 2)``, ``q(u, v) = A u^2 + 2 B u v + C v^2``,
        ``u = j - px_s``, ``v = i - py_s``, and
        ``jac[..., k, i, j] = sum_s w_s exp(-q/2) ((A u + B v) dpx_sk + (B u + C v) dpy_sk)``,
        i.e. ``d image / d theta_k`` when ``dpx = d px / d theta``, ``dpy = d py / d theta``.

    The batch shapes ``[...]`` of all inputs broadcast. Inputs of 32 bits or fewer are
    computed in float64 and the results cast back to the inputs' dtype, as the renderer does
    for tilted PSFs. ``B == 0`` needs no special case. The outputs are differentiable by
    autograd in every input (the tile size is chosen from detached values), and may be
    non-contiguous views.

    Example:
        >>> S, Q = 16, 2
        >>> px, py = torch.linspace(10, 20, S), torch.full((S,), 12.0)
        >>> dpx, dpy = torch.stack((torch.ones(S), torch.zeros(S)), -1), torch.stack((torch.zeros(S), torch.ones(S)), -1)
        >>> img, jac = gaussian_splat_with_jacobian(px, py, dpx, dpy, torch.full((S,), 1 / S),
        ...     torch.tensor(0.3), torch.tensor(-0.1), torch.tensor(0.4), 24, 32)
        >>> img.shape, jac.shape
        (torch.Size([24, 32]), torch.Size([2, 24, 32]))
    """
    for name, val in (("height", height), ("width", width)):
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ParameterError(f"{name}: expected an integer >= 1, got {val!r}")
    names = ("px", "py", "dpx", "dpy", "w", "A", "B", "C")
    args = (px, py, dpx, dpy, w, A, B, C)
    for name, val in zip(names, args):
        if not isinstance(val, torch.Tensor):
            raise InputTypeError(f"{name}: expected a torch.Tensor, got {type(val).__name__}")
        if val.is_complex():
            raise InputTypeError(f"{name}: expected a real tensor, got {val.dtype}")
    dtype = functools.reduce(torch.promote_types, (v.dtype for v in args))
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    wide = torch.float64 if torch.finfo(dtype).bits <= 32 else dtype
    device = px.device
    px, py, dpx, dpy, w, A, B, C = (v.to(device=device, dtype=wide) for v in args)
    for name, val, nd in (("px", px, 1), ("py", py, 1), ("w", w, 1), ("dpx", dpx, 2), ("dpy", dpy, 2)):
        if val.dim() < nd:
            raise ShapeError(f"{name}: expected at least {nd} dimension(s), got shape {tuple(val.shape)}")
    S, nq = px.shape[-1], dpx.shape[-1]
    try:
        batch = torch.broadcast_shapes(
            px.shape[:-1], py.shape[:-1], w.shape[:-1], dpx.shape[:-2], dpy.shape[:-2], A.shape, B.shape, C.shape
        )
        px, py, w = (v.expand(batch + (S,)) for v in (px, py, w))
        dpx, dpy = (v.expand(batch + (S, nq)) for v in (dpx, dpy))
        A, B, C = (v.expand(batch) for v in (A, B, C))
    except RuntimeError as exc:
        raise ShapeError(
            f"px, py, w [..., S], dpx, dpy [..., S, Q], A, B, C [...]: shapes do not broadcast "
            f"({', '.join(f'{n} {tuple(v.shape)}' for n, v in zip(names, args))}): {exc}"
        ) from None
    image, jac = _splat_jacobian(px, py, dpx, dpy, w, A, B, C, height, width)
    return image.to(dtype), jac.to(dtype)


def _splat_jacobian(px, py, dpx, dpy, w, A, B, C, H, W):
    """Broadcast inputs of one floating dtype -> (image [..., H, W], jac [..., Q, H, W])."""
    dtype, device = px.dtype, px.device
    batch = A.shape
    S, nq = px.shape[-1], dpx.shape[-1]
    lo = _exp_floor(dtype)
    # Tile size: the rule of _gaussian_tiled.
    kappa = float((torch.maximum(A, C) + B.abs()).detach().max()) if A.numel() else 1.0
    if not (math.isfinite(kappa) and kappa > 0):
        raise ParameterError(f"A, B, C: expected a finite positive definite precision, got max(A, C) + |B| = {kappa}")
    t_max = max(1, int(2 * math.sqrt(_exp_budget(dtype) / kappa)) - 1)
    nh, nw = -(-H // t_max), -(-W // t_max)
    if -(-H // nh) < -(-W // nw):  # tiles wider than tall: transpose, the variants go on the short side
        image, jac = _splat_jacobian(py, px, dpy, dpx, w, C, B, A, W, H)
        return image.transpose(-1, -2), jac.transpose(-1, -2)
    Th, Yc, ly = _tile_grid(H, nh, dtype, device, None)
    Tw, Xc, lx = _tile_grid(W, nw, dtype, device, None)
    P, R = Yc.numel(), Xc.numel()
    V = 1 + 2 * nq

    # Frames flattened to N; per-node quantities for all frames at once (small).
    N = math.prod(batch)
    px, py, w = (v.reshape(N, S) for v in (px, py, w))
    dpx, dpy = (v.reshape(N, S, nq) for v in (dpx, dpy))
    A, B, C = (v.reshape(N) for v in (A, B, C))
    An, Bn, Cn = (v[:, None, None, None] for v in (A, B, C))
    a = px[:, None, None, :] - Xc[:, None]  # [N, 1, R, S]
    b = py[:, None, None, :] - Yc[:, None, None]  # [N, P, 1, S]
    z1 = An * a + Bn * b  # [N, P, R, S]
    z2 = Bn * a + Cn * b
    qf = ((An * a * a + 2 * Bn * a * b + Cn * b * b) / 4)[..., None]  # [N, P, R, S, 1]
    hx = ((-0.5 * A[:, None]) * lx * lx)[:, None, None, None, :]  # [N, 1, 1, 1, Tw]
    hy = ((-0.5 * C[:, None]) * ly * ly)[:, None, None, None, :]  # [N, 1, 1, 1, Th]
    Aq, Bq, Cq, wq = A[:, None, None], B[:, None, None], C[:, None, None], w[..., None]
    wdx, wdy = dpx * wq, dpy * wq  # [N, S, Q]
    alpha = (Aq * wdx + Bq * wdy)[:, None, None, :, :, None]  # [N, 1, 1, S, Q, 1]
    beta = (Bq * wdx + Cq * wdy)[:, None, None].expand(N, P, R, S, nq)
    gamma = z1[..., None] * wdx[:, None, None] + z2[..., None] * wdy[:, None, None]  # [N, P, R, S, Q]
    coef = torch.cat((w[:, None, None, :, None].expand(N, P, R, S, 1), beta, -gamma), -1)[..., None]  # [N, P, R, S, V, 1]
    z1, z2 = z1[..., None], z2[..., None]
    neg_b = -B[:, None, None, None, None]
    lyx = ly[:, None] * lx  # [Th, Tw]
    # The cross term exp(-B X Y) [Th, Tw]: once for the batch when every frame has the same B
    # (one PSF for all frames, the usual case), else per frame.
    eb_shared = torch.exp(neg_b[:1] * lyx) if N and bool((B == B[0]).all()) else None
    ly_q = ly[:, None, None]  # [Th, 1, 1]

    image = px.new_empty(N, P, Th, R, Tw)
    jac = px.new_empty(N, nq, P, Th, R, Tw)
    per_frame = 8 * P * R * (S * (Th + Tw) + V * S * Tw + 2 * V * Th * Tw)
    step = max(1, int(_CHUNK_BYTES // per_frame))
    for i in range(0, N, step):
        sl = slice(i, i + step)
        n = min(step, N - i)
        # exp(f), exp(g): clamped from below at _exp_floor as in _gaussian_tiled. [n, P, R, S, T]
        gx = torch.addcmul(hx[sl], z1[sl], lx).sub_(qf[sl]).clamp_min_(lo).exp_()
        gy = torch.addcmul(hy[sl], z2[sl], ly).sub_(qf[sl]).clamp_min_(lo).exp_()
        # Column-factor variants [n, P, R, S, V, Tw]: w, w beta_k, w (X alpha_k - gamma_k).
        rp = gx[..., None, :] * coef[sl]
        rp[..., 1 + nq:, :].addcmul_((gx * lx)[..., None, :], alpha[sl])
        r = (gy.transpose(-1, -2) @ rp.view(n, P, R, S, V * Tw)).view(n, P, R, Th, V, Tw)
        eb = eb_shared if eb_shared is not None else torch.exp(neg_b[sl] * lyx)  # [n or 1, 1, 1, Th, Tw]
        image[sl].transpose(2, 3).copy_(r[..., 0, :]).mul_(eb)
        jv = jac[sl].permute(0, 2, 4, 3, 1, 5)  # [n, P, R, Th, Q, Tw]
        jv.copy_(r[..., 1 + nq:, :]).addcmul_(r[..., 1:1 + nq, :], ly_q).mul_(eb[..., None, :])
    image = image.view(N, P * Th, R * Tw)[..., :H, :W]
    jac = jac.view(N, nq, P * Th, R * Tw)[..., :H, :W]
    return image.reshape(batch + (H, W)), jac.reshape(batch + (nq, H, W))


def window_nodes(start, duration, tau, weights, amplitude):
    """Time nodes and splat weights of exposure windows on a quadrature rule over [0, 1].

    Args:
        start, duration: window start and length in seconds ``[...]``.
        tau, weights: a rule on [0, 1] ``[S]`` (:func:`~torchblur.render.blur.quadrature_nodes`).
        amplitude: the PSF's peak intensity per second ``[...]``.

    Returns:
        ``(t [..., S], w [..., S])``: ``t = start + duration * tau`` (s) and
        ``w = duration * weights * amplitude``, the weight of each node in the splat.
    """
    t = start[..., None] + duration[..., None] * tau
    w = duration[..., None] * weights * amplitude[..., None]
    return t, w


def sine_blur_with_jacobian(t, w, amplitude, phase, omega, direction, center, precision, height, width, *,
                            center_jacobian=False, jacobian=True):
    """The forward model of every fitter: a Gaussian spot moved by a sum of sines, and the
    image's derivatives with respect to the sines' amplitudes and phases (and the rest position).

    The spot's position at time ``t`` is
    ``p(t) = center + sum_k direction_k * amplitude_k * sin(omega_k t + phase_k)``, so a motion
    along x is one component with direction ``(1, 0)``, a Lissajous figure two components along
    x and y, a multisine ``K`` tones along one direction, a parametric model's response the sine
    its frequency response gives. The image is ``sum_s w_s Psi(eta - p(t_s))`` (point-sampled
    pixels), computed with its Jacobian in one splat (:func:`gaussian_splat_with_jacobian`).

    Args:
        t: time nodes (s) ``[..., S]``; w: their splat weights ``[..., S]`` (:func:`window_nodes`).
        amplitude: ``[..., K]`` px; phase: ``[..., K]`` rad; omega: ``[..., K]`` rad/s.
        direction: unit image directions of the components ``[..., K, 2]`` (x, y).
        center: rest position ``[..., 2]`` px (x, y).
        precision: ``(A, B, C)``, each ``[...]``: the PSF's inverse covariance ``[[A, B], [B, C]]``.
        height, width: frame size H, W in pixels.
        center_jacobian: also differentiate with respect to ``center`` (two more parameters).
        jacobian: ``False`` returns an empty Jacobian (``P = 0``): the image alone, same splat.

    Returns:
        ``(image [..., H, W], jac [..., P, H, W])`` with ``jac[..., p, i, j] = d image[..., i, j] /
        d theta_p`` for ``theta = (amplitude_1..K, phase_1..K[, center_x, center_y])``, ``P = 2K (+ 2)``.
        The batch dims ``[...]`` of all inputs broadcast.
    """
    arg = omega[..., None, :] * t[..., :, None] + phase[..., None, :]  # [..., S, K]
    sn, cs = torch.sin(arg), torch.cos(arg)
    a = amplitude[..., None, :]
    ux, uy = direction[..., None, :, 0], direction[..., None, :, 1]  # [..., 1, K]
    disp = a * sn  # [..., S, K]
    px = center[..., 0, None] + (ux * disp).sum(-1)  # [..., S]
    py = center[..., 1, None] + (uy * disp).sum(-1)
    if jacobian:
        acs = a * cs
        dpx = torch.cat([ux * sn, ux * acs], -1)  # [..., S, 2K]
        dpy = torch.cat([uy * sn, uy * acs], -1)
        if center_jacobian:
            one, zero = torch.ones_like(px)[..., None], torch.zeros_like(px)[..., None]
            dpx = torch.cat([dpx, one, zero], -1)
            dpy = torch.cat([dpy, zero, one], -1)
    else:
        dpx = dpy = px[..., None][..., :0]
    A, B, C = precision
    return gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, height, width)
