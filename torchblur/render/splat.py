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

from torchblur.errors import InputTypeError, ParameterError, ShapeError, check_int
from torchblur.render.blur import _exp_budget, _exp_floor, _next_odd_fast, _tile_grid

__all__ = ["gaussian_splat_with_jacobian", "kernel_shift_with_jacobian", "sine_blur_with_jacobian", "window_nodes"]

# Temporaries of one chunk of frames. Cache-sized chunks (~8 MB) were no faster than this on an
# idle 2-core machine, and many small ops are far slower when the cores are shared.
_CHUNK_BYTES = 32e6


def _broadcast(names, args, core_dims, desc: str):
    """``args`` (errors name them by ``names``): real tensors with at least ``core_dims`` trailing
    dims each, whose batch dims (those before) broadcast -> ``(dtype, args)``: their promoted
    floating dtype (the default one for integers), and the args on the first's device in float64
    or wider (to compute in), expanded to the common batch. ``desc``: their shapes, for the error."""
    for name, val in zip(names, args):
        if not isinstance(val, torch.Tensor):
            raise InputTypeError(f"{name}: expected a torch.Tensor, got {type(val).__name__}")
        if val.is_complex():
            raise InputTypeError(f"{name}: expected a real tensor, got {val.dtype}")
    dtype = functools.reduce(torch.promote_types, (v.dtype for v in args))
    dtype = dtype if dtype.is_floating_point else torch.get_default_dtype()
    wide = torch.float64 if torch.finfo(dtype).bits <= 32 else dtype
    for name, val, nd in zip(names, args, core_dims):
        if val.dim() < nd:
            raise ShapeError(f"{name}: expected at least {nd} dimension(s), got shape {tuple(val.shape)}")
    try:
        batch = torch.broadcast_shapes(*(v.shape[:v.dim() - nd] for v, nd in zip(args, core_dims)))
    except RuntimeError as exc:
        raise ShapeError(f"{desc}: shapes do not broadcast ({', '.join(f'{n} {tuple(v.shape)}' for n, v in zip(names, args))}): "
                         f"{exc}") from None
    device = args[0].device
    return dtype, [v.to(device=device, dtype=wide).expand(batch + v.shape[v.dim() - nd:]) for v, nd in zip(args, core_dims)]


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
    height, width = check_int(height, "height", low=1), check_int(width, "width", low=1)
    dtype, (px, py, dpx, dpy, w, A, B, C) = _broadcast(("px", "py", "dpx", "dpy", "w", "A", "B", "C"), (px, py, dpx, dpy, w, A, B, C),
                                                       (1, 1, 2, 2, 1, 0, 0, 0), "px, py, w [..., S], dpx, dpy [..., S, Q], A, B, C [...]")
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


def kernel_shift_with_jacobian(kernel, dx, dy, dpx, dpy, w, *, pad=None):
    """A measured kernel shifted along the nodes (a band-limited image, Fourier shift) and its
    Jacobian with respect to node-moving parameters: the kernel path of the one forward model.

    Proposition 1 in Fourier space, as :func:`torchblur.render.blur._kernel_fourier` renders a
    :class:`~torchblur.render.psf.KernelPSF`: ``image = IFFT(K(k) D(k))`` with
    ``D(k) = sum_s w_s exp(-i (kx dx_s + ky dy_s))``, a separable complex GEMM on a padded
    (odd-sized) grid. The derivative of a node's phase factor is ``-i (kx dpx_sk + ky dpy_sk)``
    times it, and ``kx`` (a column) and ``ky`` (a row) factor out of the sum over nodes, so

        jac_k = IFFT(-i K(k) (kx Dx_k(k) + ky Dy_k(k))),  Dx_k = sum_s w_s dpx_sk e_s, Dy_k likewise,

    ``1 + 2 Q`` column variants of one GEMM (exact: no finite differences, no forward AD).

    Args:
        kernel: the still spot's image ``[..., H, W]`` (intensity per second; its rest position
            wherever it sits in the frame).
        dx, dy: node displacements from that rest position (px) ``[..., S]``.
        dpx, dpy: their derivatives with respect to ``Q`` parameters ``[..., S, Q]``.
        w: node weights ``[..., S]`` (quadrature weight * duration * intensity scale).
        pad: px of zeros around the kernel on the FFT grid (the shifted kernel must not wrap
            round): None, the largest displacement of the batch plus 2 px; a number, at least
            that many (a fit fixes it from its motion bound so that its model does not jump
            between iterations). Items of one batch share the grid.

    Returns:
        ``(image [..., H, W], jac [..., Q, H, W])``, ``image[..., i, j] = sum_s w_s K(j - dx_s, i - dy_s)``
        (K the band-limited interpolant of the kernel), ``jac[..., k, i, j] = d image / d theta_k``.
        Broadcast batch ``[...]``; computed in float64 for inputs of 32 bits or fewer (cast back);
        differentiable by autograd in every input.

    Example:
        >>> S = 16
        >>> dx, dy = torch.linspace(-3, 3, S), torch.zeros(S)
        >>> img, jac = kernel_shift_with_jacobian(torch.rand(24, 32), dx, dy, torch.ones(S, 1), torch.zeros(S, 1), torch.full((S,), 1 / S))
        >>> img.shape, jac.shape
        (torch.Size([24, 32]), torch.Size([1, 24, 32]))
    """
    if pad is not None and (isinstance(pad, bool) or not isinstance(pad, (int, float)) or not pad >= 0):
        raise ParameterError(f"pad: expected None or a number >= 0 (px), got {pad!r}")
    dtype, (kernel, dx, dy, dpx, dpy, w) = _broadcast(("kernel", "dx", "dy", "dpx", "dpy", "w"), (kernel, dx, dy, dpx, dpy, w),
                                                      (2, 1, 1, 2, 2, 1), "kernel [..., H, W], dx, dy, w [..., S], dpx, dpy [..., S, Q]")
    reach = float(torch.maximum(dx.detach().abs().max(), dy.detach().abs().max())) if dx.numel() else 0.0
    pad_px = max(int(math.ceil(reach)) + 2, int(math.ceil(pad or 0)))
    image, jac = _kernel_jacobian(kernel, dx, dy, dpx, dpy, w, pad_px)
    return image.to(dtype), jac.to(dtype)


def _kernel_jacobian(kernel, dx, dy, dpx, dpy, w, pad: int):
    """Broadcast inputs of one floating dtype, ``pad`` px -> (image [..., H, W], jac [..., Q, H, W])."""
    batch, (H, W) = kernel.shape[:-2], kernel.shape[-2:]
    S, nq = dx.shape[-1], dpx.shape[-1]
    N, V = math.prod(batch), 1 + 2 * nq
    Hp, Wp = _next_odd_fast(H + 2 * pad), _next_odd_fast(W + 2 * pad)
    ph, pw = (Hp - H) // 2, (Wp - W) // 2
    two_pi = 2 * math.pi
    ky = two_pi * torch.fft.fftfreq(Hp, dtype=dx.dtype, device=dx.device)  # [Hp]
    kx = two_pi * torch.fft.rfftfreq(Wp, dtype=dx.dtype, device=dx.device)  # [Kx]
    Kx = kx.numel()
    kernel, dx, dy, w = kernel.reshape(N, H, W), dx.reshape(N, S), dy.reshape(N, S), w.reshape(N, S)
    coef = torch.cat((w[..., None], dpx.reshape(N, S, nq) * w[..., None], dpy.reshape(N, S, nq) * w[..., None]), -1)  # [N, S, V]
    image = kernel.new_empty(N, H, W)
    jac = kernel.new_empty(N, nq, H, W)
    per_item = 16 * (S * (Hp + V * Kx) + 3 * V * Hp * Kx)
    step = max(1, int(_CHUNK_BYTES // per_item))
    for i in range(0, N, step):
        sl = slice(i, i + step)
        kp = torch.nn.functional.pad(kernel[sl], (pw, Wp - W - pw, ph, Hp - H - ph))
        khat = torch.fft.rfft2(kp)  # [n, Hp, Kx]
        ay, ax = -dy[sl, :, None] * ky, -dx[sl, :, None] * kx  # [n, S, Hp], [n, S, Kx]
        ey = torch.polar(torch.ones_like(ay), ay)
        ex = torch.polar(torch.ones_like(ax), ax)
        rp = ex[:, :, None, :] * coef[sl, :, :, None].to(ex.dtype)  # [n, S, V, Kx]
        d = (ey.transpose(-1, -2) @ rp.flatten(-2)).unflatten(-1, (V, Kx))  # [n, Hp, V, Kx]
        spec = torch.cat((d[:, :, :1], -1j * (kx * d[:, :, 1:1 + nq] + ky[:, None, None] * d[:, :, 1 + nq:])), 2)
        out = torch.fft.irfft2(khat[:, None] * spec.movedim(2, 1), s=(Hp, Wp))[..., ph:ph + H, pw:pw + W]  # [n, V', H, W]
        image[sl] = out[:, 0]
        jac[sl] = out[:, 1:]
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
                            center_jacobian=False, jacobian=True, kernel=None, pad=None):
    """The forward model of every fitter: a spot (a Gaussian or a measured kernel) moved by a sum
    of sines, and the image's derivatives with respect to the sines' amplitudes and phases (and
    the rest position).

    The spot's position at time ``t`` is
    ``p(t) = center + sum_k direction_k * amplitude_k * sin(omega_k t + phase_k)``, so a motion
    along x is one component with direction ``(1, 0)``, a Lissajous figure two components along
    x and y, a multisine ``K`` tones along one direction, a parametric model's response the sine
    its frequency response gives. The image is ``sum_s w_s Psi(eta - p(t_s))`` (point-sampled
    pixels), computed with its Jacobian in one splat: :func:`gaussian_splat_with_jacobian` for a
    Gaussian, :func:`kernel_shift_with_jacobian` for a measured kernel (``kernel`` given: the
    still spot's image shifted as a band-limited image, as the renderer renders a
    :class:`~torchblur.render.psf.KernelPSF`; ``center`` is then the shift of the kernel's rest
    position, zeros for the spot at rest where the kernel shows it).

    Args:
        t: time nodes (s) ``[..., S]``; w: their splat weights ``[..., S]`` (:func:`window_nodes`).
        amplitude: ``[..., K]`` px; phase: ``[..., K]`` rad; omega: ``[..., K]`` rad/s.
        direction: unit image directions of the components ``[..., K, 2]`` (x, y).
        center: rest position ``[..., 2]`` px (x, y).
        precision: ``(A, B, C)``, each ``[...]``: the Gaussian's inverse covariance ``[[A, B], [B, C]]``
            (ignored, may be None, with ``kernel``).
        height, width: frame size H, W in pixels.
        center_jacobian: also differentiate with respect to ``center`` (two more parameters).
        jacobian: ``False`` returns an empty Jacobian (``P = 0``): the image alone, same splat.
        kernel: None (a Gaussian), or the measured kernel ``[..., H, W]`` (intensity per second,
            one per item or shared; ``w`` then carries no PSF amplitude, only an intensity scale).
        pad: kernel path: the FFT grid's padding (px), see :func:`kernel_shift_with_jacobian`.

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
    if kernel is not None:
        if not isinstance(kernel, torch.Tensor) or kernel.dim() < 2 or tuple(kernel.shape[-2:]) != (height, width):
            got = tuple(kernel.shape) if isinstance(kernel, torch.Tensor) else type(kernel).__name__
            raise ShapeError(f"kernel: expected a tensor [..., {height}, {width}] (the still spot in the frame), got {got}")
        return kernel_shift_with_jacobian(kernel, px, py, dpx, dpy, w, pad=pad)
    A, B, C = precision
    return gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, height, width)
