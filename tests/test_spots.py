"""Many spots (issue 6 part 2): the grid model, detection with varying PSFs, crops at the frame
edge, the config, and a short identification with a missing spot and one half outside the frame."""
import math

import numpy as np
import pytest
import torch

from torchblur.render.camera import CameraModel
from torchblur.config import load_config
from torchblur.errors import ConfigError, ParameterError
from torchblur.systems.lti import Plant
from torchblur.rig.simulated import SimulatedRig
from torchblur.image.spots import SpotGrid, crop_spots, crop_valid, locate_spots, raster_order, spot_labels


def test_grid_layout_follows_the_model():
    g = SpotGrid(3, 3, 30.0, sigma_px=1.5, sigma_variation=0.4, elongation=0.5, gain_variation=0.2, rotation_rad=0.3,
                 missing=(5,))
    lay = g.layout((96, 96), 2)
    assert len(lay) == 8 and g.n_spots == 8 and lay.index.tolist() == [0, 1, 2, 3, 4, 6, 7, 8]
    np.testing.assert_allclose(lay.rest_px[0].numpy(), [17.5, 17.5])
    np.testing.assert_allclose(lay.rest_px[4].numpy(), [47.5, 47.5])  # the centre
    np.testing.assert_allclose(lay.cov[4].numpy(), 1.5**2 * np.eye(2), atol=1e-12)  # round at the centre
    ev, vec = np.linalg.eigh(lay.cov[0].numpy())  # corner: sigma 1.5 * 1.4, axis ratio 1.5^2, major axis radial
    s = 1.5 * 1.4
    np.testing.assert_allclose(np.sqrt(ev), [s / 1.5, s * 1.5], rtol=1e-12)
    assert abs(abs(vec[0, 1]) - abs(vec[1, 1])) < 1e-9  # major axis along the diagonal
    # G_k = (1 + 0.2 u) R(0.3 v): top-left u = v = -1
    th = -0.3
    np.testing.assert_allclose(lay.response[0].numpy(), 0.8 * np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]))
    assert g.layout((96, 96), 1).response.shape == (8, 2, 1)
    with pytest.raises(ParameterError, match="gain_variation"):
        SpotGrid(2, 2, 20.0, gain_variation=1.0)
    with pytest.raises(ParameterError, match="missing"):
        SpotGrid(2, 2, 20.0, missing=(4,))
    assert spot_labels(2) == ["s0.x", "s0.y", "s1.x", "s1.y"]


def test_raster_order_rows_then_columns():
    c = torch.tensor([[50.0, 31.0], [10.0, 9.0], [30.5, 30.0], [51.0, 10.5], [9.0, 29.0]], dtype=torch.float64)
    assert raster_order(c, 20.0).tolist() == [1, 3, 4, 2, 0]


def test_crops_beyond_the_frame_are_zero_and_invalid():
    img = torch.arange(20.0 * 30, dtype=torch.float64).reshape(20, 30)
    off = torch.tensor([[2, 3], [-4, 15], [25, -2]])
    c = crop_spots(img, off, (8, 8))
    v = crop_valid((20, 30), off, (8, 8))
    assert c.shape == (3, 8, 8) and v.shape == (3, 8, 8)
    torch.testing.assert_close(c[0], img[3:11, 2:10])
    assert v[0].all() and not v[1].all() and not v[2].all()
    assert (c[~v] == 0).all()
    torch.testing.assert_close(c[1][v[1]], img[15:20, 0:4].reshape(-1))
    batch = crop_spots(torch.stack([img, 2 * img]), off, (8, 8))  # batch == stacked singles
    torch.testing.assert_close(batch[1], 2 * c)
    m = crop_spots(torch.ones(20, 30, dtype=torch.bool), off, (8, 8))
    assert m.dtype == torch.bool and torch.equal(m, v)


@pytest.fixture(scope="module")
def grid_still():
    grid = SpotGrid(3, 3, 30.0, sigma_px=1.6, sigma_variation=0.3, elongation=0.3, gain_variation=0.2, missing=(7,))
    rig = SimulatedRig(plant=Plant((1.0,), (1e-3, 1.0)), camera=CameraModel(), frame_shape=(90, 90), spots=grid, seed=4)
    te = 2e-3
    still = (rig.still(n=8, exposure_s=te).frames - rig.camera.dark_level_adu).mean(0)
    return rig, still, te


def test_spots_found_with_their_own_psfs(grid_still):
    rig, still, te = grid_still
    sp = locate_spots(still, exposure_s=te, noise_std=math.sqrt(25 + float(still.max())) / math.sqrt(8), pitch_px=30.0)
    lay = rig.spots
    assert len(sp) == 8  # 9 lenslets, one missing
    np.testing.assert_allclose(sp.psf.center.numpy(), lay.rest_px.numpy(), atol=0.05)  # raster order = the grid's
    # The rig renders pixel-integrated Gaussians; the PSF is fitted point-sampled, as the sweep
    # fit samples, so its truth is the point-sampled equivalent: a pixel's box adds 1/12 px^2 to
    # the covariance, and the peak drops as the area grows (the light is the same).
    cov_pt = lay.cov + torch.eye(2, dtype=lay.cov.dtype) / 12
    amp_pt = 1e6 * torch.sqrt(torch.linalg.det(lay.cov) / torch.linalg.det(cov_pt))
    np.testing.assert_allclose(sp.psf.cov.numpy(), cov_pt.numpy(), rtol=0.05, atol=0.03)
    np.testing.assert_allclose(sp.psf.amplitude.numpy(), amp_pt.numpy(), rtol=0.03)
    assert sp.size == (30, 30) and not sp.clipped.any() and (sp.inside_fraction > 0.999).all()


def test_a_spot_found_twice_is_fitted_once():
    """A detached lobe beside a spot (as an aberrated diffraction spot has) is a connected component
    of its own, and its crop's fit lands within half a pitch of the spot: one spot, fitted once."""
    from torchblur.image.detection import find_spots

    yy, xx = torch.meshgrid(torch.arange(32, dtype=torch.float64), torch.arange(64, dtype=torch.float64), indexing="ij")
    truth = torch.tensor([[15.3, 15.6], [47.6, 15.4]], dtype=torch.float64)
    still = sum(2000 * torch.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.6**2)) for x, y in truth.tolist())
    still = still + 300 * torch.exp(-((xx - 57.6) ** 2 + (yy - 19.4) ** 2) / (2 * 0.8**2))  # 10.8 px from the second spot
    still = still + 5 * torch.randn(still.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert len(find_spots(still, noise_std=5.0)[0]) == 3  # the lobe is a component of its own
    sp = locate_spots(still, exposure_s=1e-3, noise_std=5.0, pitch_px=32.0)
    assert len(sp) == 2
    np.testing.assert_allclose(sp.psf.center.numpy(), truth.numpy(), atol=0.3)


def test_spots_config_errors_name_the_key():
    for over, key in ((["spots.rows=-1"], "spots.rows"), (["spots.rows=2", "spots.cols=0"], "spots.cols"),
                      (["spots.rows=2", "spots.cols=2", "spots.gain_variation=1.5"], "spots.gain_variation"),
                      (["spots.rows=2", "spots.cols=2", "spots.missing=[4]"], "spots.missing[0]"),
                      (["spots.rows=2", "spots.cols=2", "spots.pitch_px=20"], "excitation.target_px"),
                      (["spots.rows=2", "spots.cols=2", "spots.crop_px=100"], "spots.crop_px")):
        with pytest.raises(ConfigError) as info:
            load_config(None, over)
        assert str(info.value).startswith(key + ":"), str(info.value)
    assert not load_config().spots.enabled


EDGE = ["sweep.freq_hz=[3,450]", "camera.height=32", "camera.width=80", "spots.rows=1", "spots.cols=4", "spots.pitch_px=22",
        "spots.center_px=[47.5,15.5]", "spots.missing=[1]", "spots.sigma_px=1.6", "spots.gain_variation=0.3",
        "excitation.target_px=4", "model.max_order=2", "seed=5"]


@pytest.fixture(scope="module")
def edge_run():
    """Four lenslets in a row, the second missing, the last centred 1.5 px beyond the frame's
    right edge (a quarter of its light in the frame)."""
    from torchblur.identify.run import identify

    return identify(load_config(None, EDGE), progress=False)


def test_short_spots_identification_with_missing_and_edge_spots(edge_run):
    res = edge_run
    frf = res.frf
    assert frf.output_labels == ("s0.x", "s0.y", "s1.x", "s1.y", "s2.x", "s2.y") and frf.input_labels == ("u_x",)
    log = "\n".join(res.log)
    assert "3 found (grid 1x4 = 4)" in log and "1 of the 4 expected spot(s) not found" in log
    assert "spots psf: Gaussian per spot (each of the 2 spots' Gaussians explains its still" in log  # the edge spot: not fitted
    assert frf.meta["psf"] == "gaussian"
    assert "s2 flagged at every point (mostly outside the frame)" in log
    assert np.isnan(frf.response[4:]).all()  # the edge spot: flagged, not fitted
    t = res.truth
    for o in (0, 2):  # the two whole spots, along x (gains 0.7 and 1.1 of the plant)
        em = np.abs(frf.magnitude[o, 0] - np.abs(t[o, 0])) / np.abs(t[o, 0])
        ep = np.degrees(np.abs(np.angle(frf.response[o, 0] / t[o, 0])))
        assert em.max() < 0.03 and ep.max() < 2.0, (o, em, ep)
        # no motion along y (rotation 0): the fitted y amplitude is at the noise level
        assert np.all(frf.magnitude[o + 1, 0] < 0.02 * frf.magnitude[o, 0])
    np.testing.assert_allclose(np.abs(t[2, 0]) / np.abs(t[0, 0]), 1.1 / 0.7)  # spots move by their own gains
    assert res.images.shape[:4] == (1, 2, 3, 4) and res.images.shape[-2:] == (22, 22)


def test_spots_run_outputs_read_back_with_each_channels_judgement(edge_run, tmp_path, monkeypatch):
    """The spots run's outputs (the figures left out: their own tests draw them) read back, each
    spot channel's model with its judgement, the --json line too. The run is the spots route on
    a 1x4 row (edge_run: reduced from configs/identify_spots.yaml's 3x3 grid and 2x2 plant, whose
    calibration alone takes ~30 s)."""
    import json

    from torchblur.identify import outputs
    from torchblur.identify.report import run_summary, verdict_summary
    from readback import assert_reads_back

    monkeypatch.setattr(outputs, "write_figures", lambda *a, **k: None)
    v = outputs.write_outputs(load_config(None, EDGE), edge_run, tmp_path, 1.0, "test")
    got = assert_reads_back(tmp_path, json.dumps({**run_summary(edge_run, tmp_path, 1.0), **verdict_summary(v)}))
    assert got["frf.json"].output_labels == edge_run.frf.output_labels and got["model.json"].output_labels == ("s0.x", "s0.y", "s1.x", "s1.y")
    assert len(json.loads((tmp_path / "model.json").read_text())["judgement"]) == 4  # one per channel that has a model


def test_a_flagged_spot_is_left_out_of_the_model_not_the_others(edge_run):
    """The edge spot has no valid point; the other spots still get their models."""
    res = edge_run
    log = "\n".join(res.log)
    assert "output(s) s2.x, s2.y have a channel with no valid point and are left out of the model" in log
    assert res.model is not None
    assert res.model.output_labels == ("s0.x", "s0.y", "s1.x", "s1.y")
