"""Matching along the epipolar direction only (semlab.match_epipolar) and its auto_match stage."""

import numpy as np
import pytest
from conftest import shared_path
from scipy import ndimage

from semlab.errors import SemlabError
from semlab.match_epipolar import epipolar_refine
from semlab.subset import icgn_refine

H, W = 96, 160
PROFILE = ndimage.gaussian_filter1d(np.random.default_rng(0).normal(size=4 * W), 6) * 40


def grooves(shift_px, noise, seed, scale=1.0):
    """Grooves along y: the texture varies along x only (a machined substrate)."""
    x = (np.arange(W) - shift_px) / scale
    row = np.interp(4 * x, np.arange(4 * W), PROFILE)
    im = np.tile(row, (H, 1)) + 128
    return im + np.random.default_rng(seed).normal(0, noise, im.shape)


def grid():
    gy, gx = np.mgrid[20:H - 20:8, 24:W - 40:8]
    return np.column_stack([gx.ravel(), gy.ravel()]).astype(float)


def test_grooves_matched_along_x_where_2d_icgn_fails():
    p = grid()
    a, b = grooves(0.0, 1.0, 1), grooves(1.3, 1.0, 2)
    guess = p + [1.0, 2.5]                     # y off by 2.5 px: the grooves cannot tell
    two_d = icgn_refine(a, b, p, guess, 10)
    assert two_d.converged.mean() < 0.2        # no texture along y: 2D IC-GN wanders
    r = epipolar_refine(a, b, p, guess, (1.0, 0.0), 10)
    assert r.converged.all() and np.all(r.zncc > 0.9)
    assert np.array_equal(r.pts[:, 1], guess[:, 1])    # held on the epipolar line
    err = r.pts[:, 0] - p[:, 0] - 1.3
    assert np.abs(err).max() < 4 * np.median(r.sigma_px[:, 0])


def test_search_finds_a_far_shift_and_the_gradient():
    p = grid()
    a, b = grooves(0.0, 0.5, 3), grooves(7.4, 0.5, 4, scale=1.01)
    guess = p + [0.0, 0.0]                     # 7-8 px off along x
    r = epipolar_refine(a, b, p, guess, (1.0, 0.0), 10, search_px=10, shape="gradient")
    ok = r.converged
    assert ok.mean() > 0.95
    true_x = p[:, 0] * 1.01 + 7.4
    assert np.abs(r.pts[ok, 0] - true_x[ok]).max() < 0.05
    du_dx = r.warp[ok, 1]                                   # the 1 % x-scale
    assert abs(np.median(du_dx) - 0.01) < 1e-3 and np.abs(du_dx - 0.01).max() < 0.01


def test_predicted_sigma_matches_the_scatter_over_noise_draws():
    """The predicted σ of the shift is within 20 % of the empirical one (12 noise draws)."""
    p = grid()
    errs, sig = [], []
    for k in range(12):
        r = epipolar_refine(grooves(0.0, 2.0, 10 + k), grooves(0.6, 2.0, 100 + k), p, p,
                            (1.0, 0.0), 10, shape="translation")
        errs.append(r.pts[:, 0] - p[:, 0] - 0.6)
        sig.append(r.sigma_px[:, 0])
    emp = np.std(np.array(errs), axis=0, ddof=1)            # per point, over the draws
    ratio = np.median(np.array(sig), axis=0) / emp
    assert 0.8 < np.median(ratio) < 1.2


def test_bad_input_is_refused():
    p = grid()[:3]
    a = grooves(0, 1, 1)
    with pytest.raises(SemlabError, match="direction"):
        epipolar_refine(a, a, p, p, (0.0, 0.0))
    with pytest.raises(SemlabError, match="shape"):
        epipolar_refine(a, a, p, p, (1.0, 0.0), shape="affine")
    with pytest.raises(SemlabError, match="direction"):
        epipolar_refine(a, a, p, p, np.ones((2, 2)))


def test_auto_match_finds_the_grooved_pollen_substrate():
    """pollen_pot1 (real): a 256×160 crop of the grooved substrate, views 0 and 1. The 2D
    subsets diverge along the grooves (28 of 448 grid points accepted without the epipolar
    stage, 131 with it; most of the rest fail the roughness test on the grooves' relief)."""
    from semlab.io import read_image
    from semlab.matching import auto_match

    d = shared_path("real_sem", "pollen_pot1")
    ims = [read_image(d / f"pot1_0{i}.jpg").data[:160, :256] for i in (0, 1)]
    m = auto_match(ims, progress=False)
    old = auto_match(ims, progress=False, epipolar=False)
    assert m.valid.sum() > 100 and m.valid.sum() > 2.5 * old.valid.sum()
    v = m.only_valid()
    assert np.all(np.isfinite(v.sigma_px)) and np.median(v.sigma_px) < 0.2
    # the grooves are along y: across the rows the parallax of one column hardly changes
    par = v.pts[:, 1, 0] - v.pts[:, 0, 0]
    col = np.rint(v.pts[:, 0, 0]).astype(int)
    dev = [par[col == c] - np.median(par[col == c]) for c in np.unique(col)
           if (col == c).sum() >= 4]
    assert np.median(np.abs(np.concatenate(dev))) < 0.3
