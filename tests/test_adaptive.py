"""Tests of semlab.adaptive: subsets sized by the information they hold."""

import numpy as np
import pytest

from semlab.adaptive import TARGET_MISSED, adaptive_icgn
from semlab.errors import SemlabError
from semlab.subset import icgn_refine

from test_subset import _grid, _render, _sinusoid_pair, _texture


def _scene(contrast_left=0.12, shift=(0.35, -0.25), shape=(140, 220), noise=2.0, seed=0):
    """Texture whose contrast falls from 1 on the right to contrast_left on the left."""
    T = _texture(0, kmax=0.5)
    x = np.arange(shape[1])[None, :]
    c = contrast_left + (1 - contrast_left) * np.clip((x - 60) / 100, 0, 1)
    rng = np.random.default_rng(seed)
    ref = 100 + c * (_render(T, shape) - 100) + rng.normal(0, noise, shape)
    cur = 100 + c * (_render(T, shape, t=shift) - 100) + rng.normal(0, noise, shape)
    return ref, cur, shift


def test_subsets_grow_where_texture_is_poor():
    ref, cur, shift = _scene()
    pts = _grid(ref.shape, 32, 9)
    a = adaptive_icgn(ref, cur, pts, np.rint(pts + shift), target_sigma_px=0.03,
                      half_windows=(5, 8, 12, 18, 28), smooth_sigma_px=0.8)
    poor, rich = pts[:, 0] < 55, pts[:, 0] > 165
    conv = a.subset.converged
    assert conv.mean() > 0.95
    # poor texture -> larger subsets; rich texture -> small ones
    assert np.median(a.half_window[poor & conv]) >= 2 * np.median(a.half_window[rich & conv])
    assert np.median(a.half_window[rich & conv]) <= 8
    # where the target is met the predicted and the actual errors meet it too
    err = a.subset.pts - (pts + shift)
    m = a.target_met
    assert m.mean() > 0.7
    assert np.all(a.subset.sigma_px[m].max(1) <= 0.03)
    assert np.sqrt(np.mean(err[m] ** 2)) < 0.03 * 1.3
    # missed targets are reported, never silent
    miss = conv & ~m
    assert all(r.startswith(TARGET_MISSED) for r in a.subset.reason[miss])
    assert all(r == "" for r in a.subset.reason[m])
    assert np.allclose(a.subset_size_um(0.03)[conv], (2 * a.half_window[conv] + 1) * 0.03)
    # a fixed small subset has a much larger error on the poor side
    f = icgn_refine(ref, cur, pts[poor], np.rint(pts[poor] + shift), half_window=5,
                    smooth_sigma_px=0.8)
    ef = f.pts - (pts[poor] + shift)
    ea = err[poor]
    assert np.sqrt(np.nanmean(ef ** 2)) > 2 * np.sqrt(np.nanmean(ea ** 2))


def test_translation_with_held_gradient_where_texture_is_poor():
    """Known x-scaling held fixed: translation reaches a target affine cannot."""
    T = _texture(3, kmax=0.5)
    shape = (120, 160)
    A = np.diag([1.03, 1.0])
    rng = np.random.default_rng(1)
    ref = 100 + 0.25 * (_render(T, shape) - 100) + rng.normal(0, 2, shape)
    cur = 100 + 0.25 * (_render(T, shape, A=A) - 100) + rng.normal(0, 2, shape)
    pts = _grid(shape, 35, 12)
    c = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    truth = (pts - c) @ A.T + c
    iw = [0, 0.03, 0, 0, 0, 0]
    a = adaptive_icgn(ref, cur, pts, np.rint(truth), target_sigma_px=0.05,
                      half_windows=(6, 9, 13), init_warp=iw, smooth_sigma_px=0.8)
    assert (a.shape_function == "translation").sum() > (a.shape_function == "affine").sum()
    ok = a.subset.converged
    assert np.sqrt(np.mean((a.subset.pts[ok] - truth[ok]) ** 2)) < 0.06
    # a wrong held gradient does not fit: translation is refused, the subset grows or
    # falls back to affine
    b = adaptive_icgn(ref, cur, pts, np.rint(truth), target_sigma_px=0.05,
                      half_windows=(6, 9, 13), init_warp=[0, -0.05, 0, 0, 0, 0],
                      smooth_sigma_px=0.8)
    assert (b.shape_function == "translation").sum() < (a.shape_function == "translation").sum()


def test_affine_where_a_real_shear_is_not_in_the_held_gradient():
    """A shear du/dy the held gradient lacks: the translation is biased (0.12 px at h = 9)
    and the position difference to the affine fit of the same subset shows it (Hausman-
    type MSE test), so the affine fit is chosen. The former test (translation residual
    within the chi-square scatter of one residual variance of the affine's) kept the
    translation at 24 % of the points and 2.1× the affine-only RMS error."""
    T = _texture(3, kmax=0.5)
    shape = (120, 160)
    pts = _grid(shape, 35, 12)
    c = np.array([(shape[1] - 1) / 2, (shape[0] - 1) / 2])
    n_aff, se_auto, se_aff = 0, 0.0, 0.0
    for shear in (0.02, 0.04):
        A = np.array([[1.03, shear], [0.0, 1.0]])
        rng = np.random.default_rng(1)
        ref = _render(T, shape) + rng.normal(0, 2, shape)
        cur = _render(T, shape, A=A) + rng.normal(0, 2, shape)
        truth = (pts - c) @ A.T + c
        kw = dict(target_sigma_px=0.05, half_windows=(6, 9, 13), init_warp=[0, 0.03, 0, 0, 0, 0],
                  smooth_sigma_px=0.8)
        a = adaptive_icgn(ref, cur, pts, np.rint(truth), **kw)
        f = adaptive_icgn(ref, cur, pts, np.rint(truth), warp="affine", **kw)
        assert a.subset.converged.all() and f.subset.converged.all()
        n_aff += (a.shape_function == "affine").sum()
        se_auto += np.sum((a.subset.pts - truth) ** 2)
        se_aff += np.sum((f.subset.pts - truth) ** 2)
    assert n_aff >= 0.85 * 2 * len(pts)
    assert np.sqrt(se_auto / se_aff) < 1.8


def test_adaptive_errors():
    ref, cur, _ = _scene(shape=(60, 60))
    with pytest.raises(SemlabError, match="target_sigma_px"):
        adaptive_icgn(ref, cur, [[30.0, 30.0]], [[30.0, 30.0]], target_sigma_px=0)
    with pytest.raises(SemlabError, match="half_windows"):
        adaptive_icgn(ref, cur, [[30.0, 30.0]], [[30.0, 30.0]], half_windows=(8, 5))
    with pytest.raises(SemlabError, match="warp"):
        adaptive_icgn(ref, cur, [[30.0, 30.0]], [[30.0, 30.0]], warp="quadratic")
    a = adaptive_icgn(ref, cur, [[2.0, 2.0]], [[2.0, 2.0]])
    assert not a.subset.converged[0] and a.half_window[0] == 0 and a.subset.reason[0]
    # sized by the total error: a point no size can match says why (IC-GN's reason), not
    # "no subset tried" (the refined clicks of a featureless scene said so 46 times)
    flat = np.full((60, 60), 100.0) + np.random.default_rng(0).normal(0, 1e-3, (60, 60))
    a = adaptive_icgn(flat, flat, [[30.0, 30.0]], [[30.0, 30.0]], half_windows=(5, 7),
                      curvature_neighbours=1)
    assert not a.subset.converged[0]
    assert a.subset.reason[0].startswith("no subset converged (half sizes 5–7 px; at 7: ")
    assert "tried" not in a.subset.reason[0] and len(a.subset.reason[0]) > 50


def test_curvature_aware_sizing_on_a_sinusoidal_displacement():
    """u(x) = 0.2 sin(2π x / 80) px: an affine subset is biased by ∇²u h (h + 1) / 6 at the
    crests, so sizing by the noise alone (the target is out of reach: every point grows to
    the largest subset) is worse than sizing by noise and curvature, which keeps subsets
    smaller at the crests than at the zero crossings, where the displacement is straight.
    (Fixed subsets: RMS 0.034 / 0.021 / 0.027 / 0.049 px at h = 6 / 9 / 13 / 19.)"""
    shape, period = (110, 240), 80.0
    ref, cur, u, _ = _sinusoid_pair(shape, 0.2, period, 3)
    pts = _grid(shape, 30, 6)
    kw = dict(target_sigma_px=0.002, half_windows=(6, 9, 13, 19), warp="affine",
              smooth_sigma_px=0.8, noise_sigma="calibrated")
    noise_only = adaptive_icgn(ref, cur, pts, pts, **kw)
    curved = adaptive_icgn(ref, cur, pts, pts, curvature_neighbours=9, **kw)
    rms = {}
    for name, a in (("noise", noise_only), ("curvature", curved)):
        ok = a.subset.converged
        assert ok.mean() > 0.95
        e = a.subset.pts[ok, 0] - pts[ok, 0] - u(pts[ok, 0])
        rms[name] = np.sqrt(np.mean(e ** 2))
    assert rms["curvature"] < 0.75 * rms["noise"], rms
    phase = np.abs(np.sin(2 * np.pi * pts[:, 0] / period))
    crest, zero = phase > 0.9, phase < 0.3
    assert np.median(curved.half_window[crest]) < np.median(curved.half_window[zero])
    assert np.median(curved.half_window[crest]) < np.median(noise_only.half_window[crest])
    assert curved.bias_px.shape == (len(pts),) and noise_only.bias_px is None
    assert np.median(curved.bias_px[crest]) > 3 * np.median(curved.bias_px[zero])
    assert not curved.target_met.any()
    assert all(r.startswith(TARGET_MISSED) for r in curved.subset.reason[curved.subset.converged])
    with pytest.raises(SemlabError, match="curvature_neighbours"):
        adaptive_icgn(ref, cur, pts[:3], pts[:3], curvature_neighbours=0)
    # target 0: no target, each point at its smallest predicted total error; the target
    # above was out of reach, so the same choice, now reported as met (a size that fits)
    best = adaptive_icgn(ref, cur, pts, pts, curvature_neighbours=9,
                         **{**kw, "target_sigma_px": 0.0})
    assert np.array_equal(best.half_window, curved.half_window)
    assert np.allclose(best.subset.pts, curved.subset.pts, equal_nan=True)
    assert best.target_met[best.subset.converged].mean() > 0.95
    assert all(r == "" for r in best.subset.reason[best.target_met])


def test_nested_bias_from_independent_increments():
    """Nested subsets' matches as cumulative means of independent pixel contributions plus
    a bias β c_h: the increment estimate of β is unbiased with the variance it reports,
    which is several times smaller than the ends-of-the-ladder variance the sizing uses."""
    from semlab.adaptive import _nested_bias

    rng = np.random.default_rng(0)
    hs = np.array([7, 10, 14, 20, 28])
    c = hs * (hs + 1) / 6.0
    npx = (2 * hs + 1) ** 2
    beta, sig1, m = 4e-4, 1.0, 4000
    # pixel contributions of the nested rings: cumulative means
    ring = np.diff(np.concatenate([[0], npx]))
    sums = np.cumsum(np.stack([rng.normal(0, sig1 * np.sqrt(k), m) for k in ring]), axis=0)
    U = sums / npx[:, None] + beta * c[:, None]                 # (H, M)
    S = np.broadcast_to((sig1 / np.sqrt(npx))[:, None], U.shape)
    U, S = np.stack([U, U], -1), np.stack([S, S], -1)            # (H, M, 2)
    b, v = _nested_bias(U, S, np.ones(U.shape, bool), c)
    assert abs(np.mean(b[:, 0]) - beta) < 3 * np.sqrt(v[0, 0] / m)
    assert np.var(b[:, 0]) == pytest.approx(v[0, 0], rel=0.1)
    ends = (S[0, 0, 0] ** 2 - S[-1, 0, 0] ** 2) / (c[-1] - c[0]) ** 2
    assert v[0, 0] < ends / 3
    # an unconverged middle size is skipped (its neighbours' increment joins them)
    fin = np.ones(U.shape, bool)
    fin[2] = False
    b2, v2 = _nested_bias(np.where(fin, U, np.nan), S, fin, c)
    assert np.all(np.isfinite(b2)) and np.all(v2 >= v[0, 0])
    assert np.all(np.isnan(_nested_bias(U[:1], S[:1], fin[:1], c[:1])[0]))


def test_error_bar_holds_the_curvature_bias_the_ladder_leaves_unknown():
    """u(x) = 0.3 sin(2π x / 160) px, noise 6 grey: most points grow past h = 14, where the
    curvature bias is ~1-3 noise σ but below what the ladder resolves point by point, so
    the de-biased estimate (``bias_px``) is mostly 0 and its error bars cover too little
    (52 % / 86 % within 1σ / 2σ when written); the expected squared bias
    (``bias_rms_px``) covers as a 1σ should (73 % / 97 %), the same matches."""
    shape = (120, 400)
    ref, cur, u, _ = _sinusoid_pair(shape, 0.3, 160.0, 6)
    pts = _grid(shape, 30, 5)
    a = adaptive_icgn(ref, cur, pts, pts, 0.02, half_windows=(7, 10, 14, 20, 28),
                      warp="affine", smooth_sigma_px=0.8, noise_sigma="calibrated",
                      curvature_neighbours=1)
    ok = a.subset.converged
    assert ok.mean() > 0.95 and np.median(a.half_window[ok]) >= 14
    e = np.abs(a.subset.pts[ok, 0] - pts[ok, 0] - u(pts[ok, 0]))
    s = a.subset.sigma_px[ok, 0]
    old, new = np.hypot(s, a.bias_px[ok]), np.hypot(s, a.bias_rms_px[ok])
    assert np.mean(e < 2 * old) < 0.9
    assert np.mean(e < 2 * new) > 0.93
    assert 0.6 < np.mean(e < new) < 0.85          # not loosened past a 1σ
    noise_only = adaptive_icgn(ref, cur, pts[:5], pts[:5], 0.02, half_windows=(7, 10),
                               warp="affine")
    assert noise_only.bias_rms_px is None and noise_only.bias_px is None


def test_grid_icgn_bias_keyword_selects_the_bias_returned():
    """``bias``: none (two items), the signed de-biased estimate or the expected squared
    bias of :func:`adaptive_icgn`; zeros for fixed subsets; anything else refused."""
    from semlab.adaptive import _grid_icgn
    from semlab.subset import prefilter_image

    shape = (120, 400)
    ref, cur, _, _ = _sinusoid_pair(shape, 0.3, 160.0, 6)
    pts = _grid(shape, 30, 10)
    rc, cc = prefilter_image(ref, 0.8), prefilter_image(cur, 0.8)
    args = (ref, cur, pts, pts, 7, "affine", np.zeros(6), 0.8, rc, cc, 0.02, 28)
    kw = dict(noise_sigma="calibrated", curvature_neighbours=1)
    a = adaptive_icgn(ref, cur, pts, pts, 0.02, half_windows=(7, 10, 14, 20, 28),
                      warp="affine", smooth_sigma_px=0.8, ref_prefiltered=rc,
                      cur_prefiltered=cc, init_warp=np.zeros(6), **kw)
    assert len(_grid_icgn(*args, **kw)) == 2
    signed, rms = (_grid_icgn(*args, bias=b, **kw)[2] for b in ("signed", "rms"))
    assert np.array_equal(signed, np.nan_to_num(a.bias_px))
    assert np.array_equal(rms, np.nan_to_num(a.bias_rms_px)) and not np.array_equal(rms, signed)
    fixed = _grid_icgn(*args[:10], None, 28, bias="rms")
    assert len(fixed) == 3 and not fixed[2].any()
    with pytest.raises(SemlabError, match="bias"):
        _grid_icgn(*args, bias=True)
