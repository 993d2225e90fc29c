"""The deformable-mirror model: mirror, Shack-Hartmann geometry, plans, the simulated DM rig (9
actuators, 4 x 4 subapertures; seconds)."""
import math

import numpy as np
import pytest
from scipy.special import erf

from torchblur.dm.mirror import DeformableMirror, actuator_grid, influence, influence_width, read_actuator_table
from torchblur.dm.plans import (choose_plan, driven_spots, hadamard_plan, one_at_a_time_plan, plan_cost, seen_by, sparse_plan,
                                static_motion_px)
from torchblur.dm.shack_hartmann import ShackHartmann, subaperture_grid
from torchblur.errors import ConfigError, ParameterError


@pytest.fixture
def small():
    mirror = DeformableMirror.build(3, mode_hz=800.0, damping=0.1, mode_spread=0.05, seed=1)
    wfs = ShackHartmann(n_across=4, pupil_diameter=3.0, pitch_px=16.0, sigma_px=1.5)
    return mirror, wfs, wfs.geometry_matrix(mirror)


# ------------------------------------------------------------------ mirror


def test_actuator_grid_counts_and_symmetry():
    assert actuator_grid(3).shape == (9, 2)
    assert actuator_grid(8).shape == (52, 2)
    xy = actuator_grid(8)
    assert np.allclose(xy.mean(0), 0.0)
    assert np.all(np.hypot(*xy.T) <= 4.1)
    # row-major: y non-decreasing, x increasing within a row
    assert np.all(np.diff(xy[:, 1]) >= 0)


def test_influence_is_coupling_one_pitch_away():
    v = influence(np.array([[1.0, 0.0], [0.0, 0.0]]), np.zeros((1, 2)), 0.15)
    assert v[0, 0] == pytest.approx(0.15)
    assert v[1, 0] == pytest.approx(1.0)
    assert influence_width(0.15) == pytest.approx(0.5134, abs=1e-4)
    with pytest.raises(ParameterError, match="coupling"):
        influence_width(1.0)


def test_response_matches_python_control():
    control = pytest.importorskip("control")
    m = DeformableMirror.build(3, mode_hz=700.0, damping=0.08, delay_s=30e-6, mode_spread=0.1, gain_spread=0.05, seed=3)
    f = np.array([10.0, 500.0, 700.0, 2000.0])
    h = m.response(f)
    assert h.shape == (9, 4)
    for j, tf in enumerate(m.to_control()):
        ref = np.array([complex(tf(2j * np.pi * fk)) for fk in f]) * np.exp(-2j * np.pi * f * m.delay_s[j])
        np.testing.assert_allclose(h[j], ref, rtol=1e-10)
    np.testing.assert_allclose(m.response(500.0), h[:, 1])
    assert np.allclose(m.response(1e-6).real, m.gain, rtol=1e-6)


def test_spread_dead_and_weak():
    a = DeformableMirror.build(8, mode_spread=0.05, seed=4)
    b = DeformableMirror.build(8, mode_spread=0.05, seed=4, dead=[2], weak=[7], weak_gain=0.4)
    np.testing.assert_array_equal(a.mode_hz, b.mode_hz)  # the same draws whatever the other settings
    assert 0.02 < np.std(a.mode_hz) / 1000.0 < 0.08
    assert b.gain[2] == 0 and b.dead[2] and b.dead.sum() == 1
    assert b.gain[7] == pytest.approx(0.4)
    assert np.all(np.abs(b.response([100.0, 900.0])[2]) == 0)
    with pytest.raises(ParameterError, match="dead"):
        DeformableMirror.build(3, dead=[9])
    with pytest.raises(ParameterError, match="mode_spread"):
        DeformableMirror.build(3, mode_spread=0.5)


def test_input_limit():
    m = DeformableMirror.build(3, input_limit=2.0)
    m.check_command([1.0, -2.0])
    with pytest.raises(ParameterError, match="amplitude.*input_limit"):
        m.check_command([2.5])


# ------------------------------------------------------------------ actuator table


def _write(tmp_path, text, name="table.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_table_sets_the_listed_actuators(tmp_path):
    p = _write(tmp_path, "actuator,mode_hz,damping,gain,delay_s\n4,1234.5,0.2,0,1e-5\n\n0,900,0.05,1.1,0\n")
    table = read_actuator_table(p, 9)
    assert table == {4: (1234.5, 0.2, 0.0, 1e-5), 0: (900.0, 0.05, 1.1, 0.0)}
    ref = DeformableMirror.build(3, mode_spread=0.05, seed=2)
    m = DeformableMirror.build(3, mode_spread=0.05, seed=2, table=table)
    assert m.dead[4] and m.mode_hz[4] == 1234.5 and m.delay_s[4] == 1e-5
    assert m.gain[0] == 1.1 and m.damping[0] == 0.05
    keep = [1, 2, 3, 5, 6, 7, 8]
    np.testing.assert_array_equal(m.mode_hz[keep], ref.mode_hz[keep])


@pytest.mark.parametrize("text, where", [
    ("actuator,mode_hz,damping,gain\n0,1,1,1\n", "row 1"),
    ("", "row 1"),
    ("actuator,mode_hz,damping,gain,delay_s\n0,1000,0.1,1\n", "row 2: expected 5 cells"),
    ("actuator,mode_hz,damping,gain,delay_s\n0,1000,0.1,1,0\nx,1000,0.1,1,0\n", "row 3, column actuator"),
    ("actuator,mode_hz,damping,gain,delay_s\n9,1000,0.1,1,0\n", "row 2, column actuator"),
    ("actuator,mode_hz,damping,gain,delay_s\n-1,1000,0.1,1,0\n", "row 2, column actuator"),
    ("actuator,mode_hz,damping,gain,delay_s\n1,1000,0.1,1,0\n1,1000,0.1,1,0\n", "row 3, column actuator.*twice"),
    ("actuator,mode_hz,damping,gain,delay_s\n1,nan,0.1,1,0\n", "row 2, column mode_hz"),
    ("actuator,mode_hz,damping,gain,delay_s\n1,1000,0,1,0\n", "row 2, column damping"),
    ("actuator,mode_hz,damping,gain,delay_s\n1,1000,0.1,-1,0\n", "row 2, column gain"),
    ("actuator,mode_hz,damping,gain,delay_s\n1,1000,0.1,1,abc\n", "row 2, column delay_s"),
])
def test_bad_tables_are_refused(tmp_path, text, where):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError, match=f"dm.actuator_table: .*{where}"):
        read_actuator_table(p, 9)


def test_missing_or_huge_table_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="dm.actuator_table: .*cannot read"):
        read_actuator_table(tmp_path / "nope.csv", 9)
    p = _write(tmp_path, "actuator,mode_hz,damping,gain,delay_s\n" + "0,1,1,1,0\n" * 200000)
    with pytest.raises(ConfigError, match="bytes"):
        read_actuator_table(p, 9)


# ------------------------------------------------------------------ Shack-Hartmann geometry


def test_valid_subapertures():
    _, _, frac = subaperture_grid(4, 3.0)
    assert (frac >= 0.5).sum() == 12  # the 4 corners are dark
    assert ShackHartmann(n_across=10, pupil_diameter=8.0).n_valid == 80
    wfs = ShackHartmann(n_across=4, pupil_diameter=3.0, pitch_px=16.0)
    assert wfs.frame_shape == (64, 64)
    np.testing.assert_allclose(wfs.rest_px[0], [23.5, 7.5])  # grid cell (0, 1)


def _closed_form_slopes(lo, hi, xj, w):
    """Mean of d phi / dx and d phi / dy over the square [lo, hi] (x, y pitches), in erf."""
    def edge(a, c):  # exp(-(a - c)^2 / (2 w^2))
        return np.exp(-((a - c) ** 2) / (2 * w * w))

    def integral(a0, a1, c):  # int_a0^a1 exp(-(a - c)^2 / 2 w^2) da
        s = w * math.sqrt(2)
        return w * math.sqrt(math.pi / 2) * (erf((a1 - c) / s) - erf((a0 - c) / s))

    area = (hi[0] - lo[0]) * (hi[1] - lo[1])
    gx = (edge(hi[0], xj[0]) - edge(lo[0], xj[0])) * integral(lo[1], hi[1], xj[1]) / area
    gy = (edge(hi[1], xj[1]) - edge(lo[1], xj[1])) * integral(lo[0], hi[0], xj[0]) / area
    return gx, gy


@pytest.mark.parametrize("oversample, tol", [(16, 1e-3), (32, 2.5e-4)])
def test_geometry_matches_the_closed_form_on_full_subapertures(small, oversample, tol):
    mirror, _, _ = small
    wfs = ShackHartmann(n_across=4, pupil_diameter=3.0, oversample=oversample)
    G = wfs.geometry_matrix(mirror)
    M = wfs.n_valid
    full = np.flatnonzero(wfs.illuminated_fraction == 1.0)
    assert full.size == 4
    w = influence_width(mirror.coupling)
    for m in full:
        c = wfs.centres[m]
        lo, hi = c - wfs.side / 2, c + wfs.side / 2
        for j, xj in enumerate(mirror.actuator_xy):
            gx, gy = _closed_form_slopes(lo, hi, xj, w)
            assert G[m, j] == pytest.approx(wfs.slope_px * gx, abs=tol * np.abs(G).max())
            assert G[M + m, j] == pytest.approx(wfs.slope_px * gy, abs=tol * np.abs(G).max())


def test_geometry_matches_a_finite_difference_of_the_wavefront(small):
    """Partly lit subapertures too: the mean of np.gradient of the surface of one actuator on
    a fine grid, over the lit points of each subaperture."""
    mirror, _, _ = small
    wfs = ShackHartmann(n_across=4, pupil_diameter=3.0, oversample=64)
    G = wfs.geometry_matrix(mirror)
    M = wfs.n_valid
    h = 3.0 / 900
    u = -1.5 + h * (np.arange(900) + 0.5)
    Y, X = np.meshgrid(u, u, indexing="ij")
    lit = np.hypot(X, Y) <= 1.5
    for j in (0, 4, 5):
        phi = influence(np.stack([X, Y], -1), mirror.actuator_xy[j:j + 1], mirror.coupling)[..., 0]
        dy, dx = np.gradient(phi, h)
        for m in range(M):
            c = wfs.centres[m]
            sel = lit & (np.abs(X - c[0]) < wfs.side / 2) & (np.abs(Y - c[1]) < wfs.side / 2)
            assert G[m, j] == pytest.approx(dx[sel].mean(), abs=1e-3 * np.abs(G).max())
            assert G[M + m, j] == pytest.approx(dy[sel].mean(), abs=1e-3 * np.abs(G).max())


def test_centred_actuator_is_antisymmetric(small):
    mirror, wfs, G = small
    M = wfs.n_valid
    j = int(np.argmin(np.hypot(*mirror.actuator_xy.T)))
    assert np.allclose(mirror.actuator_xy[j], 0)
    c = wfs.centres
    flip_x = [int(np.argmin(np.hypot(c[:, 0] + x, c[:, 1] - y))) for x, y in c]
    np.testing.assert_allclose(G[:M, j], -G[:M, j][flip_x], atol=1e-12)
    np.testing.assert_allclose(G[M:, j], G[M:, j][flip_x], atol=1e-12)
    np.testing.assert_allclose(G[:M, j], G[M:, j][[int(np.argmin(np.hypot(c[:, 0] - y, c[:, 1] - x))) for x, y in c]], atol=1e-12)
    assert np.abs(G[:M, j]).max() > 0.1


# ------------------------------------------------------------------ plans


def test_sparse_plan_no_subaperture_sees_two(small):
    _, wfs, G = small
    for t in (0.001, 0.01, 0.05):
        plan = sparse_plan(G, t)
        seen = seen_by(G, t)
        assert set(np.unique(plan.patterns)) <= {0.0, 1.0}
        np.testing.assert_array_equal(plan.patterns.sum(0), 1.0)  # every actuator in exactly one pattern
        per_subap = seen.astype(int) @ plan.patterns.T.astype(int)  # [M, P] active actuators seen
        assert per_subap.max() <= 1
        np.testing.assert_array_equal(plan.support, np.concatenate([seen, seen]))
    big = ShackHartmann(n_across=10, pupil_diameter=8.0)
    Gb = big.geometry_matrix(DeformableMirror.build(8))
    plan = sparse_plan(Gb, 0.01)
    assert plan.n_patterns < 52
    assert (seen_by(Gb, 0.01).astype(int) @ plan.patterns.T.astype(int)).max() <= 1


def test_driven_spots_are_the_problems_the_demultiplexing_uses(small):
    """driven_spots marks (pattern, spot) where the pattern moves an actuator the spot's x or y slope
    sees; D demultiplexed with every other response NaN (not fitted) is D from all of them, bit for bit;
    Hadamard and one at a time (its support is every actuator) drive every pair, a sparse plan fewer
    (of the 52-actuator mirror under 70 %)."""
    from torchblur.dm.demux import demultiplex
    _, _, G = small
    Gb = ShackHartmann(n_across=10, pupil_diameter=8.0).geometry_matrix(DeformableMirror.build(8))  # 52 actuators, 80 spots
    rng = np.random.default_rng(3)
    for plan in (sparse_plan(G, 0.001), one_at_a_time_plan(G), hadamard_plan(G), sparse_plan(Gb, 0.001), sparse_plan(Gb, 0.01)):
        d = driven_spots(plan)
        M = plan.support.shape[0] // 2
        sup = plan.support[:M] | plan.support[M:]
        brute = np.array([[bool(np.any((plan.patterns[p] != 0) & sup[m])) for m in range(M)] for p in range(plan.n_patterns)])
        np.testing.assert_array_equal(d, brute)
        P, F = plan.n_patterns, 2
        Y = rng.normal(size=(P, 2 * M, F)) + 1j * rng.normal(size=(P, 2 * M, F))
        C = np.broadcast_to(np.diag([0.01, 0.02]), (P, 2 * M, F, 2, 2)).copy()
        Yn, Cn = Y.copy(), C.copy()
        off = ~np.concatenate([d, d], 1)  # [P, 2M]
        Yn[off], Cn[off] = np.nan, np.nan
        D, Dc = demultiplex(Y, C, plan.patterns, plan.support)
        Dn, Dcn = demultiplex(Yn, Cn, plan.patterns, plan.support)
        np.testing.assert_array_equal(Dn, D)
        np.testing.assert_array_equal(Dcn, Dc)
        assert d.all() if plan.kind != "sparse" else d.mean() < (1 if M == G.shape[0] // 2 else 0.7)


def test_hadamard_and_one_at_a_time(small):
    _, _, G = small
    h = hadamard_plan(G)
    assert h.patterns.shape == (16, 9)
    np.testing.assert_array_equal(h.patterns.T @ h.patterns, 16 * np.eye(9))
    assert h.support.all()
    o = one_at_a_time_plan(G)
    np.testing.assert_array_equal(o.patterns, np.eye(9))
    assert o.n_frames(5, 2, 3) == 9 * 5 * 2 * 3
    assert static_motion_px(o, G) == pytest.approx(np.hypot(G[:12], G[12:]).max())


def test_plan_cost_and_choice():
    G = ShackHartmann(n_across=10, pupil_diameter=8.0).geometry_matrix(DeformableMirror.build(8))
    plan, R, info = choose_plan("auto", G, budget_frames=20000, n_freq=20, n_exposures=2)
    assert plan.kind == min(info["costs"], key=info["costs"].get) == "hadamard"
    assert R == 20000 // (64 * 20 * 2)
    assert info["cost_ratio_to_one_at_a_time"] < 0.25
    o = one_at_a_time_plan(G)
    assert plan_cost(o, G) == pytest.approx(52 * static_motion_px(o, G) ** 2)
    plan, R, _ = choose_plan("sparse", G, budget_frames=None, n_freq=3, n_exposures=2, n_repeats=2)
    assert plan.kind == "sparse" and R == 2
    with pytest.raises(ParameterError, match="dm_plan.budget_frames"):
        choose_plan("hadamard", G, budget_frames=100, n_freq=20, n_exposures=2)
    with pytest.raises(ParameterError, match="dm_plan.kind"):
        choose_plan("random", G, budget_frames=100, n_freq=2, n_exposures=2)


# ------------------------------------------------------------------ the simulated DM rig


def _quiet_camera():
    from torchblur.render.camera import CameraModel

    return CameraModel(dark_level_adu=0.0, read_noise_e=0.0, shot_noise=False, quantize=False, full_well_e=1e12, bit_depth=32)


def _small_rig(small, **kw):
    from torchblur.rig.dm import SimulatedDMRig

    mirror, wfs, _ = small
    kw = {"camera": _quiet_camera(), "peak_e_per_s": 1e5, "jitter_s": 1e-6, "seed": 5, **kw}
    return SimulatedDMRig(mirror=mirror, wfs=wfs, **kw)


def test_rig_frames_match_a_direct_render_of_the_truth(small):
    """Every spot rendered over the whole frame (render_blur, pixel integration) with the
    motion from G and each actuator's Plant (not the mirror's response formula)."""
    import torch
    from torchblur.render.blur import RenderSettings, render_blur
    from torchblur.render.psf import GaussianPSF
    from torchblur.render.trajectory import Sinusoid
    from torchblur.render.window import ExposureWindow

    mirror, wfs, G = small
    rig = _small_rig(small, latency_s=20e-6)
    pattern = np.array([1.0, -1.0, 0.0, 0.5, 1.0, 0.0, -0.5, 0.0, 1.0])
    f, amp = 650.0, 1.0
    cap = rig.pattern_sine(pattern, f, amp, [0.3 / f, 0.8 / f], 0.1 / f, 2)
    assert cap.frames.shape == (2, 2, 64, 64)
    h = np.array([complex(mirror.plant(j).frequency_response(2 * np.pi * f)) for j in range(9)])
    Y = amp * (G * h) @ pattern
    M = wfs.n_valid
    start = cap.meta["actual_start_s"].reshape(-1)
    win = ExposureWindow(start, cap.exposure_s.reshape(-1))
    ref = 0
    for m in range(M):
        yx = np.array([Y[m], Y[M + m]])
        traj = Sinusoid(torch.tensor(np.abs(yx)), torch.tensor(np.angle(yx)), torch.tensor(2 * np.pi * f, dtype=torch.float64))
        psf = GaussianPSF(torch.tensor(wfs.rest_px[m]), wfs.sigma_px ** 2 * torch.eye(2, dtype=torch.float64), 1e5)
        ref = ref + render_blur(traj, psf, win, height=64, width=64, settings=RenderSettings(pixel_integration=True, max_nodes=1 << 20))
    np.testing.assert_allclose(cap.frames.reshape(-1, 64, 64).numpy(), ref.numpy(), rtol=0, atol=1e-7 * float(ref.max()))
    # latency + trigger delay: the windows start at the trigger + 20 us (+- jitter)
    d = (start - cap.trigger_time_s.reshape(-1)).numpy()
    assert np.all(np.abs(d - 20e-6) < 6e-6)


def test_rig_truth_inputs_and_limits(small):
    mirror, wfs, G = small
    rig = _small_rig(small)
    f = np.array([100.0, 700.0])
    D = rig.truth_D(f)
    assert D.shape == (24, 9, 2)
    np.testing.assert_allclose(D, G[:, :, None] * mirror.response(f)[None])
    np.testing.assert_allclose(rig.truth_D(700.0), D[..., 1])
    a = rig.sine(300.0, 1.5, [1e-3], 0.0, 1, input="a4")
    b = _small_rig(small).pattern_sine(np.eye(9)[4], 300.0, 1.5, [1e-3], 0.0, 1)
    np.testing.assert_array_equal(a.frames.numpy(), b.frames.numpy())
    assert rig.still(1, 1e-3).frames.shape == (1, 64, 64)
    with pytest.raises(ParameterError, match="input"):
        rig.sine(300.0, 1.0, [1e-3], 0.0, 1, input="x")
    with pytest.raises(ParameterError, match="multisine"):
        rig.multisine([100.0], [1.0], [0.0], [1e-3], 0.0, 1)
    with pytest.raises(ParameterError, match="amplitude.*crop"):
        rig.pattern_sine(np.ones(9), 300.0, 50.0, [1e-3], 0.0, 1)
    limited = _small_rig((DeformableMirror.build(3, input_limit=1.0), wfs, G))
    with pytest.raises(ParameterError, match="amplitude.*input_limit"):
        limited.pattern_sine(np.eye(9)[0], 300.0, 1.5, [1e-3], 0.0, 1)
    from torchblur.errors import ShapeError

    with pytest.raises(ShapeError, match="pattern"):
        rig.pattern_sine(np.ones(8), 300.0, 1.0, [1e-3], 0.0, 1)
