"""Tests of semlab.subset: ZNCC search and IC-GN sub-pixel refinement."""

from pathlib import Path

import numpy as np
import pytest

from semlab.errors import ImageError, SemlabError
from semlab.noise import image_noise_sigma
from semlab.subset import (SubsetResult, icgn_refine, oriented_subset, prefilter_image,
                           zncc_match)

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SAMPLE5 = SHARED / "dic_challenge" / "sample5"


def _texture(seed=0, n_waves=80, kmax=0.7):
    """Band-limited random texture T(x, y): a sum of plane waves with |k| <= kmax rad/px."""
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.15, kmax, n_waves)
    ang = rng.uniform(0, 2 * np.pi, n_waves)
    kx, ky = k * np.cos(ang), k * np.sin(ang)
    amp = rng.uniform(0.5, 1.0, n_waves)
    ph = rng.uniform(0, 2 * np.pi, n_waves)

    def T(x, y):
        x = np.asarray(x, float)[..., None]
        y = np.asarray(y, float)[..., None]
        return 100 + 10 * np.sum(amp * np.cos(kx * x + ky * y + ph), axis=-1)
    return T



def _sinusoid_pair(shape, amp, period, noise, seed=2):
    """A texture pair whose second view is displaced by ``u(x) = amp sin(2π x / period)`` px
    along x (``x = X + u(X)`` solved by fixed point, error ~1e-5 px), each with Gaussian
    noise of ``noise`` grey. Returns ``ref, cur, u`` and the generator (for further draws)."""
    T = _texture(4, kmax=0.6)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)

    def u(x):
        return amp * np.sin(2 * np.pi * x / period)

    X = xx - u(xx - u(xx - u(xx)))
    ref = T(xx, yy) + rng.normal(0, noise, shape)
    cur = T(X, yy) + rng.normal(0, noise, shape)
    return ref, cur, u, rng


def _render(T, shape, A=np.eye(2), t=(0.0, 0.0), center=None):
    """Image of the texture after the map X -> A (X - c) + c + t (exact sampling).

    The pixel x' shows the material point X = A^-1 (x' - c - t) + c.
    """
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2]) if center is None else np.asarray(center)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    Ai = np.linalg.inv(A)
    q = np.stack([xx - c[0] - t[0], yy - c[1] - t[1]], -1) @ Ai.T + c
    return T(q[..., 0], q[..., 1])


def _grid(shape, margin, step):
    h, w = shape
    xs = np.arange(margin, w - margin, step, dtype=float)
    ys = np.arange(margin, h - margin, step, dtype=float)
    X, Y = np.meshgrid(xs, ys)
    return np.stack([X.ravel(), Y.ravel()], 1)


def _map(pts, A, t, shape):
    h, w = shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    return (pts - c) @ np.asarray(A).T + c + np.asarray(t)


SHAPE = (120, 140)


@pytest.fixture(scope="module")
def tex():
    return _texture(0)


@pytest.mark.parametrize("shift", [(0.3, -0.45), (1.7, 0.2), (-2.25, 3.6)])
def test_translation_recovered(tex, shift):
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 9)
    guess = np.rint(pts + shift)   # integer guess: up to 0.5 px off
    r = icgn_refine(ref, cur, pts, guess, half_window=10)
    assert isinstance(r, SubsetResult)
    assert r.converged.all()
    err = r.pts - (pts + shift)
    assert np.abs(err).max() < 0.01
    assert np.sqrt(np.mean(err ** 2)) < 0.003
    assert np.allclose(r.warp[:, [0, 3]], r.pts - pts)
    assert np.all(r.zncc > 0.999)
    assert np.all(r.reason == "")


def test_translation_warp_mode(tex):
    shift = (0.4, -0.7)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 15)
    r = icgn_refine(ref, cur, pts, pts, half_window=10, warp="translation")
    assert r.converged.all()
    assert np.abs(r.pts - (pts + shift)).max() < 0.01
    assert np.all(r.warp[:, [1, 2, 4, 5]] == 0)


def test_affine_warp_recovered(tex):
    A = np.array([[1.012, 0.006], [-0.005, 0.993]])
    t = (0.35, -0.6)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, A=A, t=t)
    pts = _grid(SHAPE, 28, 8) + np.array([0.3, -0.2])   # sub-pixel reference points
    truth = _map(pts, A, t, SHAPE)
    r = icgn_refine(ref, cur, pts, np.rint(truth), half_window=12)
    assert r.converged.all()
    assert np.abs(r.pts - truth).max() < 0.01
    G = A - np.eye(2)
    assert np.allclose(r.warp[:, [1, 2, 4, 5]], G.ravel(), atol=1e-3)
    # a translation-only model is measurably worse on the same affine data
    rt = icgn_refine(ref, cur, pts, np.rint(truth), half_window=12, warp="translation")
    assert np.sqrt(np.nanmean((rt.pts - truth) ** 2)) > 2 * np.sqrt(np.mean((r.pts - truth) ** 2))


def test_init_warp_helps_large_stretch(tex):
    A = np.array([[1.06, 0.0], [0.0, 1.0]])
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, A=A)
    pts = _grid(SHAPE, 30, 10)
    truth = _map(pts, A, (0, 0), SHAPE)
    r = icgn_refine(ref, cur, pts, truth + 0.3, half_window=10, init_warp=[0, 0.06, 0, 0, 0, 0])
    assert r.converged.all()
    assert np.abs(r.pts - truth).max() < 0.01


def test_gain_offset_invariance(tex):
    shift = (0.27, 0.61)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 12)
    a = icgn_refine(ref, cur, pts, pts, half_window=10)
    b = icgn_refine(ref, 0.37 * cur + 55.0, pts, pts, half_window=10)
    c = icgn_refine(3.0 * ref - 40.0, cur, pts, pts, half_window=10)
    assert a.converged.all() and b.converged.all() and c.converged.all()
    assert np.abs(a.pts - b.pts).max() < 1e-6
    assert np.abs(a.pts - c.pts).max() < 1e-6
    assert np.allclose(a.zncc, b.zncc, atol=1e-9)
    p1, z1 = zncc_match(ref, cur, pts, pts, 10, 3)
    p2, z2 = zncc_match(ref, 0.37 * cur + 55.0, pts, pts, 10, 3)
    assert np.allclose(p1, p2, atol=1e-6) and np.allclose(z1, z2, atol=1e-9)


def test_large_intensity_offset_keeps_precision(tex):
    # General warps sample the current image from float32 B-spline coefficients; they are
    # stored minus their mean, so a large intensity level costs no precision.
    A = np.array([[1.01, 0.004], [-0.003, 0.995]])
    t = (0.31, -0.42)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, A=A, t=t)
    pts = _grid(SHAPE, 28, 12)
    guess = np.rint(_map(pts, A, t, SHAPE))
    a = icgn_refine(ref, cur, pts, guess, half_window=10)
    b = icgn_refine(ref, cur + 1e6, pts, guess, half_window=10)
    assert a.converged.all() and b.converged.all()
    assert np.abs(a.pts - _map(pts, A, t, SHAPE)).max() < 0.01
    assert np.abs(a.pts - b.pts).max() < 1e-5
    assert np.abs(a.warp - b.warp).max() < 1e-6


def test_bspline_sampler_matches_map_coordinates():
    # The tap-gather sampler used for general warps equals scipy's cubic B-spline
    # (mode="mirror") minus the coefficients' mean, up to float32 rounding, everywhere
    # in the image including the border rows and columns.
    from scipy import ndimage
    from semlab.subset import _bspline_sample, _pair_table
    rng = np.random.default_rng(5)
    img = ndimage.gaussian_filter(rng.normal(100, 20, (37, 53)), 1.0)
    coef = ndimage.spline_filter(img, order=3, mode="mirror")
    H, W = img.shape
    x = np.concatenate([rng.uniform(0, W - 1, 3000), [0, W - 1, 0, W - 1, 17.0]])
    y = np.concatenate([rng.uniform(0, H - 1, 3000), [0, 0, H - 1, H - 1, 11.5]])
    want = ndimage.map_coordinates(coef, [y, x], order=3, prefilter=False, mode="mirror")
    table, wp, scale = _pair_table(np.pad(coef - coef.mean(), 2, mode="reflect"))
    assert wp == W + 4
    got = _bspline_sample(table, wp, np.stack([x, y])[None]).ravel() + coef.mean()
    assert np.abs(got - want).max() < 1e-5 * scale
    assert np.abs(got - want).max() > 0      # it is the float32 path, not a copy


def test_flat_current_subset_under_general_warp(tex):
    # With a non-identity init_warp the first iteration already samples a general warp.
    ref = _render(tex, SHAPE)
    blank = np.full(SHAPE, 80.0)
    blank[0, 0] = 81.0                     # a non-constant image, flat where matched
    pts = np.array([[70.0, 60.0]])
    r = icgn_refine(ref, blank, pts, pts, half_window=10, init_warp=[0, 0.01, 0, 0, 0, 0])
    assert not r.converged[0] and np.isnan(r.pts).all()
    assert "current image" in r.reason[0]


def test_zncc_match_integer_and_subpixel(tex):
    shift = (3.3, -2.6)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 10) + 0.25
    p, z = zncc_match(ref, cur, pts, pts, half_window=10, search_px=5)
    assert np.all(np.isfinite(p))
    assert np.abs(p - (pts + shift)).max() < 0.15
    assert np.all(z > 0.95)
    # the match then refines with IC-GN
    r = icgn_refine(ref, cur, pts, p, half_window=10)
    assert np.abs(r.pts - (pts + shift)).max() < 0.01


def test_zncc_match_flags_edges_and_outside(tex):
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=(4.0, 0.0))
    pts = np.array([[70.0, 60.0], [3.0, 60.0], [70.0, 200.0], [np.nan, 5.0]])
    p, z = zncc_match(ref, cur, pts, pts, half_window=10, search_px=3)
    # first point: true shift 4 px lies beyond the search range of 3 -> edge peak -> NaN
    assert np.all(np.isnan(p))
    assert z[1] == -1 and z[2] == -1 and z[3] == -1
    p, z = zncc_match(ref, cur, pts, pts, half_window=10, search_px=6)
    assert np.abs(p[0] - (pts[0] + [4, 0])).max() < 0.15
    assert np.all(np.isnan(p[1:])) and np.all(z[1:] == -1)


def test_icgn_flags_outside_nan_and_blank(tex):
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=(0.2, 0.1))
    pts = np.array([[70.0, 60.0], [5.0, 60.0], [70.0, 500.0], [np.nan, 1.0],
                    [128.5, 60.0]])
    guess = pts.copy()
    guess[4, 0] = 131.0      # reference subset inside, current subset leaves the image
    r = icgn_refine(ref, cur, pts, guess, half_window=10)
    assert list(r.converged) == [True, False, False, False, False]
    assert np.all(np.isnan(r.pts[1:])) and np.all(np.isnan(r.warp[1:]))
    assert np.all(r.reason[1:] != "")
    assert "leaves" in r.reason[1] and "leaves" in r.reason[4] and "NaN" in r.reason[3]
    blank = np.full(SHAPE, 80.0)
    rb = icgn_refine(ref, blank, pts[:1], pts[:1], half_window=10)
    assert not rb.converged[0] and np.isnan(rb.pts[0]).all()
    rr = icgn_refine(blank, cur, pts[:1], pts[:1], half_window=10)
    assert not rr.converged[0] and "texture" in rr.reason[0]
    pb, zb = zncc_match(blank, cur, pts[:1], pts[:1])
    assert np.isnan(pb).all() and zb[0] == -1


def test_divergence_flagged(tex):
    ref = _render(tex, SHAPE)
    rng = np.random.default_rng(3)
    cur = rng.normal(100, 10, SHAPE)      # unrelated image
    pts = _grid(SHAPE, 30, 20)
    r = icgn_refine(ref, cur, pts, pts, half_window=8, max_iter=20)
    # most subsets diverge; any that "converge" on noise have a low correlation
    assert (~r.converged).sum() >= len(pts) // 2
    assert np.all(r.zncc[r.converged] < 0.6)
    assert np.all(np.isnan(r.pts[~r.converged]))


def test_sigma_estimate_matches_scatter(tex):
    rng = np.random.default_rng(1)
    shift = (0.4, 0.25)
    ref0 = _render(tex, SHAPE)
    cur0 = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 7)
    errs, sig = [], []
    for _ in range(3):
        ref = ref0 + rng.normal(0, 2.0, SHAPE)
        cur = cur0 + rng.normal(0, 2.0, SHAPE)
        r = icgn_refine(ref, cur, pts, pts + shift, half_window=10)
        errs.append(r.pts - pts - shift)
        sig.append(r.sigma_px)
    emp = np.std(np.concatenate(errs), axis=0)
    pred = np.sqrt(np.mean(np.concatenate(sig) ** 2, axis=0))
    assert np.all(pred / emp > 0.6) and np.all(pred / emp < 1.6)


def test_smoothing_keeps_translation_exact(tex):
    shift = (0.3, -0.2)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, t=shift)
    pts = _grid(SHAPE, 25, 15)
    r = icgn_refine(ref, cur, pts, pts, half_window=10, smooth_sigma_px=0.8)
    assert np.abs(r.pts - (pts + shift)).max() < 0.01
    cc = prefilter_image(cur, smooth_sigma_px=0.8)
    r2 = icgn_refine(ref, cur, pts, pts, half_window=10, smooth_sigma_px=0.8,
                     cur_prefiltered=cc)
    assert np.allclose(r.pts, r2.pts)


def test_oriented_subset_shape_and_matching(tex):
    off = oriented_subset(12, 2, 30.0)
    a = np.deg2rad(30.0)
    along = off[:, 0] * np.cos(a) + off[:, 1] * np.sin(a)
    across = -off[:, 0] * np.sin(a) + off[:, 1] * np.cos(a)
    assert np.abs(along).max() <= 12 and np.abs(across).max() <= 2
    assert np.abs(along).max() > 10 and len(off) > 60
    assert len(np.unique(off, axis=0)) == len(off)
    A = np.array([[1.01, 0.003], [-0.004, 0.996]])
    t = (0.45, -0.3)
    ref = _render(tex, SHAPE)
    cur = _render(tex, SHAPE, A=A, t=t)
    pts = _grid(SHAPE, 30, 10) + 0.4
    truth = _map(pts, A, t, SHAPE)
    # thin subsets constrain the across-gradient terms weakly: IC-GN converges slowly
    r = icgn_refine(ref, cur, pts, np.rint(truth), half_window=12, subset_offsets=off,
                    max_iter=80, tol_px=1e-3)
    assert r.converged.all()
    assert np.abs(r.pts - truth).max() < 0.01
    # a long subset near the border leaves the image and is flagged
    rb = icgn_refine(ref, cur, [[8.0, 60.0]], [[8.0, 60.0]], subset_offsets=off)
    assert not rb.converged[0] and "leaves" in rb.reason[0]
    with pytest.raises(SemlabError):
        icgn_refine(ref, cur, pts, pts, subset_offsets=[[0, 0], [1, 0]])
    with pytest.raises(SemlabError):
        oriented_subset(0, 2, 10)


def test_bad_input_raises(tex):
    ref = _render(tex, SHAPE)
    pts = np.array([[60.0, 60.0]])
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, pts, np.zeros((2, 2)))
    with pytest.raises(SemlabError):
        zncc_match(ref, ref, pts, np.zeros((2, 2)))
    with pytest.raises(ImageError):
        icgn_refine(ref[..., None].repeat(3, 2), ref, pts, pts)
    with pytest.raises(ImageError):
        zncc_match(np.ones(10), ref, pts, pts)
    bad = ref.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ImageError):
        icgn_refine(bad, ref, pts, pts)
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, pts, pts, warp="quadratic")
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, pts, pts, half_window=1)
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, pts, pts, init_warp=np.zeros((2, 6)))
    with pytest.raises(SemlabError):
        icgn_refine(ref, ref, pts, pts, tol_px=0)
    with pytest.raises(SemlabError):
        zncc_match(ref, ref, pts, pts, search_px=0)


def test_empty_input(tex):
    ref = _render(tex, SHAPE)
    r = icgn_refine(ref, ref, np.zeros((0, 2)), np.zeros((0, 2)))
    assert r.pts.shape == (0, 2) and r.converged.shape == (0,)
    p, z = zncc_match(ref, ref, np.zeros((0, 2)), np.zeros((0, 2)))
    assert p.shape == (0, 2) and z.shape == (0,)


@pytest.mark.shared
def test_dic_challenge_sample5():
    if not SAMPLE5.is_dir():
        pytest.skip("../shared/data/dic_challenge/sample5 not available")
    tifffile = pytest.importorskip("tifffile")
    ref = tifffile.imread(SAMPLE5 / "Sample5 Reference.tif").astype(float)
    cur = tifffile.imread(SAMPLE5 / "Sample5-001 X0.10 Y0.10 N2 C100 R20.tif").astype(float)
    h = 15
    pts = _grid(ref.shape, h + 6, 10)
    p0, z0 = zncc_match(ref, cur, pts, pts, half_window=h, search_px=3)
    r = icgn_refine(ref, cur, pts, p0, half_window=h, smooth_sigma_px=0.8)
    assert r.converged.all()
    u = r.pts - pts
    # sign convention: the content of image 001 sits at +0.1 px in x and y
    assert np.all(np.abs(u.mean(0) - 0.1) < 0.002)
    rms = np.sqrt(np.mean((u - 0.1) ** 2))
    assert rms <= 0.005
    # the predicted error holds on a sharp speckle: the default lowers the image noise
    # estimate to what the residuals allow; Immerkaer's alone (given) sees the speckle as noise
    assert 0.75 < rms / np.sqrt(np.mean(r.sigma_px ** 2)) < 1.25
    ri = icgn_refine(ref, cur, pts, p0, half_window=h, smooth_sigma_px=0.8,
                     noise_sigma=(image_noise_sigma(ref), image_noise_sigma(cur)))
    assert np.sqrt(np.mean(ri.sigma_px ** 2)) > 2 * rms


# ------------------------------------------------------- predicted error from the covariance
@pytest.mark.parametrize("noise,h,smooth", [(3.0, 10, 0.8), (6.0, 8, 0.8), (1.5, 8, 0.0),
                                              (6.0, 12, 0.0), (9.0, 14, 0.0)])
def test_predicted_sigma_matches_empirical_error(noise, h, smooth):
    """sigma_px (Gauss-Newton covariance, noise measured from the images) is within 20 %
    of the RMS error over many noise draws of a known sub-pixel shift, and the error bars
    cover like a Gaussian's."""
    T = _texture(0, kmax=0.5)
    shape, shift = (120, 150), (0.3, -0.2)
    ref0, cur0 = _render(T, shape), _render(T, shape, t=shift)
    pts = _grid(shape, 20, 7)
    rng = np.random.default_rng(7)
    err, sig = [], []
    for _ in range(8):
        ref = ref0 + rng.normal(0, noise, shape)
        cur = cur0 + rng.normal(0, noise, shape)
        # low SNR: the noisy reference gradients slow IC-GN's convergence down
        r = icgn_refine(ref, cur, pts, np.rint(pts + shift), half_window=h,
                        smooth_sigma_px=smooth, max_iter=100)
        assert r.converged.mean() > 0.95
        assert np.allclose(r.noise_sigma, noise, rtol=0.05)      # measured, not assumed
        ok = r.converged
        err.append(r.pts[ok] - (pts[ok] + shift))
        sig.append(r.sigma_px[ok])
    err, sig = np.concatenate(err), np.concatenate(sig)
    assert np.all(np.isfinite(sig))
    ratio = np.sqrt(np.mean(err ** 2, 0)) / np.sqrt(np.mean(sig ** 2, 0))
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    z = np.abs(err / sig)
    assert 0.6 < np.mean(z < 1) < 0.75 and np.mean(z < 2) > 0.93


@pytest.mark.parametrize("smooth", [0.0, 0.8])
def test_noise_measured_on_texture_sharp_at_the_pixel_scale(smooth):
    """White-noise texture (σ 20 grey levels, sharp at the pixel scale) shifted by whole
    pixels (so that the views differ by the shift and the noise only), plus a known noise
    of 2: Immerkær's mask reads the texture as noise (about 20); the default measurement
    (residual of the matched subsets, corrected for the smoothing and interpolation gains)
    finds the added noise within 15 % (at whole-pixel positions the interpolation keeps
    the noise, 1/0.764 more than its mean gain assumes: about +6 % in σ unsmoothed)."""
    rng = np.random.default_rng(3)
    shape, noise = (140, 160), 2.0
    T = rng.normal(0, 20.0, (shape[0] + 4, shape[1] + 4))
    ref = T[:shape[0], :shape[1]] + rng.normal(0, noise, shape)
    cur = T[2:2 + shape[0], 1:1 + shape[1]] + rng.normal(0, noise, shape)   # (x, y) -(1, 2)
    pts = _grid(shape, 14, 8)
    r = icgn_refine(ref, cur, pts, pts - [1.2, 1.8], half_window=8, smooth_sigma_px=smooth)
    ok = r.converged
    assert ok.mean() > 0.9
    assert np.allclose(r.pts[ok] - pts[ok], [-1, -2], atol=0.05)
    assert image_noise_sigma(ref) > 5 * noise           # the old default, fooled
    assert np.allclose(r.noise_sigma, noise, rtol=0.15), r.noise_sigma


def test_predicted_sigma_grows_with_noise_and_residual_mode():
    T = _texture(1, kmax=0.5)
    shape = (90, 100)
    ref0, cur0 = _render(T, shape), _render(T, shape, t=(0.4, 0.1))
    pts = _grid(shape, 20, 10)
    rng = np.random.default_rng(0)
    ref, cur = ref0 + rng.normal(0, 2, shape), cur0 + rng.normal(0, 2, shape)
    a = icgn_refine(ref, cur, pts, pts, half_window=10)
    b = icgn_refine(ref, cur, pts, pts, half_window=10, noise_sigma=4.0)
    c = icgn_refine(ref, cur, pts, pts, half_window=10, noise_sigma="residual")
    assert np.all(b.sigma_px > 1.9 * a.sigma_px)      # twice the noise, twice the error
    assert np.allclose(np.median(c.sigma_px / a.sigma_px), 1, atol=0.25)
    assert np.all(np.isnan(c.residual_ratio)) and np.all(np.isnan(c.noise_sigma))
    assert 0.6 < np.median(a.residual_ratio) < 1.3
    with pytest.raises(SemlabError, match="noise_sigma"):
        icgn_refine(ref, cur, pts, pts, noise_sigma="guess")
    with pytest.raises(SemlabError, match="noise_sigma"):
        icgn_refine(ref, cur, pts, pts, noise_sigma=-1.0)


def test_sigma_infinite_where_texture_is_below_noise():
    rng = np.random.default_rng(3)
    T = _texture(2, kmax=0.5)
    shape = (80, 80)
    ref = 100 + 0.02 * (_render(T, shape) - 100) + rng.normal(0, 3, shape)
    cur = ref + rng.normal(0, 3, shape)
    r = icgn_refine(ref, cur, [[40.0, 40.0]], [[40.0, 40.0]], half_window=6)
    assert r.converged.all() is False or np.all(~np.isfinite(r.sigma_px) | (r.sigma_px > 0.3))
