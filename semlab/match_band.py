"""Band-aware subsets: thin rectangles along the parallax bands near extrusion edges.

Used by :func:`semlab.matching.refine_correspondences` and
:func:`semlab.matching.auto_match`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .match_filters import _local_outliers, _parallax_gradients
from .match_prior import _apply_affine
from .subset import icgn_refine, oriented_subset, zncc_match


def _band_orientation(query_xy, grid_xy, grid_par, radius_px):
    """Direction of the parallax bands (degrees from x) and its coherence at query points.

    The structure tensor ``<∇p ∇pᵀ>`` of the parallax field ``p`` averaged within
    ``radius_px`` (Bigun & Granlund 1987; Jähne, Digital Image Processing, 6th ed.,
    section 13.3); the band direction is perpendicular to its main eigenvector. Returns
    ``(angle_deg, coherence, energy)`` with coherence in [0, 1] and energy the mean squared
    parallax gradient (px/px)².
    """
    ok = np.isfinite(grid_par)
    nq = len(query_xy)
    if ok.sum() < 6:
        return np.zeros(nq), np.zeros(nq), np.zeros(nq)
    gxy, gp = grid_xy[ok], grid_par[ok]
    g = _parallax_gradients(gxy, gp)
    T = np.stack([g[:, 0] ** 2, g[:, 0] * g[:, 1], g[:, 1] ** 2], axis=1)
    tree = cKDTree(gxy)
    groups = tree.query_ball_point(query_xy, r=radius_px)
    Tq = np.array([T[idx].mean(0) if len(idx) else np.zeros(3) for idx in groups])
    jxx, jxy, jyy = Tq.T
    tr = jxx + jyy
    coh = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / np.maximum(tr, 1e-30)
    grad_angle = 0.5 * np.degrees(np.arctan2(2 * jxy, jxx - jyy))
    return (grad_angle + 90.0) % 180.0, coh, tr


def _coarse_parallax(ref_img, img, M, half_window, search_px, smooth_sigma_px, ref_coef,
                     cur_coef, return_sigma=False):
    """Dense square-subset parallax on a grid every ``half_window`` px, for orientations.

    Returns grid points (G, 2) and the residual to the affine ``M`` along its principal
    direction (NaN where unmatched); with ``return_sigma`` also the noise σ of x (G,).
    """
    hgt, wid = ref_img.shape
    m = half_window + search_px + 2
    xs = np.arange(m, wid - m, half_window, dtype=float)
    ys = np.arange(m, hgt - m, half_window, dtype=float)
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    if len(grid) < 6:
        nan = np.full(len(grid), np.nan)
        return (grid, nan, nan) if return_sigma else (grid, nan)
    g0 = _apply_affine(M, grid)
    guess, _ = zncc_match(ref_img, img, grid, g0, half_window=half_window, search_px=search_px)
    L = M[:, :2] - np.eye(2)
    r = icgn_refine(ref_img, img, grid, np.where(np.isfinite(guess), guess, g0),
                    half_window=half_window, init_warp=[0, L[0, 0], L[0, 1], 0, L[1, 0], L[1, 1]],
                    smooth_sigma_px=smooth_sigma_px, ref_prefiltered=ref_coef,
                    cur_prefiltered=cur_coef)
    ok = r.converged & (r.zncc > 0.5)
    res = r.pts - _apply_affine(M, grid)
    if ok.sum() < 6:
        nan = np.full(len(grid), np.nan)
        return (grid, nan, nan) if return_sigma else (grid, nan)
    rc = res[ok] - np.median(res[ok], axis=0)
    _, _, vt = np.linalg.svd(rc, full_matrices=False)
    par = np.where(ok, res @ vt[0], np.nan)
    # drop gross outliers before differentiating
    good = np.isfinite(par)
    bad = _local_outliers(grid[good], par[good], 8, 0.5)
    par[np.flatnonzero(good)[bad]] = np.nan
    if return_sigma:
        return grid, par, np.where(np.isfinite(par), r.sigma_px[:, 0], np.nan)
    return grid, par


def _oriented_refine(ref_img, img, pts_ref, guess, grad, angles_deg, half_length, half_width,
                     smooth_sigma_px, ref_coef, cur_coef, step_deg=15.0,
                     return_residual_ratio=False):
    """IC-GN with thin rectangular subsets along the band direction of each point.

    ``grad`` is one initial warp (6,) for all points or one per point (n, 6);
    ``half_length`` one half length (pixels) for all points or one per point (n,). Returns
    positions (n, 2), noise σ of x (n,), ZNCC (n,) and with ``return_residual_ratio``
    the residual ratios (n,)."""
    n = len(pts_ref)
    pts = np.full((n, 2), np.nan)
    sig = np.full(n, np.nan)
    zn = np.full(n, -1.0)
    rr = np.full(n, np.nan)
    bins = np.round(np.asarray(angles_deg) / step_deg).astype(int) % int(round(180 / step_deg))
    lengths = np.broadcast_to(np.asarray(half_length, int), (n,))
    for b, hl in sorted(set(zip(bins.tolist(), lengths.tolist()))):
        sel = np.flatnonzero((bins == b) & (lengths == hl))
        off = oriented_subset(hl, half_width, b * step_deg)
        # thin subsets pin the across-band gradient terms weakly and IC-GN converges
        # slowly; 1e-3 px is ample for a choice made at the ~0.03 px level
        g = grad[sel] if np.ndim(grad) == 2 else grad
        r = icgn_refine(ref_img, img, pts_ref[sel], guess[sel], half_window=hl,
                        init_warp=g, smooth_sigma_px=smooth_sigma_px, subset_offsets=off,
                        ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, max_iter=60,
                        tol_px=1e-3)
        pts[sel] = r.pts
        sig[sel] = r.sigma_px[:, 0]
        zn[sel] = r.zncc
        rr[sel] = r.residual_ratio
    if return_residual_ratio:
        return pts, sig, zn, rr
    return pts, sig, zn


def _combine(sq_pts, sq_sig, or_pts, or_sig, or_zn, min_zncc, kappa):
    """Pick the band-aligned estimate where it disagrees with the square subset by more than
    ``kappa`` of its own σ (intersection-of-confidence-intervals / Lepski rule: the square
    subset is kept only while it is consistent with the less biased thin subset)."""
    use = (np.isfinite(or_pts[:, 0]) & (or_zn >= min_zncc)
           & ~(np.abs(sq_pts[:, 0] - or_pts[:, 0]) <= kappa * or_sig))
    pts = np.where(use[:, None], or_pts, sq_pts)
    sig = np.where(use, or_sig, sq_sig)
    return pts, sig, use
