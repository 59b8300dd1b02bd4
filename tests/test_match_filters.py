"""Ablation tests of auto_match's filter stages: each stage, switched off alone through its
parameter, lets through matches that are wrong by more than the test's tolerance, on a small
scene where that stage matters. (The roughness stage's test is in test_matching.py. The
local-consistency stage has no such small scene yet: on 7 synthetic scenes switching it off
changed the gross errors by -1..+4 points; its evidence is the real-texture quick cell of
benchmarks/accuracy_matrix.py, see ``consistency_px``.)

Scenes are the synthetic stereo pairs of test_matching.py, altered where the stage matters.
The filters judge the subset matches, so they are tested on those (``variational_fusion=False``):
stage 9, which averages the accepted matches with the variational map afterwards, pulls some
wrong matches back too (the spotted pair's forward–backward test: 13 against 5 gross errors
with it, so the stage still more than halves them).
"""

import numpy as np
from scipy import ndimage

from semlab.match_filters import _multiview_residual
from semlab.matching import auto_match

from test_matching import TILTS, Scene


def _view_errors(sc, m, tilts, view):
    """|match - truth| (px) in ``view`` of the accepted points of m."""
    v = m.only_valid()
    x, y = sc.material(v.pts[:, 0, 0], v.pts[:, 0, 1], tilts[0])
    return v, np.hypot(*(v.pts[:, view] - sc.project(x, y, tilts[view])).T)


def _spotted_pair():
    """The scene and its two views, 25 spots of view 1 moved 1.5 px across the parallax."""
    sc = Scene(seed=5)
    ims = [sc.render(TILTS[0], noise=0.05, seed=1), sc.render(TILTS[1], noise=0.05, seed=2)]
    moved = ndimage.shift(ims[1], (1.5, 0.0), order=3, mode="nearest")
    rng = np.random.default_rng(3)
    for _ in range(25):
        cx, cy = rng.integers(30, 230), rng.integers(30, 170)
        ims[1][cy - 8:cy + 9, cx - 8:cx + 9] = moved[cy - 8:cy + 9, cx - 8:cx + 9]
    return sc, ims


def test_forward_backward_stage_removes_mismatched_spots():
    """25 spots of 17×17 px in the second view moved by 1.5 px across the parallax
    direction (local charging or debris): subsets partly over a spot converge to a mix
    that the backward match does not reproduce. Without the forward–backward stage at
    least twice as many accepted matches are off by more than 0.5 px."""
    sc, ims = _spotted_pair()
    gross = {}
    for name, kw in (("on", {}), ("off", dict(backward_px=None))):
        m = auto_match(ims, progress=False, variational_fusion=False, **kw)
        _, e = _view_errors(sc, m, TILTS, 1)
        gross[name] = int((e > 0.5).sum())
    assert gross["off"] >= 2 * gross["on"] + 10, gross


def _three_views_one_wrong(shift_px=2.5):
    sc = Scene(seed=2)
    tilts = (-5.0, 0.0, 5.0)
    ims = [sc.render(t, seed=k, noise=0.05) for k, t in enumerate(tilts)]
    # a 72×72 px region of the third view moved by shift_px in x (charging in that view
    # only): its matches agree with their neighbours and with the first two views' pair,
    # but their three x coordinates fit no single height
    moved = ndimage.shift(ims[2], (0.0, shift_px), order=3, mode="nearest")
    ims[2][60:132, 90:162] = moved[60:132, 90:162]
    return sc, tilts, ims


def test_multiview_stage_removes_points_wrong_in_one_view():
    sc, tilts, ims = _three_views_one_wrong()
    n_wrong = {}
    for name, kw in (("on", {}), ("off", dict(multiview_px=None))):
        m = auto_match(ims, progress=False, variational_fusion=False, **kw)
        v, e = _view_errors(sc, m, tilts, 2)
        n_wrong[name] = int((e > 1.0).sum())
        # the first view pair is right everywhere: only the multi-view test can tell
        _, e1 = _view_errors(sc, v, tilts, 1)
        assert np.all(e1 < 0.3)
    assert n_wrong["on"] == 0 and n_wrong["off"] >= 15, n_wrong


def test_multiview_residual_is_robust_to_a_group_wrong_in_one_view():
    """The rank-2 residual from a least-squares fit hides a group of points wrong in one
    view (the fitted height direction turns towards them); the robust start keeps their
    residual near the value of a 2.5 px error in one of three views, 2.5 / √18 px."""
    sc, tilts, _ = _three_views_one_wrong()
    gy, gx = np.mgrid[20:180:8, 20:240:8]
    x, y = sc.material(gx.ravel().astype(float), gy.ravel().astype(float), tilts[0])
    pts = np.stack([sc.project(x, y, t) for t in tilts], axis=1)
    wrong = (pts[:, 2, 0] >= 90) & (pts[:, 2, 0] < 162) & (pts[:, 2, 1] >= 60) \
        & (pts[:, 2, 1] < 132)
    pts[wrong, 2, 0] += 2.5
    res, _ = _multiview_residual(pts, 0, np.ones(len(pts), bool))
    assert wrong.sum() > 20
    assert np.all(np.abs(res[wrong] - 2.5 / np.sqrt(18)) < 0.05)
    assert np.all(res[~wrong] < 0.05)


def test_forward_backward_against_error_bars_keeps_rejecting_mismatched_spots():
    """``backward_sigma_p``: the forward–backward distance judged against each point's own
    σ (χ², 2 dof) instead of the fixed ``backward_px`` alone. On the spotted scene of
    :func:`test_forward_backward_stage_removes_mismatched_spots` it accepts at least the
    points the fixed test accepts and still removes at least 3/4 of the gross mismatches
    (> 0.5 px) that the fixed test removes (measured: fixed 271 points / 20 gross,
    σ-judged 279 / 25, stage off 393 / 56: the few it adds are mostly mismatched spots,
    whose forward and backward matches agree on the same wrong mix)."""
    sc, ims = _spotted_pair()
    n, gross = {}, {}
    for name, kw in (("fixed", {}), ("sigma", dict(backward_sigma_p=0.99)),
                     ("off", dict(backward_px=None))):
        m = auto_match(ims, progress=False, variational_fusion=False, **kw)
        _, e = _view_errors(sc, m, TILTS, 1)
        n[name], gross[name] = len(e), int((e > 0.5).sum())
    assert n["sigma"] >= n["fixed"], n
    assert gross["off"] - gross["sigma"] >= 0.75 * (gross["off"] - gross["fixed"]), gross
