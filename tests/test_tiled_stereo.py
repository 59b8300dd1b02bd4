"""The run's tiled stereo steps equal the untiled ones on small scenes cut into tiles."""

import numpy as np
import pytest
from scipy import ndimage

from semlab import tiled_stereo
from semlab.errors import SemlabError
from semlab.heightmap import DenseParams, dense_parallax
from semlab.matching import auto_match
from semlab.tiled_stereo import TilingParams, tiled_auto_match, tiled_parallax


def _pair(h=256, w=320, seed=0, drift=(0.0, 0.0)):
    """Band-limited texture; view 1 sees it through a parallax of 0.5-2.5 px (a slow wave)
    plus a uniform shift ``drift`` (x, y) px, both with noise."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.normal(size=(h + 80, w + 80)), 2.0) * 50 + 100
    yy, xx = np.mgrid[0:h + 80, 0:w + 80].astype(float)
    par = 1.5 + 1.0 * np.sin(xx / 40) * np.cos(yy / 50)
    cur = ndimage.map_coordinates(img, [yy + 0.2 - drift[1], xx + par - drift[0]], order=3,
                                  mode="mirror")
    ref = img[40:40 + h, 40:40 + w] + rng.normal(0, 0.5, (h, w))
    cur = cur[40:40 + h, 40:40 + w] + rng.normal(0, 0.5, (h, w))
    return ref, cur


@pytest.fixture(scope="module")
def pair():
    return _pair()


def test_tiled_auto_match_equals_untiled(pair):
    ref, cur = pair
    tiling = TilingParams(tile_px=128, halo_px=48)                         # 2 × 3 tiles
    # the subset matches (stage 9, the variational map, is judged below)
    kw = dict(spacing_px=8, smooth_sigma_px=0.0, variational_fusion=False)
    a = auto_match([ref, cur], progress=False, **kw)
    b = tiled_auto_match([ref, cur], tiling=tiling, progress=False, **kw)
    # the same grid, in the same order, each point once
    assert np.array_equal(a.pts[:, 0], b.pts[:, 0])
    assert np.array_equal(a.source_index, b.source_index) and b.params == a.params
    assert (a.valid == b.valid).mean() >= 0.99 and a.valid.sum() > 900
    ok = a.valid & b.valid
    d = np.abs(a.pts[ok, 1] - b.pts[ok, 1]).max(axis=1)
    # the IC-GN matches converge to the same positions; the band-aware choice between the
    # square and the oriented subset uses σ from each tile's own noise estimate, so a few
    # per cent of points take the other subset (differences up to ~0.06 px here)
    assert np.median(d) < 1e-4 and (d < 1e-3).mean() >= 0.95 and d.max() < 0.1
    # without the band-aware stage the two runs are the same matches
    a2 = auto_match([ref, cur], progress=False, band_aware=False, **kw)
    b2 = tiled_auto_match([ref, cur], tiling=tiling, progress=False, band_aware=False, **kw)
    assert np.array_equal(a2.valid, b2.valid) and np.array_equal(a2.view_valid, b2.view_valid)
    ok = a2.valid
    assert np.abs(a2.pts[ok, 1] - b2.pts[ok, 1]).max() < 1e-3
    assert np.array_equal(a2.subset_px, b2.subset_px)
    # with stage 9 each tile averages its points with its own variational map, which is
    # computed on the tile and its halo (with the tile's own noise and prior scale), so the
    # positions differ slightly from one map of the whole view: far inside the σ. The band
    # prior (the default) reaches 80 px and pools along the bands, so at the run's default
    # 96 px halo (measured, 2026-12-06: median 0.0020 px, 0.12σ; at most 0.08 px; at a 48 px
    # halo 0.0037 px, 0.22σ; the isotropic prior at 48 px: 0.0009 px, 0.04σ). Since stage 9
    # weighs the map by its noise-plus-bias σ (2026-12-06 evening) the map has more weight and
    # the tiles' own maps show more: median 0.0024 px (0.09σ), at most 0.107 px
    a3 = auto_match([ref, cur], progress=False, spacing_px=8, smooth_sigma_px=0.0)
    b3 = tiled_auto_match([ref, cur], tiling=TilingParams(tile_px=128), progress=False,
                          spacing_px=8, smooth_sigma_px=0.0)
    assert (a3.valid == b3.valid).mean() >= 0.99
    ok = a3.valid & b3.valid
    d = np.abs(a3.pts[ok, 1] - b3.pts[ok, 1]).max(axis=1)
    assert np.median(d) < 0.15 * np.median(a3.sigma_px[ok]) and d.max() < 0.15
    # and stage 9 did move the points (the check above is not of two equal runs)
    assert np.median(np.abs(a3.pts[ok, 1] - a.pts[ok, 1]).max(axis=1)) > 1e-3


def test_tiled_auto_match_follows_a_drift_and_rejects_bad_grids():
    ref, cur = _pair(h=192, w=256, seed=1, drift=(23.0, -9.0))
    t = TilingParams(tile_px=128, halo_px=48)
    b = tiled_auto_match([ref, cur], tiling=t, spacing_px=8, progress=False)
    v = b.only_valid()
    assert len(v) > 0.7 * len(b.pts)
    shift = np.median(v.pts[:, 1] - v.pts[:, 0], axis=0)
    assert abs(shift[0] - 21.5) < 1.0 and abs(shift[1] + 9.2) < 0.1
    with pytest.raises(SemlabError, match="whole number"):
        tiled_auto_match([ref, cur], tiling=t, spacing_px=7.5, progress=False)
    with pytest.raises(SemlabError, match="max_points"):
        tiled_auto_match([ref, cur], tiling=t, max_points=100, progress=False)
    with pytest.raises(SemlabError, match="no parameter"):
        tiled_auto_match([ref, cur], tiling=t, spacing=8, progress=False)


def test_tiling_params_are_checked():
    assert TilingParams().tiles((3072, 4096)) and not TilingParams().tiles((1536, 2048))
    for bad in (dict(tile_px=100), dict(halo_px=-1), dict(max_parallax_px=-2.0),
                dict(min_pixels=1.5), dict(prior_max_side_px=10), dict(map_min_pixels=-1)):
        with pytest.raises(SemlabError):
            TilingParams(**bad)


def test_global_affine_on_downsampled_views():
    ref, cur = _pair(h=256, w=320, seed=2, drift=(12.0, 5.0))
    M, feats = tiled_stereo.global_affine([ref, cur], max_side_px=100)     # 4× smaller
    c = np.array([160.0, 128.0])
    shift = M[1][:, :2] @ c + M[1][:, 2] - c
    assert abs(shift[0] - 10.5) < 1.5 and abs(shift[1] - 4.8) < 1.0
    src, dst = feats[1]
    assert len(src) >= 6 and src.max() > 200            # full-resolution pixels


def _calibration(ref, cur, seeds, p):
    """A calibration measured on the central 96² window, for both runs."""
    c = dense_parallax(ref, cur, seeds=seeds, roi=(112, 80, 208, 176), params=p).calibration
    return c


def test_tiled_parallax_equals_one_call_with_its_calibration(pair):
    ref, cur = pair
    p = DenseParams(half_window=5)
    m = auto_match([ref, cur], spacing_px=16, progress=False)
    seeds = m.pts[m.valid]
    roi = (64, 48, 256, 208)
    cal = _calibration(ref, cur, seeds, p)
    whole = dense_parallax(ref, cur, seeds=seeds, roi=roi, params=p, calibration=cal)
    tiled = tiled_parallax(ref, cur, seeds=seeds, roi=roi, params=p, calibration=cal,
                           tiling=TilingParams(dense_tile_px=96, max_parallax_px=8),
                           progress=False)                                   # 2 × 2 tiles
    assert tiled.roi == whole.roi and tiled.x1_px.shape == whole.x1_px.shape
    assert (tiled.valid == whole.valid).mean() >= 0.995 and whole.valid.mean() > 0.9
    ok = tiled.valid & whole.valid
    d = np.abs(tiled.x1_px[ok] - whole.x1_px[ok])
    # only the initial guesses differ (each tile's own flow): IC-GN converges to the same
    # matches within its 1e-3 px tolerance
    assert np.percentile(d, 99) < 2e-3 and d.max() < 0.05
    ds = np.abs(tiled.sigma_px[ok] - whole.sigma_px[ok])
    assert np.percentile(ds, 99) < 1e-3 and ds.max() < 0.02
    assert tiled.calibration["sigma_factor"] == cal["sigma_factor"]


def test_tiled_parallax_calibrates_once_and_takes_a_method(pair):
    ref, cur = pair
    p = DenseParams(half_window=5)
    calls = []

    def method(v0, v1, seeds=None, roi=None, params=None, calibration=None):
        calls.append(dict(calibration))
        return dense_parallax(v0, v1, seeds=seeds, roi=roi, params=params,
                              calibration=calibration)

    t = TilingParams(dense_tile_px=64, max_parallax_px=8)
    out = tiled_parallax(ref, cur, roi=(96, 96, 224, 160), params=p, method=method, tiling=t,
                         progress=False)
    # the tile holding the centre calibrates (and is kept), then the other of the 2 × 1
    # tiles gets its σ factor and τ
    assert len(calls) == 2 and "sigma_factor" not in calls[0]
    assert calls[1]["sigma_factor"] == out.calibration["sigma_factor"]
    assert out.valid.mean() > 0.9
    par = (out.x1_px - out.grid()[0])[out.valid]
    assert -2.7 < np.median(par) < -0.3        # view 1 sees the texture at x - parallax
    # the kept calibration tile is what the tiling computes given that calibration
    calls.clear()
    again = tiled_parallax(ref, cur, roi=(96, 96, 224, 160), params=p, method=method,
                           tiling=t, progress=False, calibration=out.calibration)
    assert len(calls) == 2 and all("sigma_factor" in c for c in calls)
    both = out.valid & again.valid
    assert both.mean() > 0.9 and np.max(np.abs(again.x1_px - out.x1_px)[both]) < 1e-6
    calls.clear()                        # a one-tile region: the calibration call is the map
    one = tiled_parallax(ref, cur, roi=(96, 96, 160, 160), params=p, method=method, tiling=t,
                         progress=False)
    assert len(calls) == 1 and one.valid.shape == (64, 64)
    # the same pixels as the first tile of the larger region (its own σ factor and τ)
    assert np.nanmedian(np.abs(one.x1_px - out.x1_px[:, :64])) < 0.01
    with pytest.raises(SemlabError, match="dense_parallax's signature"):
        tiled_parallax(ref, cur, method="variational", tiling=t, progress=False)


def test_the_run_steps_take_the_tiled_path_above_the_threshold(small_experiment_master):
    from semlab import pipeline
    from semlab.experiment import load
    from semlab.heightmap import heightmap_from_stereo

    exp = load(small_experiment_master)                       # 96 × 128 views
    small = TilingParams(min_pixels=0, tile_px=64, halo_px=48, dense_tile_px=64)
    views = exp.views()
    a = tiled_stereo.run_auto_match(views, progress=False)                 # untiled
    b = tiled_stereo.run_auto_match(views, tiling=small, progress=False)   # 2 × 2 tiles
    assert np.array_equal(a.pts[:, 0], b.pts[:, 0]) and (a.valid == b.valid).mean() > 0.95
    st = pipeline.run_stereo(exp, n_boot=0, progress=False)
    whole = heightmap_from_stereo(exp, st)
    tiled = heightmap_from_stereo(exp, st, tiling=small, roi=(0, 0, 128, 96))
    assert any("64 px tiles" in n for n in tiled.notes)
    assert not any("tiles" in n for n in whole.notes)
    assert tiled.model == whole.model and tiled.z_um.shape == whole.z_um.shape
    both = tiled.valid & whole.valid
    assert both.mean() > 0.8
    # one calibration from the central 64² window instead of the whole map's: the same
    # heights within a nanometre or so
    assert np.median(np.abs(tiled.z_um[both] - whole.z_um[both])) < 0.002
    # a map larger than map_min_pixels is tiled even when the views are not
    big_map = TilingParams(map_min_pixels=64 * 64, dense_tile_px=64)
    assert not big_map.tiles(views[0].shape) and big_map.tiles_map(views[0].shape)
    assert not big_map.tiles_map(views[0].shape, roi=(0, 0, 64, 64))
    by_map = heightmap_from_stereo(exp, st, tiling=big_map)
    assert any("tiles" in n for n in by_map.notes)
    assert np.median(np.abs(by_map.z_um[both] - whole.z_um[both])) < 0.002


def test_each_dense_params_names_its_method_tile_size_and_shared_calibration():
    """tiled_parallax asks the params, not their type: the subset map tiles at
    dense_tile_px and shares view 1's B-spline level; the variational map tiles at
    variational_tile_px and shares the epipolar relation of all the seeds."""
    from semlab.variational import VariationalParams, variational_parallax

    t = TilingParams(dense_tile_px=64, variational_tile_px=192)
    dp, vp = DenseParams(), VariationalParams()
    assert dp.dense_method() is dense_parallax and vp.dense_method() is variational_parallax
    assert dp.tile_px(t) == 64 and vp.tile_px(t) == 192
    rng = np.random.default_rng(0)
    v1 = rng.normal(100, 10, (40, 50))
    x, y = rng.uniform(0, 50, 20), rng.uniform(0, 40, 20)
    d = rng.uniform(-2, 2, 20)
    seeds = np.stack([np.c_[x, y], np.c_[x + d, y + 0.5 + 0.01 * x]], 1)   # y1 − y0 = e0 + e1 x
    given = {"noise_sigma": (1.0, 1.0)}
    cd = dp.shared_calibration(None, v1, seeds, given)
    cv = vp.shared_calibration(None, v1, seeds, given)
    assert given == {"noise_sigma": (1.0, 1.0)}                          # copies
    assert "epipolar" not in cd and "coef_offset" not in cv
    spline = ndimage.spline_filter(v1, order=3, mode="mirror").mean()
    assert cd["coef_offset"] == pytest.approx(spline) and cd["noise_sigma"] == (1.0, 1.0)
    assert np.allclose(cv["epipolar"][:2], [0.5, 0.01], atol=1e-9)
    assert dp.shared_calibration(None, v1, seeds, {"coef_offset": 3.0})["coef_offset"] == 3.0
