"""Subsets beside a step of the parallax: shiftable windows.

A square subset centred on a point that lies within half a subset of a slip-band step
holds pixels of both sides of the step. Its affine shape function cannot follow the step,
and IC-GN returns a parallax between the two sides, with a Gauss–Newton σ that does not see
the misfit (the residual does). Shiftable windows (Kanade & Okutomi 1994; Fusiello,
Roberto & Trucco 1997, "Efficient stereo with multiple windowing", CVPR) match, for such a
point, the same-size subset displaced by ``shift`` pixels in several directions, the point
still inside it; a window that lies on the point's side of the step fits its shape
function, and its affine warp, expressed about the point (the subset offsets are measured
from the point), carries that side's parallax back to the point. The window with the
smallest normalised residual (residual variance over the one the image noise predicts) is
kept when it fits clearly better than the centred one.

The σ stays the subset's own Gauss–Newton covariance: for a displaced window it includes
the extrapolation of the affine terms from the window's centre to the point (larger than
the centred window's σ on the same texture).

Functions
---------
- :func:`shifted_offsets` — the pixel offsets of a square subset displaced from its point;
- :func:`step_candidates` — the points whose centred subset misfits (residual ratio);
- :func:`shiftable_refine` — re-match those points with displaced windows, keep the best.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .subset import icgn_refine

__all__ = ["shifted_offsets", "step_candidates", "shiftable_refine"]


def shifted_offsets(half_window, shift_px, angle_deg):
    """Integer offsets of a ``(2h+1)²`` square subset whose centre is displaced from the point.

    Parameters
    ----------
    half_window : int
        Subset half size ``h`` (pixels).
    shift_px : float
        Distance (pixels) from the point to the window's centre; at most ``h`` keeps the
        point inside the window.
    angle_deg : float
        Direction of the displacement in the image, degrees from +x toward +y.

    Returns
    -------
    (P, 2) int array of ``(dx, dy)`` offsets from the point, ``P = (2h+1)²``, for
    ``icgn_refine(subset_offsets=...)``.
    """
    h = int(half_window)
    a = np.deg2rad(angle_deg)
    c = np.rint([shift_px * np.cos(a), shift_px * np.sin(a)]).astype(int)
    off = np.arange(-h, h + 1)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    return np.stack([ox.ravel() + c[0], oy.ravel() + c[1]], 1)


def step_candidates(result, min_ratio=1.5):
    """(N,) bool: converged subsets whose residual variance exceeds ``min_ratio`` times the
    one the image noise predicts (``SubsetResult.residual_ratio``): the shape function does
    not fit, e.g. across a step of the parallax."""
    rr = np.asarray(result.residual_ratio, float)
    return np.asarray(result.converged, bool) & np.isfinite(rr) & (rr > min_ratio)


def shiftable_refine(ref_img, cur_img, pts_ref, result, half_windows, *, init_warp=None,
                     min_ratio=1.5, shift_frac=1.0, n_directions=8, min_gain=0.7,
                     min_zncc=0.9, smooth_sigma_px=0.0, ref_prefiltered=None,
                     cur_prefiltered=None, max_iter=30, tol_px=1e-4):
    """Re-match the points of ``result`` that misfit with displaced (shiftable) windows.

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current images (as given to :func:`semlab.subset.icgn_refine`).
    pts_ref : (N, 2) array
        Reference points ``(x, y)``, pixels.
    result : SubsetResult
        The centred subsets' result at ``pts_ref`` (from ``icgn_refine`` or
        ``adaptive_icgn``); its ``noise_sigma`` is reused so that every window's σ and
        residual ratio are on the same noise.
    half_windows : int or (N,) int array
        Each point's subset half size ``h`` (the displaced windows keep it).
    init_warp : (N, 6) array, optional
        Starting warps (default: ``result.warp``).
    min_ratio : float
        Points with a residual ratio above this are tried (:func:`step_candidates`).
    shift_frac : float
        Displacement of the window centre, as a fraction of ``h``.
    n_directions : int
        Displacement directions, evenly spaced over 360°.
    min_gain : float
        A displaced window replaces the centred one only when its residual ratio is below
        ``min_gain`` times the centred one's (and it converged with ZNCC ≥ ``min_zncc``).
    smooth_sigma_px, ref_prefiltered, cur_prefiltered, max_iter, tol_px
        As in :func:`semlab.subset.icgn_refine`.

    Returns
    -------
    result : SubsetResult
        ``result`` with the replaced points' position, warp, ZNCC, σ and residual ratio
        from their best displaced window.
    shifted : (N,) bool array
        Where a displaced window was kept.
    """
    pr = np.asarray(pts_ref, float)
    n = len(pr)
    hw = np.broadcast_to(np.asarray(half_windows, int), (n,))
    cand = step_candidates(result, min_ratio) & (hw > 0)
    shifted = np.zeros(n, bool)
    if not cand.any():
        return result, shifted
    out = {k: np.array(getattr(result, k), copy=True)
           for k in ("pts", "warp", "zncc", "sigma_px", "residual_ratio")}
    best = np.where(cand, min_gain * np.asarray(result.residual_ratio, float), np.nan)
    iw = result.warp if init_warp is None else init_warp
    noise = tuple(np.asarray(result.noise_sigma, float))
    for h in np.unique(hw[cand]):
        idx = np.flatnonzero(cand & (hw == h))
        for ang in np.arange(n_directions) * 360.0 / n_directions:
            r = icgn_refine(ref_img, cur_img, pr[idx], result.pts[idx], half_window=int(h),
                            warp="affine", init_warp=iw[idx],
                            subset_offsets=shifted_offsets(h, shift_frac * h, ang),
                            smooth_sigma_px=smooth_sigma_px, ref_prefiltered=ref_prefiltered,
                            cur_prefiltered=cur_prefiltered, noise_sigma=noise,
                            max_iter=max_iter, tol_px=tol_px)
            rr = np.where(r.converged & (r.zncc >= min_zncc), r.residual_ratio, np.inf)
            win = rr < best[idx]
            if not win.any():
                continue
            k = idx[win]
            best[k] = rr[win]
            shifted[k] = True
            for name in out:
                out[name][k] = getattr(r, name)[win]
    return replace(result, **out), shifted
