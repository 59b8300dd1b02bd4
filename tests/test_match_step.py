"""Tests of semlab.match_step: shiftable windows beside a step of the parallax."""

import numpy as np
from scipy import ndimage

from semlab.match_step import shiftable_refine, shifted_offsets, step_candidates
from semlab.subset import icgn_refine

H, W, X_STEP, STEP_PX, HALF = 96, 128, 64.0, 1.5, 10


def _step_pair(step_px=STEP_PX, seed=0):
    """Speckle view 0 and a view 1 whose x parallax jumps by ``step_px`` at x = X_STEP."""
    rng = np.random.default_rng(seed)
    ref = ndimage.gaussian_filter(rng.normal(size=(H, W)), 1.5) * 40 + 100
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    cur = ndimage.map_coordinates(ref, [yy, xx - np.where(xx >= X_STEP, step_px, 0.0)],
                                  order=3, mode="mirror")
    return ref + rng.normal(0, 1, ref.shape), cur + rng.normal(0, 1, ref.shape)


def _points_beside_step():
    """Points 3-8 px either side of the step (the centred subset straddles it)."""
    xs = np.concatenate([X_STEP - np.arange(3, 9), X_STEP - 1 + np.arange(3, 9)])
    return np.array([(x, y) for y in range(24, H - 24, 8) for x in xs], float)


def test_shifted_offsets_are_a_displaced_square_holding_the_point():
    off = shifted_offsets(4, 4, 0.0)
    assert off.shape == (81, 2)
    assert off[:, 0].min() == 0 and off[:, 0].max() == 8      # shifted by +4 in x
    assert np.ptp(off[:, 1]) == 8 and off[:, 1].min() == -4
    assert np.any(np.all(off == 0, axis=1))                   # the point is inside
    up = shifted_offsets(4, 2, 270.0)                         # 270°: toward -y
    assert up[:, 1].min() == -6 and up[:, 1].max() == 2


def test_displaced_windows_take_the_parallax_of_the_points_side_of_a_step():
    ref, cur = _step_pair()
    p = _points_beside_step()
    true_x = p[:, 0] + np.where(p[:, 0] >= X_STEP, STEP_PX, 0.0)
    r = icgn_refine(ref, cur, p, p + [STEP_PX / 2, 0], half_window=HALF)
    r2, shifted = shiftable_refine(ref, cur, p, r, HALF)
    before = np.sqrt(np.nanmean((r.pts[:, 0] - true_x) ** 2))
    after = np.sqrt(np.nanmean((r2.pts[:, 0] - true_x) ** 2))
    assert step_candidates(r).mean() > 0.8          # the residual sees the straddling
    assert shifted.mean() > 0.8
    assert before > 0.3 and after < 0.5 * before, (before, after)
    # a displaced window's σ carries the extrapolation of its affine terms to the point
    assert np.nanmedian(r2.sigma_px[shifted, 0] / r.sigma_px[shifted, 0]) > 1.0


def test_no_step_no_displaced_window():
    ref, cur = _step_pair(step_px=0.0)
    p = _points_beside_step()
    r = icgn_refine(ref, cur, p, p + [0.3, 0], half_window=HALF)
    r2, shifted = shiftable_refine(ref, cur, p, r, HALF)
    assert shifted.mean() < 0.1
    np.testing.assert_array_equal(r2.pts[~shifted], r.pts[~shifted])
