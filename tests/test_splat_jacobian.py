"""Analytic splat Jacobian: image against the renderer's splats, Jacobian against forward AD."""
import math

import pytest
import torch
import torch.autograd.forward_ad as fwAD

from torchblur.render.blur import _exp_budget, _gaussian_separable, _gaussian_tiled, quadrature_nodes
from torchblur.render import splat as splat_jacobian
from torchblur.render.splat import gaussian_splat_with_jacobian

F64 = torch.float64


def precision(sx, sy, rho, dtype=F64):
    """``cov^-1 = [[A, B], [B, C]]`` of a Gaussian with standard deviations sx, sy and correlation rho."""
    det = (sx * sy) ** 2 * (1 - rho ** 2)
    A, B, C = sy ** 2 / det, -rho * sx * sy / det, sx ** 2 / det
    return tuple(torch.tensor(v, dtype=dtype) for v in (A, B, C))


def make_nodes(batch, H, W, motion, n_panels, seed=0, dtype=F64):
    """A sinusoid along a direction per batch element: ``p = c + M (cos d, sin d) sin(omega t + phi)``.

    Returns theta [..., 4] = (M, phi, cx, cy), the node map theta -> (px, py), the analytic
    derivatives (dpx, dpy) [..., S, 4] at theta, and the node weights w [..., S]."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda: torch.rand(batch, generator=g, dtype=F64)  # noqa: E731
    theta = torch.stack(
        (motion * (0.8 + 0.4 * rnd()), 2 * math.pi * rnd(), W / 2 + 3 * (rnd() - 0.5), H / 2 + 3 * (rnd() - 0.5)), -1
    )
    d = (math.pi * rnd())[..., None]  # motion direction
    omega, t0, dur = 2 * math.pi * 100.0, 1.3e-3, 7e-3  # 0.7 period
    tau, wq = quadrature_nodes(n_panels, 8, dtype=F64)
    t = t0 + dur * tau  # [S]
    amp = 2.0 + rnd()[..., None]
    w = dur * wq * amp  # [..., S]

    def node_map(th):
        M, phi, cx, cy = (th[..., i, None] for i in range(4))
        s = torch.sin(omega * t + phi)
        return cx + M * torch.cos(d) * s, cy + M * torch.sin(d) * s

    M, phi = theta[..., 0, None], theta[..., 1, None]
    s, c = torch.sin(omega * t + phi), torch.cos(omega * t + phi)
    one, zero = torch.ones_like(s), torch.zeros_like(s)
    dpx = torch.stack((torch.cos(d) * s, M * torch.cos(d) * c, one, zero), -1)
    dpy = torch.stack((torch.sin(d) * s, M * torch.sin(d) * c, zero, one), -1)
    cast = lambda v: v.to(dtype)  # noqa: E731
    return theta, node_map, cast(dpx), cast(dpy), cast(w)


def forward_ad_jacobian(node_map, theta, w, A, B, C, H, W):
    """``d _gaussian_tiled / d theta`` by forward AD, one pass per parameter: [..., Q, H, W]."""
    cols = []
    with fwAD.dual_level():
        for k in range(theta.shape[-1]):
            tangent = torch.zeros_like(theta)
            tangent[..., k] = 1
            px, py = node_map(fwAD.make_dual(theta, tangent))
            cols.append(fwAD.unpack_dual(_gaussian_tiled(px, py, w, A, B, C, H, W, None)).tangent)
    return torch.stack(cols, -3)


def rel(x, ref):
    return float((x - ref).abs().max() / ref.abs().max())


@pytest.mark.parametrize("tilted", [True, False])
@pytest.mark.parametrize("H, W", [(40, 56), (56, 40)])  # tiles wider than tall (transposed internally), and not
def test_image_and_jacobian_match_renderer_and_forward_ad(tilted, H, W):
    batch = (3, 2)
    A, B, C = precision(2.4, 1.6, 0.6 if tilted else 0.0)
    A, B, C = (v.expand(batch) for v in (A, B, C))
    theta, node_map, dpx, dpy, w = make_nodes(batch, H, W, motion=10.0, n_panels=6)
    px, py = node_map(theta)
    img, jac = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    assert img.shape == batch + (H, W) and jac.shape == batch + (4, H, W)
    assert img.dtype == jac.dtype == F64
    assert rel(img, _gaussian_tiled(px, py, w, A, B, C, H, W, None)) <= 1e-12
    if not tilted:
        assert float(B.abs().max()) == 0.0
        assert rel(img, _gaussian_separable(px, py, w, A, C, H, W, None)) <= 1e-12
    ref = forward_ad_jacobian(node_map, theta, w, A, B, C, H, W)
    assert rel(jac, ref) <= 1e-10
    for k in range(4):  # every column is non-trivial, and each matches on its own scale
        assert float(ref[..., k, :, :].abs().max()) > 1e-3 * float(ref.abs().max())
        assert rel(jac[..., k, :, :], ref[..., k, :, :]) <= 1e-10


def test_float32_inputs_give_float32_outputs():
    H, W, batch = 40, 56, (3, 2)
    A, B, C = precision(2.4, 1.6, 0.6)
    theta, node_map, dpx, dpy, w = make_nodes(batch, H, W, motion=10.0, n_panels=6)
    px, py = node_map(theta)
    img64, jac64 = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    f32 = [v.float() for v in (px, py, dpx, dpy, w, A, B, C)]
    img32, jac32 = gaussian_splat_with_jacobian(*f32, H, W)
    assert img32.dtype == jac32.dtype == torch.float32
    assert rel(img32.double(), img64) <= 1e-5
    assert rel(jac32.double(), jac64) <= 1e-5


def test_large_frame_needs_several_tiles():
    H = W = 200
    A, B, C = precision(1.2, 1.2, 0.6)
    kappa = float(max(A, C) + B.abs())
    t_max = int(2 * math.sqrt(_exp_budget(F64) / kappa)) - 1
    assert -(-H // t_max) >= 4  # the tiling is exercised in both directions
    batch = (2,)
    theta, node_map, dpx, dpy, w = make_nodes(batch, H, W, motion=70.0, n_panels=24, seed=3)
    px, py = node_map(theta)
    assert float(px.max() - px.min()) > 2 * t_max  # the path crosses several tiles
    img, jac = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    assert rel(img, _gaussian_tiled(px, py, w, A.expand(batch), B.expand(batch), C.expand(batch), H, W, None)) <= 1e-12
    ref = forward_ad_jacobian(node_map, theta, w, A.expand(batch), B.expand(batch), C.expand(batch), H, W)
    assert rel(jac, ref) <= 1e-10


def test_batch_shapes_broadcast_and_direct_node_derivatives():
    # Scalar precision against [2, 3] nodes; dpx = e_k per node checks the formula directly:
    # jac = sum_s w_s exp(-q/2) ((A u + B v) dpx + (B u + C v) dpy).
    g = torch.Generator().manual_seed(5)
    H, W, S = 12, 15, 5
    px = 2 + 11 * torch.rand(2, 3, S, generator=g, dtype=F64)
    py = 2 + 8 * torch.rand(2, 3, S, generator=g, dtype=F64)
    w = torch.rand(2, 3, S, generator=g, dtype=F64)
    dpx = torch.randn(2, 1, S, 2, generator=g, dtype=F64)
    dpy = torch.randn(S, 2, generator=g, dtype=F64)
    A, B, C = precision(1.7, 1.1, -0.4)
    img, jac = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    assert img.shape == (2, 3, H, W) and jac.shape == (2, 3, 2, H, W)
    u = torch.arange(W, dtype=F64) - px[..., None, None]  # [2, 3, S, 1, W]
    v = torch.arange(H, dtype=F64)[:, None] - py[..., None, None]  # [2, 3, S, H, 1]
    e = w[..., None, None] * torch.exp(-0.5 * (A * u * u + 2 * B * u * v + C * v * v))  # [2, 3, S, H, W]
    ref_img = e.sum(-3)
    gx, gy = A * u + B * v, B * u + C * v
    ref_jac = torch.stack(
        [(e * (gx * dpx[..., k, None, None] + gy * dpy[..., k, None, None])).sum(-3) for k in range(2)], -3
    )
    assert rel(img, ref_img) <= 1e-12
    assert rel(jac, ref_jac) <= 1e-12


def test_chunks_of_frames_agree(monkeypatch):
    H, W, batch = 40, 56, (3, 2)
    A, B, C = precision(2.4, 1.6, 0.6)
    theta, node_map, dpx, dpy, w = make_nodes(batch, H, W, motion=10.0, n_panels=6)
    px, py = node_map(theta)
    img, jac = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    monkeypatch.setattr(splat_jacobian, "_CHUNK_BYTES", 1.0)  # one frame per chunk
    img1, jac1 = gaussian_splat_with_jacobian(px, py, dpx, dpy, w, A, B, C, H, W)
    assert rel(img1, img) <= 1e-14 and rel(jac1, jac) <= 1e-14


@pytest.mark.parametrize("H, W", [(5, 6), (6, 5)])
def test_differentiable_by_autograd(H, W):
    g = torch.Generator().manual_seed(9)
    S = 3
    px = (1 + 4 * torch.rand(S, generator=g, dtype=F64)).requires_grad_()
    py = (1 + 3 * torch.rand(S, generator=g, dtype=F64)).requires_grad_()
    dpx = torch.randn(S, 2, generator=g, dtype=F64).requires_grad_()
    dpy = torch.randn(S, 2, generator=g, dtype=F64).requires_grad_()
    w = torch.rand(S, generator=g, dtype=F64).requires_grad_()
    A, B, C = (v.requires_grad_() for v in precision(1.5, 1.2, 0.3))
    fn = lambda *a: gaussian_splat_with_jacobian(*a, H, W)  # noqa: E731
    assert torch.autograd.gradcheck(fn, (px, py, dpx, dpy, w, A, B, C), fast_mode=True)


# --- the one forward model: a spot moved by a sum of sines -------------------------------------

def _sine_problem(seed=0, K=3, batch=(2, 3)):
    """Random sum-of-sines motions of a tilted Gaussian, with their exposure nodes."""
    from torchblur.render.splat import window_nodes

    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    amp = 1.0 + 3.0 * rnd(*batch, K)
    phase = 2 * math.pi * rnd(*batch, K)
    omega = 2 * math.pi * (50.0 + 400.0 * rnd(*batch, K))
    ang = math.pi * rnd(*batch, K)
    direction = torch.stack((torch.cos(ang), torch.sin(ang)), -1)
    center = torch.stack((14.0 + 2 * rnd(*batch), 11.0 + 2 * rnd(*batch)), -1)
    start, dur = 1e-3 * rnd(*batch), 2e-3 + 3e-3 * rnd(*batch)
    psf_amp = 1.0 + rnd(*batch)
    tau, wq = quadrature_nodes(12, 8, dtype=F64)
    t, w = window_nodes(start, dur, tau, wq, psf_amp)
    A, B, C = precision(1.3, 0.9, 0.35)
    return dict(t=t, w=w, amplitude=amp, phase=phase, omega=omega, direction=direction, center=center,
                precision=(A, B, C), cov=torch.linalg.inv(torch.tensor([[A, B], [B, C]])), start=start, dur=dur,
                psf_amp=psf_amp)


def test_sine_forward_model_matches_the_renderer():
    """The forward model's image is the renderer's image of the same multisine along its directions."""
    import torchblur as tb
    from torchblur.render.splat import sine_blur_with_jacobian

    p = _sine_problem()
    H, W = 26, 30
    img, jac = sine_blur_with_jacobian(p["t"], p["w"], p["amplitude"], p["phase"], p["omega"], p["direction"],
                                       p["center"], p["precision"], H, W)
    assert img.shape == (2, 3, H, W) and jac.shape == (2, 3, 6, H, W)
    # Exact reference: the dense sum over the same nodes of the Gaussian at each node's position.
    arg = p["omega"][..., None, :] * p["t"][..., :, None] + p["phase"][..., None, :]  # [..., S, K]
    disp = (p["amplitude"][..., None, :, None] * torch.sin(arg)[..., None] * p["direction"][..., None, :, :]).sum(-2)
    pos = p["center"][..., None, :] + disp  # [..., S, 2]
    A, B, C = p["precision"]
    u = torch.arange(W, dtype=F64) - pos[..., 0, None, None]
    v = torch.arange(H, dtype=F64)[:, None] - pos[..., 1, None, None]
    dense = (p["w"][..., None, None] * torch.exp(-(A * u * u + 2 * B * u * v + C * v * v) / 2)).sum(-3)
    assert (img - dense).abs().max() <= 1e-13 * dense.max()
    # The renderer's multisine (each component along its direction) on the same nodes: the same image.
    amp_xy = p["amplitude"][..., None] * p["direction"]  # [..., K, 2]
    flip = (amp_xy < 0).to(F64) * math.pi  # a negative component is the positive one shifted by pi
    traj = tb.Multisine(amp_xy.abs(), p["phase"][..., None] + flip, p["omega"])
    psf = tb.GaussianPSF(p["center"], p["cov"].expand(2, 3, 2, 2), p["psf_amp"])
    ref = tb.render_blur(traj, psf, tb.ExposureWindow(p["start"], p["dur"]), height=H, width=W,
                         settings=tb.RenderSettings(nodes=96))
    assert (img - ref).abs().max() <= 1e-13 * ref.abs().max()


def test_sine_forward_model_jacobian_gradcheck():
    """float64 gradcheck: the analytic Jacobian is the derivative of the image (amplitudes, phases, centre)."""
    from torchblur.render.splat import sine_blur_with_jacobian

    p = _sine_problem(seed=1, K=2, batch=(2,))
    H, W = 20, 22

    def image(amplitude, phase, center):
        return sine_blur_with_jacobian(p["t"], p["w"], amplitude, phase, p["omega"], p["direction"], center,
                                       p["precision"], H, W, jacobian=False)[0]

    args = tuple(v.clone().requires_grad_(True) for v in (p["amplitude"], p["phase"], p["center"]))
    assert torch.autograd.gradcheck(image, args)
    _, jac = sine_blur_with_jacobian(p["t"], p["w"], *args[:2], p["omega"], p["direction"], args[2], p["precision"], H, W,
                                     center_jacobian=True)
    auto = torch.autograd.functional.jacobian(lambda a, ph, c: image(a, ph, c), tuple(v.detach() for v in args))
    # auto[k]: [2, H, W, 2, K or 2] -> per item, parameter-first
    ref = torch.cat([torch.stack([auto[k][b, :, :, b] for b in range(2)]).movedim(-1, 1) for k in range(3)], 1)
    assert torch.allclose(jac.detach(), ref, rtol=1e-9, atol=1e-12 * ref.abs().max())


def _fitter_frames(axes, fit_center, seed=0):
    """Frames of fit_sinusoid's analytic path: problems with a tilted PSF, two exposures each,
    parameters theta = (amplitudes, phases, scale, background[, center]) with the fitted axes'
    unit directions D [N, n_axes, 2]."""
    g = torch.Generator().manual_seed(seed)
    N, E = 3, 2
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    if axes == "rotated":
        a = 0.4 + rnd(N)
        D = torch.stack((a.cos(), a.sin()), -1)[:, None]
    else:
        eye = torch.eye(2, dtype=F64)
        D = {"x": eye[:1], "y": eye[1:], "xy": eye}[axes][None].expand(N, -1, 2)
    n_axes = D.shape[1]
    cov = torch.tensor([[4.0, 1.1], [1.1, 2.5]], dtype=F64).expand(N, 2, 2)
    from torchblur.render.psf import GaussianPSF

    psf = GaussianPSF(torch.stack((14 + rnd(N), 11 + rnd(N)), -1), cov, 1 + rnd(N))
    om = 2 * math.pi * (50 + 100 * rnd(N))
    start, dur = 1e-3 * rnd(N, E), 2e-3 + 4e-3 * rnd(N, E)
    cols = [2 + 3 * rnd(N, n_axes), 6 * rnd(N, n_axes) - 3, 1 + rnd(N, 1), rnd(N, 1)]
    if fit_center:
        cols.append(psf.center + rnd(N, 2) - 0.5)
    theta = torch.cat(cols, -1)
    return dict(D=D, psf=psf, om=om, start=start, dur=dur, theta=theta, n_axes=n_axes, H=24, W=30)


@pytest.mark.parametrize("fit_center", [False, True])
@pytest.mark.parametrize("axes", ["x", "y", "xy", "rotated"])
def test_fitter_model_splat_matches_renderer_and_forward_ad(axes, fit_center):
    """fit_sinusoid's model on the one forward model (window_nodes + sine_blur_with_jacobian,
    frames on rules of different panel counts, scale and background columns assembled around
    the splat) equals render_blur's image and its forward-AD Jacobian (the generic path)."""
    import dataclasses

    from torchblur.fit.sine_model import ParamLayout, sine_model
    from torchblur.render.blur import RenderSettings

    f = _fitter_frames(axes, fit_center)
    n_axes, psf = f["n_axes"], f["psf"]
    labels = ("x", "y") if axes == "xy" else ("u",)
    layout = ParamLayout(labels, fit_scale=True, fit_background=True, fit_center=fit_center)
    model = sine_model(layout, psf, f["start"], f["dur"], f["om"], f["D"], f["H"], f["W"],
                       amplitude_bound=f["theta"][:, :n_axes] + 1, settings=RenderSettings(nodes=48))
    assert model.analytic
    generic = dataclasses.replace(model, panels=None)
    assert not generic.analytic
    n = torch.tensor([0, 1, 2, 1])
    theta = f["theta"][n]
    img, jac = model.image_and_jacobian(theta, n)
    ref_img, ref_jac = generic.image_and_jacobian(theta, n)
    assert jac.shape == ref_jac.shape == (4, 2 * f["H"] * f["W"], layout.size)
    assert float((img - ref_img).abs().max()) < 1e-11 * float(ref_img.abs().max())
    assert float((jac - ref_jac).abs().max()) < 1e-11 * float(ref_jac.abs().max())
    assert torch.equal(model.image(theta, n), img)
    for r in range(4):  # the batch equals the rows one at a time
        one_img, one_jac = model.image_and_jacobian(theta[r:r + 1], n[r:r + 1])
        assert float((one_img - img[r:r + 1]).abs().max()) < 1e-12 * float(ref_img.abs().max())
        assert float((one_jac - jac[r:r + 1]).abs().max()) < 1e-12 * float(ref_jac.abs().max())
    # frames of one problem on different rules (panel counts) give the same model
    mixed = dataclasses.replace(model, panels=torch.tensor([[6, 3], [3, 6], [6, 6]]), nodes_per_panel=16)
    img2, jac2 = mixed.image_and_jacobian(theta, n)
    assert float((img2 - ref_img).abs().max()) < 1e-6 * float(ref_img.abs().max())
    assert float((jac2 - ref_jac).abs().max()) < 1e-5 * float(ref_jac.abs().max())


# --- the one forward model with a measured kernel (issue 29) ------------------------------------

def _airy_like_kernels(n, H, W, seed=0):
    """``n`` band-limited, asymmetric kernels ``[n, H, W]``: a ring plus two offset Gaussians
    (sigmas >= 1.6 px, so their Fourier interpolation is the function itself to ~1e-7)."""
    g = torch.Generator().manual_seed(seed)
    rnd = lambda *s: torch.rand(*s, generator=g, dtype=F64)  # noqa: E731
    y, x = torch.arange(H, dtype=F64)[:, None], torch.arange(W, dtype=F64)
    out = []
    for _ in range(n):
        cx, cy = W / 2 + rnd(()) - 0.5, H / 2 + rnd(()) - 0.5
        r = ((x - cx) ** 2 + (y - cy) ** 2).sqrt()
        k = torch.exp(-r ** 2 / (2 * 1.8 ** 2)) + 0.15 * torch.exp(-(r - 5.0) ** 2 / (2 * 1.6 ** 2))
        k = k + 0.3 * torch.exp(-((x - cx - 1.5) ** 2 + (y - cy + 1.0) ** 2) / (2 * 2.0 ** 2)) * (1 + rnd(()))
        out.append(k)
    return torch.stack(out)


def _kernel_reference(kernel, t, w, amplitude, phase, omega, direction, pad):
    """Slow reference: every node's kernel shifted by its own Fourier transform on the same padded
    grid (numpy, node by node), summed; the Jacobian by central differences of that sum."""
    import numpy as np

    from torchblur.render.blur import _next_odd_fast

    H, W = kernel.shape[-2:]
    Hp, Wp = _next_odd_fast(H + 2 * pad), _next_odd_fast(W + 2 * pad)
    ph, pw = (Hp - H) // 2, (Wp - W) // 2
    kp = np.zeros((Hp, Wp))
    kp[ph:ph + H, pw:pw + W] = kernel.numpy()
    khat = np.fft.fft2(kp)
    ky = 2 * np.pi * np.fft.fftfreq(Hp)[:, None]
    kx = 2 * np.pi * np.fft.fftfreq(Wp)[None, :]

    def image(a, p):
        acc = np.zeros((Hp, Wp), complex)
        for s in range(t.shape[-1]):
            d = (a * np.sin(omega * float(t[s]) + p))[:, None] * direction  # [K, 2]
            dx, dy = d[:, 0].sum(), d[:, 1].sum()
            acc += float(w[s]) * np.exp(-1j * (kx * dx + ky * dy))
        return np.fft.ifft2(khat * acc).real[ph:ph + H, pw:pw + W]

    a0, p0 = amplitude.numpy(), phase.numpy()
    img = image(a0, p0)
    cols, h = [], 1e-6
    for which in range(2):
        for k in range(a0.size):
            e = np.zeros_like(a0)
            e[k] = h
            plus = image(a0 + e, p0) if which == 0 else image(a0, p0 + e)
            minus = image(a0 - e, p0) if which == 0 else image(a0, p0 - e)
            cols.append((plus - minus) / (2 * h))
    return torch.from_numpy(img), torch.from_numpy(np.stack(cols))


def test_kernel_forward_model_matches_slow_reference_and_renderer():
    """The kernel path of the one forward model: its image is the renderer's KernelPSF image and a
    node-by-node numpy Fourier shift; its Jacobian that reference's central differences."""
    import torchblur as tb
    from torchblur.render.splat import sine_blur_with_jacobian

    H, W = 22, 26
    p = _sine_problem(seed=2, K=2, batch=(1,))
    kern = _airy_like_kernels(1, H, W)
    args = (p["t"], p["w"], p["amplitude"], p["phase"], p["omega"], p["direction"], torch.zeros(1, 2, dtype=F64), None, H, W)
    img, jac = sine_blur_with_jacobian(*args, kernel=kern, pad=12)
    ref_img, ref_jac = _kernel_reference(kern[0], p["t"][0], p["w"][0], p["amplitude"][0], p["phase"][0], p["omega"][0].numpy(),
                                         p["direction"][0].numpy(), 12)
    assert (img[0] - ref_img).abs().max() <= 1e-12 * ref_img.abs().max()
    assert (jac[0] - ref_jac).abs().max() <= 1e-6 * ref_jac.abs().max()
    # The renderer's KernelPSF path on the same nodes and, with pad=None, the same grid: the same image.
    img, _ = sine_blur_with_jacobian(*args, kernel=kern, jacobian=False)
    amp_xy = p["amplitude"][0, :, None] * p["direction"][0]
    flip = (amp_xy < 0).to(F64) * math.pi
    traj = tb.Multisine(amp_xy.abs(), p["phase"][0, :, None] + flip, p["omega"][0])
    ref = tb.render_blur(traj, tb.KernelPSF(kern[0]), tb.ExposureWindow(p["start"][0], p["dur"][0]), height=H, width=W,
                         settings=tb.RenderSettings(nodes=96))
    scale = p["psf_amp"][0]  # window_nodes put the Gaussian's amplitude into w
    assert (img[0] / scale - ref).abs().max() <= 1e-13 * ref.abs().max()


def test_kernel_forward_model_gradcheck_batch_and_errors():
    """float64 gradcheck of the kernel path (amplitudes, phases, shift, kernel); a batch with a
    kernel per item equals the items alone (same grid); a kernel of the wrong frame is refused."""
    from torchblur.errors import ShapeError
    from torchblur.render.splat import sine_blur_with_jacobian

    H, W = 14, 16
    p = _sine_problem(seed=3, K=2, batch=(2,))
    kern = _airy_like_kernels(2, H, W, seed=1)
    t, w, om, d = p["t"][:, :24], p["w"][:, :24], p["omega"], p["direction"]

    def image(amplitude, phase, center, kernel):
        return sine_blur_with_jacobian(t, w, amplitude, phase, om, d, center, None, H, W, kernel=kernel, jacobian=False, pad=9)[0]

    center = torch.tensor([[0.3, -0.2], [0.0, 0.4]], dtype=F64)
    args = tuple(v.clone().requires_grad_(True) for v in (p["amplitude"] * 0.5, p["phase"], center, kern))
    assert torch.autograd.gradcheck(image, args, fast_mode=True)
    img, jac = sine_blur_with_jacobian(t, w, *args[:2], om, d, args[2], None, H, W, kernel=args[3], center_jacobian=True, pad=9)
    auto = torch.autograd.functional.jacobian(lambda a, ph, c: image(a, ph, c, kern), tuple(v.detach() for v in args[:3]))
    ref = torch.cat([torch.stack([auto[k][b, :, :, b] for b in range(2)]).movedim(-1, 1) for k in range(3)], 1)
    assert torch.allclose(jac.detach(), ref, rtol=1e-9, atol=1e-12 * ref.abs().max())
    for b in range(2):
        one, jac1 = sine_blur_with_jacobian(t[b], w[b], p["amplitude"][b] * 0.5, p["phase"][b], om[b], d[b], center[b], None, H, W,
                                            kernel=kern[b], center_jacobian=True, pad=9)
        assert torch.allclose(one, img[b].detach(), rtol=0, atol=1e-13 * float(one.abs().max()))
        assert torch.allclose(jac1, jac[b].detach(), rtol=0, atol=1e-13 * float(jac1.abs().max()))
    with pytest.raises(ShapeError, match="kernel"):
        sine_blur_with_jacobian(t, w, *args[:2], om, d, center, None, H, W + 1, kernel=kern)


def test_splat_batches_that_do_not_broadcast_raise_a_shape_error_naming_the_inputs():
    """Both splats refuse batch shapes that do not broadcast with a ShapeError listing every
    input's shape (the Gaussian one raised NameError before: its message named an undefined list)."""
    from torchblur.errors import ShapeError
    from torchblur.render.splat import gaussian_splat_with_jacobian, kernel_shift_with_jacobian

    S, one = 4, torch.tensor(1.0, dtype=F64)
    with pytest.raises(ShapeError, match=r"shapes do not broadcast \(px \(3, 4\), py \(2, 4\), dpx \(4, 1\)"):
        gaussian_splat_with_jacobian(torch.zeros(3, S, dtype=F64), torch.zeros(2, S, dtype=F64), torch.zeros(S, 1, dtype=F64),
                                     torch.zeros(S, 1, dtype=F64), torch.ones(S, dtype=F64), one, 0 * one, one, 8, 8)
    with pytest.raises(ShapeError, match=r"shapes do not broadcast \(kernel \(3, 8, 8\), dx \(2, 4\)"):
        kernel_shift_with_jacobian(torch.ones(3, 8, 8, dtype=F64), torch.zeros(2, S, dtype=F64), torch.zeros(S, dtype=F64),
                                   torch.zeros(S, 1, dtype=F64), torch.zeros(S, 1, dtype=F64), torch.ones(S, dtype=F64))
    with pytest.raises(ShapeError, match="dpx: expected at least 2 dimension"):
        gaussian_splat_with_jacobian(torch.zeros(S), torch.zeros(S), torch.zeros(S), torch.zeros(S, 1), torch.ones(S), one, 0 * one, one, 8, 8)
