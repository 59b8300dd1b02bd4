"""Dense height maps: known parallax fields, steps kept sharp, honest σ, writers read back."""

import numpy as np
import pytest
from scipy import ndimage

from semlab import formats, heightmap as hm, plots
from semlab.errors import ImageError, SemlabError
from semlab.reconstruct import parallax_height
from semlab.synth import make_scene, project_points, render


def _texture(shape, seed=0, sigma=1.2):
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.normal(size=shape), sigma)
    return t / t.std()


def _warp(img, dx):
    """view1(x + dx(x), y) = img(x, y): sample img at x - dx (dx smooth or not)."""
    hgt, wid = img.shape
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(float)
    return ndimage.map_coordinates(img, [yy, xx - dx], order=3, mode="reflect")


@pytest.fixture(scope="module")
def scene_pair():
    """A synthetic scene at -5/+5 degrees with the true view-1 x of every view-0 pixel."""
    shape = (112, 144)
    sc = make_scene(seed=2, size=shape)
    rng = np.random.default_rng(5)
    i0, x0, y0 = render(sc, shape, -5.0, rng=rng)
    i1, _, _ = render(sc, shape, 5.0, rng=rng)
    true1 = project_points(sc, np.column_stack([x0.ravel(), y0.ravel()]), 5.0, shape)
    return i0, i1, true1[:, 0].reshape(shape), sc


@pytest.fixture(scope="module")
def scene_parallax(scene_pair):
    i0, i1, _, _ = scene_pair
    return hm.dense_parallax(i0, i1)


def test_dense_parallax_on_a_scene_is_accurate_and_its_sigma_honest(scene_pair, scene_parallax):
    _, _, tx, _ = scene_pair
    p = scene_parallax
    inner = (slice(12, -12), slice(12, -12))
    v = p.valid[inner]
    assert v.mean() > 0.95
    e = (p.x1_px - tx)[inner][v]
    assert np.sqrt(np.mean(e ** 2)) < 0.3
    cover = np.mean(np.abs(e) < p.sigma_px[inner][v])
    assert 0.55 < cover < 0.9, cover
    assert p.sigma_scale >= 1.0


def test_dense_beats_deepflow_on_a_scene(scene_pair, scene_parallax):
    import cv2

    from semlab.matching import _norm8

    i0, i1, tx, _ = scene_pair
    df = cv2.optflow.createOptFlow_DeepFlow().calc(_norm8(i0, 14, 2.0), _norm8(i1, 14, 2.0), None)
    xx = np.arange(i0.shape[1])[None, :]
    inner = (slice(12, -12), slice(12, -12))
    v = scene_parallax.valid[inner]
    ours = np.sqrt(np.mean(((scene_parallax.x1_px - tx)[inner][v]) ** 2))
    deep = np.sqrt(np.mean(((xx + df[..., 0] - tx)[inner][v]) ** 2))
    assert ours < 0.8 * deep, (ours, deep)


def test_step_in_parallax_is_not_smoothed_by_the_subset():
    img = _texture((80, 96), seed=1)
    x = np.arange(96)[None, :] * np.ones((80, 1))
    step = np.where(x >= 48, 1.0, 0.0)
    rng = np.random.default_rng(3)
    v1 = _warp(img, step) + rng.normal(0, 0.05, img.shape)
    img = img + rng.normal(0, 0.05, img.shape)
    p = hm.dense_parallax(img, v1, params=hm.DenseParams(half_window=7))
    prof = np.full(96, np.nan)
    prof[10:86] = np.nanmedian((p.x1_px - x)[20:60, 10:86], axis=0)
    # 10-90 % rise of the measured step, in pixels
    rise = np.flatnonzero((prof > 0.1) & (prof < 0.9))
    rise = rise[(rise > 30) & (rise < 66)]
    assert len(rise) <= 3, prof[36:60].round(2)          # a 15-px subset alone smears ~11 px
    plain = hm.dense_parallax(img, v1, params=hm.DenseParams(half_window=7, fusion_radius_px=0))
    prof0 = np.full(96, np.nan)
    prof0[10:86] = np.nanmedian((plain.x1_px - x)[20:60, 10:86], axis=0)
    rise0 = np.flatnonzero((prof0 > 0.1) & (prof0 < 0.9))
    rise0 = rise0[(rise0 > 30) & (rise0 < 66)]
    assert len(rise) < len(rise0)
    # far from the step both sides are exact
    assert np.abs(prof[20:36]).max() < 0.03 and np.abs(prof[62:76] - 1).max() < 0.03


def test_roi_gives_the_values_of_the_whole_image(scene_pair, scene_parallax):
    i0, i1, _, _ = scene_pair
    roi = (40, 30, 100, 80)
    p = hm.dense_parallax(i0, i1, roi=roi)
    assert p.x1_px.shape == (50, 60) and p.roi == roi
    whole = scene_parallax.x1_px[30:80, 40:100]
    both = p.valid & np.isfinite(whole)
    assert both.mean() > 0.95
    assert np.nanmax(np.abs(p.x1_px - whole)[both]) < 0.05
    gx, gy = p.grid()
    assert gx[0, 0] == 40 and gy[0, 0] == 30


def test_tiles_with_a_shared_guess_equal_the_whole_image(scene_pair):
    i0, i1, _, _ = scene_pair
    g = hm.initial_guess(i0, i1)
    whole = hm.dense_parallax(i0, i1, guess=g)
    tiles = [(0, 0, 72, 56), (72, 0, 144, 56), (0, 56, 72, 112), (72, 56, 144, 112)]
    for roi in tiles:
        t = hm.dense_parallax(i0, i1, roi=roi, guess=g, calibration=whole.calibration)
        sl = (slice(roi[1], roi[3]), slice(roi[0], roi[2]))
        assert np.array_equal(t.valid, whole.valid[sl])
        np.testing.assert_allclose(t.x1_px[t.valid], whole.x1_px[sl][t.valid], atol=1e-9)
        np.testing.assert_allclose(t.sigma_px[t.valid], whole.sigma_px[sl][t.valid], rtol=1e-6)


def test_bad_inputs_raise():
    img = _texture((40, 50))
    with pytest.raises(ImageError, match="one shape"):
        hm.dense_parallax(img, img[:, :-1])
    with pytest.raises(SemlabError, match="roi"):
        hm.dense_parallax(img, img, roi=(10, 10, 5, 20))
    with pytest.raises(SemlabError, match="tilt_deg"):
        hm.dense_heights(img, img, pixel_size_um=0.03)
    with pytest.raises(SemlabError, match="pixel_size_um"):
        hm.dense_heights(img, img, tilt_deg=(-5, 5))


def test_height_models_agree_with_the_closed_form():
    rng = np.random.default_rng(0)
    u0, v0 = rng.uniform(0, 500, 50), rng.uniform(0, 400, 50)
    u1 = u0 + rng.normal(0, 2, 50)
    z = parallax_height(u0, u1, -5.0, 5.0, 0.03, 250.0, 250.0)
    m = hm.height_model_from_tilts(-5.0, 5.0, 0.03, 250.0)
    np.testing.assert_allclose(m.height(u1, v0, u0, v0), z, atol=1e-9)
    # fitted to points whose heights sit above a tilted reference plane: exact too
    zref = z - (0.001 * u0 - 0.002 * v0 + 0.05)
    pts = np.stack([np.column_stack([u0, v0]), np.column_stack([u1, v0])], axis=1)
    mf = hm.height_model_from_points(pts, zref)
    assert mf.rms_um < 1e-9
    np.testing.assert_allclose(mf.height(u1, v0, u0, v0), zref, atol=1e-8)
    assert mf.sigma(0.1) == pytest.approx(abs(m.coef[0]) * 0.1, rel=1e-6)


def test_dense_heights_of_a_scene(scene_pair):
    i0, i1, _, sc = scene_pair
    res = hm.dense_heights(i0, i1, tilt_deg=(-5.0, 5.0), pixel_size_um=sc.pixel_size_um)
    assert res.z_um.dtype == np.float32 and res.z_um.shape == i0.shape
    assert np.all(np.isnan(res.z_um[~res.valid]))
    meta = res.metadata()
    assert meta["params"]["half_window"] == 7 and 0 < meta["measured_fraction"] <= 1


def test_write_results_read_back_exactly(tmp_path, scene_pair):
    i0, i1, _, sc = scene_pair
    res = hm.dense_heights(i0, i1, tilt_deg=(-5.0, 5.0), pixel_size_um=0.03,
                           roi=(0, 0, 96, 80))
    res.z_um[5:9, 5:9] = np.nan                       # not-measured pixels survive
    paths = hm.write_heightmap_results(res, tmp_path, regions={"left": (0, 0, 48, 80)})
    z_tif, desc = formats.read_float_tiff(paths["heightmap.tif"])
    assert desc["pixel_size_um"] == 0.03
    z_x3p, step = formats.read_x3p_um(paths["heightmap.x3p"])
    assert step == pytest.approx(0.03)
    assert np.array_equal(z_x3p.astype(np.float32), z_tif, equal_nan=True)
    assert np.array_equal(z_tif, res.z_um, equal_nan=True)
    z_gsf, head = formats.read_gsf(paths["heightmap.gsf"])
    assert head["XYUnits"] == "m" and int(head["XRes"]) == 96
    np.testing.assert_allclose(z_gsf, z_tif, rtol=1e-6, atol=1e-9)
    assert np.array_equal(np.isnan(z_gsf), np.isnan(z_tif))
    from plyfile import PlyData

    ply = PlyData.read(str(paths["heightmap.ply"]))
    assert ply["vertex"].count == int(np.isfinite(z_tif).sum())
    rows = paths["surface_parameters.csv"].read_text().splitlines()
    assert rows[0].startswith("region,n_pixels") and rows[2].startswith("left,")
    assert paths["bands.csv"].read_text().startswith("band_id,source")
    with pytest.raises(SemlabError, match="exists already"):
        hm.write_heightmap_results(res, tmp_path)


def test_hillshade():
    flat = np.zeros((20, 30))
    assert np.allclose(hm.hillshade(flat, 0.03, altitude_deg=30), 0.5)
    x = np.arange(30)[None, :] * np.ones((20, 1)) * 0.03
    # light from the west (azimuth 270): a surface rising to the east faces it
    lit = hm.hillshade(0.5 * x, 0.03, azimuth_deg=270).mean()
    level = hm.hillshade(flat, 0.03, azimuth_deg=270).mean()
    away = hm.hillshade(-0.5 * x, 0.03, azimuth_deg=270).mean()
    assert lit > level + 0.1 and level > away + 0.1
    z = flat.copy()
    z[3, 3] = np.nan
    assert np.isnan(hm.hillshade(z, 0.03)[3, 3])


def test_heightmap_plots(scene_pair):
    import matplotlib.pyplot as plt

    z = np.random.default_rng(0).normal(0, 0.05, (30, 40))
    z[0, :5] = np.nan
    fig = plots.show_heightmap_panels(z, np.full_like(z, 0.01), pixel_size_um=0.03)
    assert len(fig.axes) >= 3 and "measured" in fig.axes[2].get_title()
    ax = plots.show_hillshade(z, 0.03)
    assert "hill shade" in ax.get_title()
    plt.close("all")


def test_smoothing_prior_averages_noise_but_keeps_steps():
    rng = np.random.default_rng(4)
    shape = (60, 90)
    x = np.arange(90)[None, :] * np.ones((60, 1))
    truth = np.where(x >= 45, 0.5, 0.0)                      # a step of 10 σ
    sig = np.full(shape, 0.05)
    # noise correlated over ~3 px (like overlapping subsets), 1σ = 0.05
    noise = ndimage.gaussian_filter(rng.normal(size=shape), 1.0)
    v = truth + 0.05 * noise / noise.std()
    valid = np.ones(shape, bool)
    sm, ssm = hm.smooth_bilateral(v, sig, valid, radius_px=8, range_k=2.0, corr_px=3)
    flat = (slice(10, 50), slice(10, 35))
    assert np.std((sm - truth)[flat]) < 0.5 * np.std((v - truth)[flat])
    assert np.all(ssm <= sig + 1e-12) and np.all(ssm[flat] < 0.05)
    prof = np.median(sm[10:50], axis=0)
    assert np.sum((prof > 0.05) & (prof < 0.45)) <= 2          # the step stays sharp
    assert abs(prof[30] - 0.0) < 0.02 and abs(prof[60] - 0.5) < 0.02


def test_heightmap_from_stereo_with_too_few_points_uses_the_tilts(scene_pair):
    from types import SimpleNamespace

    i0, i1, tx, sc = scene_pair
    exp = SimpleNamespace(views=lambda: [i0, i1], pixel_size_um=sc.pixel_size_um,
                          stereo=SimpleNamespace(camera="affine"))
    pts = np.array([[[30.0, 30.0], [30.5, 30.0]], [[90.0, 40.0], [90.2, 40.0]],
                    [[60.0, 80.0], [59.8, 80.0]], [[110.0, 90.0], [110.1, 90.0]],
                    [[40.0, 70.0], [40.3, 70.0]]])
    stereo = SimpleNamespace(pts=pts, z_um=np.zeros(5), tilt_deg=np.array([-5.0, 5.0]))
    res = hm.heightmap_from_stereo(exp, stereo)
    assert res.model.source == "tilts" and any("only 5 points" in n for n in res.notes)
    assert res.valid.mean() > 0.5


def _fine_texture_pair(noise=0.05):
    """Texture sharp at the pixel scale (Immerkær's noise estimate ~2x the true ``noise``),
    a gentle parallax slope ``x1 - x0 = 0.4 + 0.002 x1``; returns views and the true x1."""
    shape = (96, 128)
    rng = np.random.default_rng(7)
    t = _texture(shape, 1, 1.0)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    t1 = ndimage.map_coordinates(t, [yy, xx - (0.4 + 0.002 * xx)], order=3, mode="reflect")
    x1 = (xx + 0.4) / (1 - 0.002)
    return t + rng.normal(0, noise, shape), t1 + rng.normal(0, noise, shape), x1


def test_sigma_is_honest_with_the_calibrated_noise():
    """On a fine texture Immerkær's estimate is ~2x the true noise, and the subset map's σ
    (σ factor clipped at >= 1) covered 88 % within 1σ; with the matcher's calibrated noise
    (icgn_refine's default) the noise used is the truth and the 1σ covers 55-80 %."""
    from semlab.noise import image_noise_sigma

    a, b, x1 = _fine_texture_pair()
    assert image_noise_sigma(a) > 1.6 * 0.05
    p = hm.dense_parallax(a, b)
    np.testing.assert_allclose(p.calibration["noise_sigma"], 0.05, rtol=0.15)
    inner = (slice(12, -12), slice(12, -12))
    v = p.valid[inner]
    assert v.mean() > 0.95
    e = (p.x1_px - x1)[inner][v]
    cover = np.mean(np.abs(e) < p.sigma_px[inner][v])
    assert 0.55 < cover < 0.8, cover


def test_heightmap_from_stereo_uses_the_matchers_noise():
    """One noise estimate per run: the map's noise is the one the stereo step recorded, else
    the matcher's calibrated measurement at the stereo matches (not Immerkær's again). The
    height model's note says an exact fit (two views' heights are linear in the parallax) in
    words, not as a residual of 1e-11 nm."""
    from types import SimpleNamespace

    from semlab.noise import calibrated_noise_sigma

    a, b, x1 = _fine_texture_pair()
    exp = SimpleNamespace(views=lambda: [a, b], pixel_size_um=0.03,
                          stereo=SimpleNamespace(camera="affine"))
    gy, gx = np.mgrid[16:80:8, 16:112:8]
    p0 = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    p1 = np.column_stack([x1[gy, gx].ravel(), gy.ravel()])
    pts = np.stack([p0, p1], 1)
    stereo = SimpleNamespace(pts=pts, z_um=0.03 * (p1[:, 0] - p0[:, 0]),
                             tilt_deg=np.array([-5.0, 5.0]))
    roi = (20, 20, 76, 60)
    res = hm.heightmap_from_stereo(exp, stereo, roi=roi)
    want = calibrated_noise_sigma(a, b, p0, p1)
    assert tuple(res.parallax.calibration["noise_sigma"]) == want
    np.testing.assert_allclose(want, 0.05, rtol=0.15)
    assert any("calibrated on the 96 stereo matches" in n for n in res.notes)
    assert any(n.startswith("height model fitted to 96 points, exact") for n in res.notes)
    # recorded by the stereo step: taken as it is, by both dense methods
    from semlab.variational import VariationalParams

    stereo.calibration = {"noise_sigma": [0.07, 0.08, 0.09]}
    # heights not linear in the views-0/1 parallax (as with 3+ views): the residual is given
    stereo.z_um = stereo.z_um + 0.002 * np.sin(p0[:, 1] / 7.0)
    for params in (None, VariationalParams()):
        res = hm.heightmap_from_stereo(exp, stereo, roi=roi, params=params)
        np.testing.assert_allclose(res.parallax.calibration["noise_sigma"], (0.07, 0.08))
        assert any("recorded by the stereo step" in n for n in res.notes)
        fit = [n for n in res.notes if n.startswith("height model fitted to 96 points")]
        assert len(fit) == 1 and " nm" in fit[0] and "exact" not in fit[0], fit


def test_heightmap_keeps_its_parallax_in_float32():
    """The map keeps the parallax it came from in float32 (half the memory of every process
    that loads it), its heights computed before from the float64 positions."""
    from semlab.heightmap import DenseParallax, DenseParams, HeightModel, _heights

    rng = np.random.default_rng(0)
    h, w = 40, 60
    x1 = 3000.0 + np.arange(w)[None, :] + 0.1 * rng.standard_normal((h, w))
    par = DenseParallax(x1_px=x1, y1_px=np.broadcast_to(np.arange(h)[:, None], (h, w)) * 1.0,
                        sigma_px=np.full((h, w), 0.05), sigma_y_px=np.full((h, w), 0.05),
                        valid=np.ones((h, w), bool), zncc=np.full((h, w), 0.9),
                        roi=(3000, 0, 3000 + w, h), sigma_scale=1.0, params=DenseParams())
    model = HeightModel(coef=(1.0, 0.0, -1.0, 0.0, 0.0))
    m = _heights(par, model, 0.03)
    for k in ("x1_px", "y1_px", "sigma_px", "sigma_y_px", "zncc"):
        assert getattr(m.parallax, k).dtype == np.float32, k
    # heights from the float64 positions: the difference x1 - x0 ~ 0.1 px exactly, not
    # rounded to float32's 2.4e-4 px at 3000 px
    gx, _ = par.grid()
    np.testing.assert_allclose(m.z_um, (x1 - gx).astype(np.float32), rtol=1e-6, atol=1e-7)
    assert np.abs(m.parallax.x1_px - x1).max() <= 2.5e-4
