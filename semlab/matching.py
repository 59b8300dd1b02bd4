"""Stereo correspondences between SEM views of the same surface.

Two or more end-state views taken at stage tilts (e.g. ±5°) differ by a near-identity
affine map (x scaling ``cos θ1 / cos θ0``, small shifts) plus a local parallax along the
epipolar direction (x for a tilt about the image y axis) proportional to the height
(``u = cx + (x cos θ + z sin θ) / s``). At ±5° and 0.03 µm/px one pixel of parallax is
about 0.17 µm of height, so the 8 nm height target needs ~0.05 px matching accuracy:
sub-pixel subset matching (:mod:`semlab.subset`, ZNCC search then IC-GN with ZNSSD).

- :func:`refine_correspondences` refines hand clicks: the reference-view click defines the
  material point; the clicks in the other views are only starting guesses (~0.5 px error).
- :func:`auto_match` finds correspondences automatically: SIFT features, Lowe's ratio test,
  a global affine RANSAC, dense optical flow for the initial guess (parallax of hundreds of
  pixels on tall objects), then a dense grid refined by IC-GN with robust outlier filters
  (texture, neighbours, forward–backward, multi-view rank 2).
- :func:`merge_matches` merges two results (e.g. clicks and automatic matches).

Conventions: images are 2D arrays indexed ``[row, col]``; points are ``(x, y)`` pixels,
x right, y down, origin at the centre of the top-left pixel. ``pts`` arrays are
``(N, V, 2)``: N points seen in V views.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from .errors import GeometryError, ImageError, SemlabError
from .adaptive import adaptive_icgn
from .noise import image_noise_sigma
from .registration import match_features
from .subset import icgn_refine, oriented_subset, prefilter_image, zncc_match

__all__ = ["MatchResult", "refine_correspondences", "auto_match", "merge_matches",
           "fit_affine"]


@dataclass(frozen=True)
class MatchResult:
    """Correspondences of N material points in V views.

    Attributes
    ----------
    pts : (N, V, 2) float array
        Pixel positions ``(x, y)`` in each view; NaN in a non-reference view where that
        view could not be matched. The reference-view positions are kept exactly as given.
    zncc : (N, V) float array
        Zero-normalised cross-correlation of the match in each view (1 in the reference
        view, -1 where undefined).
    valid : (N,) bool array
        True where every view matched with ``zncc >= min_zncc`` and passed the outlier
        tests.
    sigma_px : (N,) float array
        Estimated 1σ random matching error (pixels) along the parallax direction (x),
        root-mean-square over the non-reference views; NaN where invalid.
    reason : (N,) str array
        Empty for valid points, otherwise why the point was rejected.
    ref_view : int
        Index of the reference view.
    kind : (N,) str array
        Origin of each point: ``"click"`` (refined hand click) or ``"auto"``.
    source_index : (N,) int array
        Row of each point in the input of its kind (click row, or grid index for auto).
    subset_px : (N,) int array
        Side ``2h+1`` (pixels) of the largest square subset used for the point over the
        views: its spatial resolution (times the pixel size in µm). With
        ``target_sigma_px`` it is chosen per point (:func:`semlab.adaptive.adaptive_icgn`);
        None in results made without it.
    """

    pts: np.ndarray
    zncc: np.ndarray
    valid: np.ndarray
    sigma_px: np.ndarray
    reason: np.ndarray
    ref_view: int
    kind: np.ndarray
    source_index: np.ndarray
    subset_px: np.ndarray = None

    def __len__(self):
        return len(self.pts)

    @property
    def n_views(self):
        """Number of views V."""
        return self.pts.shape[1]

    def select(self, mask):
        """A new :class:`MatchResult` with the rows selected by ``mask`` (bool or index)."""
        m = np.asarray(mask)
        return replace(self, pts=self.pts[m], zncc=self.zncc[m], valid=self.valid[m],
                       sigma_px=self.sigma_px[m], reason=self.reason[m], kind=self.kind[m],
                       source_index=self.source_index[m],
                       subset_px=None if self.subset_px is None else self.subset_px[m])

    def only_valid(self):
        """The valid points only."""
        return self.select(self.valid)


# --------------------------------------------------------------------------- validation
def _check_images(images, n_views=None):
    if isinstance(images, np.ndarray) and images.ndim == 2:
        raise ImageError("images must be a sequence of 2 or more views, got one 2D array")
    try:
        ims = [np.asarray(im) for im in images]
    except TypeError:
        raise ImageError("images must be a sequence of 2D arrays (one per view)") from None
    if len(ims) < 2:
        raise ImageError(f"need 2 or more views, got {len(ims)}")
    for i, im in enumerate(ims):
        if im.ndim != 2:
            raise ImageError(f"view {i} must be a 2D grey image, got shape {im.shape}")
        if not np.issubdtype(im.dtype, np.number) or np.iscomplexobj(im):
            raise ImageError(f"view {i} must hold real numbers, got dtype {im.dtype}")
        if not np.all(np.isfinite(im)):
            raise ImageError(f"view {i} contains NaN or infinite values")
    shapes = {im.shape for im in ims}
    if len(shapes) != 1:
        raise ImageError(f"all views must have the same shape, got {[im.shape for im in ims]}; "
                         "crop them to a common size (the data bar removed) first")
    if n_views is not None and len(ims) != n_views:
        raise GeometryError(f"pts has {n_views} views per point but {len(ims)} images were given")
    return [im.astype(np.float64, copy=False) for im in ims]


def _check_ref_view(ref_view, n_views):
    if isinstance(ref_view, bool) or not float(ref_view).is_integer() or \
            not 0 <= int(ref_view) < n_views:
        raise GeometryError(f"ref_view must be a view index in 0..{n_views - 1}, got {ref_view!r}")
    return int(ref_view)


def fit_affine(src, dst):
    """Least-squares 2D affine map ``dst ≈ src @ M[:, :2].T + M[:, 2]``.

    Parameters
    ----------
    src, dst : (N, 2) arrays of (x, y) pixels, N >= 3 not collinear.

    Returns
    -------
    M : (2, 3) array.

    Raises
    ------
    GeometryError
        With fewer than 3 points or collinear points.
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    if len(src) < 3:
        raise GeometryError(f"an affine map needs 3 or more points, got {len(src)}")
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2:
        raise GeometryError(f"src and dst must be (N, 2) arrays of the same shape, got "
                            f"{src.shape} and {dst.shape}")
    c = src - src.mean(0)
    if np.linalg.matrix_rank(c, tol=1e-9 * max(1.0, np.abs(c).max())) < 2:
        raise GeometryError("the points are collinear; an affine map is undetermined")
    X = np.column_stack([src, np.ones(len(src))])
    sol, *_ = np.linalg.lstsq(X, dst, rcond=None)
    return sol.T


def _apply_affine(M, p):
    return p @ M[:, :2].T + M[:, 2]



# --------------------------------------------------------------------------- band-aware refinement
def _parallax_gradients(xy, par, k=12, return_residual=False, quadratic=False):
    """Gradient of a scattered parallax field by local least-squares planes (k neighbours).

    Returns (n, 2) gradients, and with ``return_residual`` also the RMS residual (n,) of
    each local plane. ``quadratic``: fit local quadrics instead (curved parallax fields of
    tall objects), residuals of those."""
    n = len(xy)
    kk = min(k, n)
    _, nb = cKDTree(xy).query(xy, k=kk)
    nb = nb.reshape(n, kk)
    d = xy[nb] - xy[:, None, :]                                    # (n, k, 2)
    cols = [np.ones((n, kk, 1)), d]
    if quadratic:
        sc = max(float(np.median(np.abs(d))), 1e-9)               # keep the system scaled
        q = d / sc
        cols.append(np.stack([q[..., 0] ** 2, q[..., 0] * q[..., 1], q[..., 1] ** 2], -1))
    X = np.concatenate(cols, axis=2)                               # (n, k, 3 or 6)
    y = par[nb]
    XtX = np.einsum("nki,nkj->nij", X, X) + 1e-9 * np.eye(X.shape[2])
    Xty = np.einsum("nki,nk->ni", X, y)
    sol = np.linalg.solve(XtX, Xty[..., None])[..., 0]
    if return_residual:
        res = y - np.einsum("nki,ni->nk", X, sol)
        return sol[:, 1:], np.sqrt(np.mean(res ** 2, axis=1))
    return sol[:, 1:]


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
                     cur_coef):
    """Dense square-subset parallax on a grid every ``half_window`` px, for orientations.

    Returns grid points (G, 2) and the residual to the affine ``M`` along its principal
    direction (NaN where unmatched).
    """
    hgt, wid = ref_img.shape
    m = half_window + search_px + 2
    xs = np.arange(m, wid - m, half_window, dtype=float)
    ys = np.arange(m, hgt - m, half_window, dtype=float)
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    if len(grid) < 6:
        return grid, np.full(len(grid), np.nan)
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
        return grid, np.full(len(grid), np.nan)
    rc = res[ok] - np.median(res[ok], axis=0)
    _, _, vt = np.linalg.svd(rc, full_matrices=False)
    par = np.where(ok, res @ vt[0], np.nan)
    # drop gross outliers before differentiating
    good = np.isfinite(par)
    bad = _local_outliers(grid[good], par[good], 8, 0.5)
    par[np.flatnonzero(good)[bad]] = np.nan
    return grid, par


def _oriented_refine(ref_img, img, pts_ref, guess, grad, angles_deg, half_length, half_width,
                     smooth_sigma_px, ref_coef, cur_coef, step_deg=15.0):
    """IC-GN with thin rectangular subsets along the band direction of each point.

    ``grad`` is one initial warp (6,) for all points or one per point (n, 6)."""
    n = len(pts_ref)
    pts = np.full((n, 2), np.nan)
    sig = np.full(n, np.nan)
    zn = np.full(n, -1.0)
    bins = np.round(np.asarray(angles_deg) / step_deg).astype(int) % int(round(180 / step_deg))
    for b in np.unique(bins):
        sel = np.flatnonzero(bins == b)
        off = oriented_subset(half_length, half_width, b * step_deg)
        # thin subsets pin the across-band gradient terms weakly and IC-GN converges
        # slowly; 1e-3 px is ample for a choice made at the ~0.03 px level
        g = grad[sel] if np.ndim(grad) == 2 else grad
        r = icgn_refine(ref_img, img, pts_ref[sel], guess[sel], half_window=half_length,
                        init_warp=g, smooth_sigma_px=smooth_sigma_px, subset_offsets=off,
                        ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, max_iter=60,
                        tol_px=1e-3)
        pts[sel] = r.pts
        sig[sel] = r.sigma_px[:, 0]
        zn[sel] = r.zncc
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

# --------------------------------------------------------------------------- refine clicks
def refine_correspondences(images, pts, ref_view=0, half_window=10, search_px=4,
                           warp="affine", min_zncc=0.8, *, smooth_sigma_px=None,
                           band_aware=True, band_half_width_px=3, kappa=1.0,
                           target_sigma_px=0.05, min_half_window=7, max_half_window=28,
                           progress=False):
    """Refine hand-clicked correspondences to sub-pixel accuracy.

    The reference-view positions are kept exactly (they define which material point is
    measured). In every other view the click is the starting guess: an integer ZNCC search
    within ``±search_px`` (:func:`semlab.subset.zncc_match`), then IC-GN refinement of an
    affine subset warp (:func:`semlab.subset.icgn_refine`), started from the linear part of
    the least-squares affine map between the clicks (so the x scaling ``cos θj / cos θref``
    of the tilt is built in).

    Parameters
    ----------
    images : sequence of V (H, W) arrays
        The views (same shape), V >= 2.
    pts : (N, V, 2) array
        Clicked ``(x, y)`` pixels of N points in each view, N >= 1.
    ref_view : int
        View whose positions are kept.
    half_window : int
        Subset half size (subset ``(2h+1)²`` pixels). 10 (21×21) was more accurate than
        15 on synthetic ±5° scenes with sharp extrusion edges
        (``benchmarks/stereo_matching_check.py``).
    search_px : int
        ZNCC search radius around each click, pixels.
    warp : {"affine", "translation"}
        Subset shape function of the IC-GN step.
    min_zncc : float
        Matches with a lower ZNCC in any view are marked invalid.
    smooth_sigma_px : float or None
        Gaussian pre-smoothing of the views for IC-GN (see
        :func:`semlab.subset.icgn_refine`); reduces noise-induced bias on noisy images and
        keeps the noise of the reference gradients out of the predicted σ. None: 0.8 px
        with ``target_sigma_px``, else 0.
    band_aware : bool
        Also match each point with a thin rectangular subset (``4h+1`` long,
        ``2 band_half_width_px + 1`` wide) along the local direction of the parallax bands,
        estimated from the structure tensor of a coarse dense parallax field (every
        ``h`` pixels), and keep it where the square subset disagrees with it by more than
        ``kappa`` of its σ: near the edges of extrusions the parallax changes within a
        square subset and biases it, while a subset along the band sees a nearly constant
        parallax.
    band_half_width_px, kappa : float
        See ``band_aware``.
    target_sigma_px : float or None
        Size each point's square subset by its information: the smallest from
        ``min_half_window`` up to ``max_half_window`` whose predicted σ reaches this target
        (pixels), with the shape function it supports
        (:func:`semlab.adaptive.adaptive_icgn`; ``warp`` and ``half_window`` are then
        ignored, ``min_half_window`` sizes the band-aware subsets). None: one fixed
        ``half_window``. On the
        192×256 accuracy-matrix cells (realistic noise, ±5°) 0.05 px gave height RMSE
        35.9 / 25.2 / 15.4 nm (polished / real:fei / speckle) against 41.6 / 38.8 / 18.6 nm
        with a fixed 21×21 subset and 43.1 / 49.7 / 27.3 nm for ECC.
    min_half_window, max_half_window : int
        Smallest and largest subset half sizes with ``target_sigma_px``.
    progress : bool
        Show progress bars.

    Returns
    -------
    MatchResult
        ``kind = "click"``; invalid points keep NaN in the views that failed.

    Raises
    ------
    ImageError
        If the views are not 2D, not finite or of different shapes, or fewer than 2.
    GeometryError
        If ``pts`` is not ``(N, V, 2)`` with N >= 1 and V = number of images, holds NaN, or
        has points outside the images.
    """
    p = np.asarray(pts, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 2:
        raise GeometryError(f"pts must be an (N, V, 2) array of (x, y) pixels, got shape {p.shape}")
    n, v = p.shape[:2]
    ims = _check_images(images, v)
    if n < 1:
        raise GeometryError("need at least 1 point to refine, got 0")
    if not np.all(np.isfinite(p)):
        bad = np.flatnonzero(~np.all(np.isfinite(p), axis=(1, 2)))
        raise GeometryError(f"pts contains NaN/inf (rows {bad[:10].tolist()}); remove those "
                            "points or complete their clicks")
    hgt, wid = ims[0].shape
    outside = (p[..., 0] < 0) | (p[..., 0] > wid - 1) | (p[..., 1] < 0) | (p[..., 1] > hgt - 1)
    if np.any(outside):
        r, c = np.nonzero(outside)
        raise GeometryError(f"{len(r)} clicked positions lie outside the {wid}×{hgt} images "
                            f"(first: point {r[0]}, view {c[0]}: {p[r[0], c[0]].tolist()})")
    ref = _check_ref_view(ref_view, v)
    if not 0 <= min_zncc <= 1:
        raise SemlabError(f"min_zncc must be in [0, 1], got {min_zncc!r}")

    out = p.copy()
    zn = np.ones((n, v))
    sig_x = np.zeros((n, v))
    valid = np.ones(n, bool)
    reason = np.full(n, "", dtype=object)
    side = np.zeros(n, int)
    pr = p[:, ref]
    if smooth_sigma_px is None:
        smooth_sigma_px = 0.0 if target_sigma_px is None else 0.8
    if target_sigma_px is not None:
        half_window = min_half_window      # the square ladder's start sizes the band subsets
    ref_coef = prefilter_image(ims[ref], smooth_sigma_px)
    for j in range(v):
        if j == ref:
            continue
        grad = np.zeros(6)
        if n >= 3:
            try:
                M = fit_affine(pr, p[:, j])
                L = M[:, :2] - np.eye(2)
                if np.all(np.abs(L) < 0.2):
                    grad = np.array([0, L[0, 0], L[0, 1], 0, L[1, 0], L[1, 1]])
            except GeometryError:
                pass
        guess, z0 = zncc_match(ims[ref], ims[j], pr, p[:, j], half_window=half_window,
                               search_px=search_px)
        cur_coef = prefilter_image(ims[j], smooth_sigma_px)
        r, hw_j = _grid_icgn(ims[ref], ims[j], pr, np.where(np.isfinite(guess), guess, p[:, j]),
                             half_window, warp, grad, smooth_sigma_px, ref_coef, cur_coef,
                             target_sigma_px, max_half_window, progress=progress)
        side = np.maximum(side, np.where(r.converged, 2 * hw_j + 1, 0))
        pts_j, sig_j, zn_j = r.pts.copy(), r.sigma_px[:, 0].copy(), r.zncc.copy()
        ok_j = r.converged & (r.zncc >= min_zncc)
        nosearch = ~np.all(np.isfinite(guess), 1)
        if band_aware:
            Mj = fit_affine(pr, p[:, j]) if n >= 3 else np.column_stack(
                [np.eye(2), np.median(p[:, j] - pr, axis=0)])
            gxy, gpar = _coarse_parallax(ims[ref], ims[j], Mj, half_window, search_px,
                                         smooth_sigma_px, ref_coef, cur_coef)
            ang, _, _ = _band_orientation(pr, gxy, gpar, 2.0 * half_window)
            # every point with a usable start: square result, else the ZNCC peak
            start = np.where(np.isfinite(r.pts), r.pts, guess)
            sel = np.flatnonzero(np.all(np.isfinite(start), 1))
            if len(sel):
                o_pts, o_sig, o_zn = _oriented_refine(
                    ims[ref], ims[j], pr[sel], start[sel], grad, ang[sel], 2 * half_window,
                    band_half_width_px, smooth_sigma_px, ref_coef, cur_coef)
                sq = np.where(ok_j[sel, None], r.pts[sel], np.nan)
                c_pts, c_sig, use = _combine(sq, sig_j[sel], o_pts, o_sig, o_zn, min_zncc,
                                             kappa)
                pts_j[sel], sig_j[sel] = c_pts, c_sig
                zn_j[sel] = np.where(use, o_zn, zn_j[sel])
                ok_j[sel] |= use
        pts_j[~ok_j] = np.nan
        out[:, j] = pts_j
        zn[:, j] = zn_j
        sig_x[:, j] = sig_j
        for i in np.flatnonzero(~ok_j):
            if not r.converged[i]:
                why = r.reason[i]
                if nosearch[i] and z0[i] > -1:
                    why += f" (ZNCC peak on the edge of ±{search_px} px: click too far off?)"
            else:
                why = f"zncc {r.zncc[i]:.2f} < min_zncc {min_zncc}"
            reason[i] = "; ".join(filter(None, [reason[i], f"view {j}: {why}"]))
            valid[i] = False
    others = [j for j in range(v) if j != ref]
    sigma = np.sqrt(np.mean(sig_x[:, others] ** 2, axis=1))
    sigma[~valid] = np.nan
    return MatchResult(pts=out, zncc=zn, valid=valid, sigma_px=sigma,
                       reason=reason.astype(str), ref_view=ref,
                       kind=np.full(n, "click"), source_index=np.arange(n), subset_px=side)


def _ladder(h_min, h_max):
    """Subset half sizes from h_min to h_max growing by ~1.4 (√2: twice the pixels)."""
    hs = [int(h_min)]
    while hs[-1] < h_max:
        hs.append(min(int(h_max), max(hs[-1] + 1, int(round(hs[-1] * 1.4)))))
    return tuple(hs)


def _grid_icgn(ref_img, img, pts, guess, half_window, warp, init_warp, smooth_sigma_px,
               ref_coef, cur_coef, target_sigma_px, max_half_window, **kw):
    """IC-GN of the square subsets, fixed or sized by ``target_sigma_px``; returns the
    SubsetResult and the (N,) half sizes used."""
    if target_sigma_px is None:
        r = icgn_refine(ref_img, img, pts, guess, half_window=half_window, warp=warp,
                        init_warp=init_warp, smooth_sigma_px=smooth_sigma_px,
                        ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, **kw)
        return r, np.full(len(pts), int(half_window))
    kw.pop("progress", None)
    a = adaptive_icgn(ref_img, img, pts, guess, target_sigma_px,
                      half_windows=_ladder(half_window, max(half_window, max_half_window)),
                      init_warp=init_warp, smooth_sigma_px=smooth_sigma_px,
                      ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, **kw)
    # a point that missed the target is still a match (its sigma says how good)
    reason = np.where(a.subset.converged, "", a.subset.reason)
    return replace(a.subset, reason=reason), np.maximum(a.half_window, 0)


# --------------------------------------------------------------------------- automatic
def _to_uint8(img):
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((img - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)


def _robust_affine(src, dst, thresh_px, seed):
    """Global affine by RANSAC (cv2.estimateAffine2D) then least squares on inliers."""
    import cv2

    cv2.setRNGSeed(int(seed))
    M, inl = cv2.estimateAffine2D(src.astype(np.float32), dst.astype(np.float32),
                                  method=cv2.RANSAC, ransacReprojThreshold=thresh_px,
                                  maxIters=5000, confidence=0.999)
    if M is None or inl is None or inl.sum() < 6:
        raise GeometryError("no consistent global affine map between the views was found "
                            "(too few SIFT matches); check that the views show the same area")
    inl = inl.ravel().astype(bool)
    M = fit_affine(src[inl], dst[inl])
    return M, inl


def _local_outliers(xy, values, k, thresh_floor, n_mad=4.0):
    """Flag values that disagree with the median of their k nearest neighbours.

    A point is an outlier when ``|v - median_nb| > max(n_mad * 1.4826 * MAD_nb,
    thresh_floor)`` (robust local consistency; Westerweel & Scarano 2005,
    "Universal outlier detection for PIV data", Exp. Fluids 39, in its median form).
    """
    if len(xy) < 3:
        return np.zeros(len(xy), bool)
    kk = min(k + 1, len(xy))
    _, nb = cKDTree(xy).query(xy, k=kk)
    nbv = values[nb[:, 1:]]
    med = np.median(nbv, axis=1)
    mad = np.median(np.abs(nbv - med[:, None]), axis=1)
    return np.abs(values - med) > np.maximum(n_mad * 1.4826 * mad, thresh_floor)


def _subset_std(img, half_window, pts):
    """Intensity standard deviation of the ``(2h+1)²`` subset at each (x, y) point."""
    import cv2

    k = 2 * int(half_window) + 1
    a = np.asarray(img, np.float64)
    mu = cv2.boxFilter(a, -1, (k, k), borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(a * a, -1, (k, k), borderType=cv2.BORDER_REFLECT)
    sd = np.sqrt(np.maximum(m2 - mu * mu, 0.0))
    ij = np.rint(pts).astype(int)
    return sd[ij[:, 1], ij[:, 0]]


def _norm8(img, sigma_px, eps):
    """Local contrast normalisation to 8 bits: ``(I - G*I) / (sqrt(G*(I - G*I)²) + eps)``
    with a Gaussian ``G`` of ``sigma_px``, mapped to 128 ± 32 per local standard deviation.
    Removes the smooth shading differences between SEM views before optical flow."""
    import cv2

    a = np.asarray(img, np.float32)
    mu = cv2.GaussianBlur(a, (0, 0), sigma_px)
    d = a - mu
    sd = np.sqrt(cv2.GaussianBlur(d * d, (0, 0), sigma_px))
    return np.clip(d / (sd + np.float32(eps)) * 32 + 128, 0, 255).astype(np.uint8)


def _sample(field, pts):
    """Bilinear samples of an (H, W) or (H, W, C) float field at (x, y) points:
    (n,) or (n, C) array (border values replicated)."""
    import cv2

    f = np.ascontiguousarray(field, dtype=np.float32)
    n = len(pts)
    cols = 1024                        # remap maps must stay below 32767 rows
    rows = max(1, -(-n // cols))
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = pts[:, 0], pts[:, 1]
    out = cv2.remap(f, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    out = out.reshape(rows * cols, -1)[:n].astype(np.float64)
    return out[:, 0] if f.ndim == 2 else out


def _flow_field(ref_img, img, M, half_window, eps):
    """Dense optical flow from the reference view to ``img`` mapped into its frame.

    View ``img`` is mapped into the reference frame by the global affine ``M`` (ref → img),
    both views are contrast-normalised (:func:`_norm8`, regulariser ``eps`` grey levels)
    and the residual displacement ``f(x)`` (parallax and what the affine misses) is found by
    DIS optical flow (Kroeger et al. 2016, "Fast optical flow using dense inverse search",
    ECCV; coarse to fine, so it follows parallax of hundreds of pixels that varies over the
    image), forward and backward.

    Returns
    -------
    warped : (H, W) float32 array, ``img`` mapped into the reference frame by ``M``.
    fwd, bwd : (H, W, 2) float32 arrays, flow reference → warped and back, pixels.
    """
    import cv2

    hgt, wid = ref_img.shape
    if np.shape(M) == (2, 3):
        warped = cv2.warpAffine(np.asarray(img, np.float32), M.astype(np.float64), (wid, hgt),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_REFLECT)
    else:   # a dense prior map (H, W, 2): where each reference pixel lies in img
        warped = cv2.remap(np.asarray(img, np.float32), M[..., 0], M[..., 1],
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    sig = 2.0 * half_window
    a8 = _norm8(ref_img, sig, eps)
    b8 = _norm8(warped, sig, eps)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    dis.setFinestScale(0)
    fwd = dis.calc(a8, b8, None)
    bwd = dis.calc(b8, a8, None)
    return warped, fwd, bwd


def _aligned_noise(ref_img, warped, fwd, half_window):
    """Image noise σ (grey levels) from the difference of two aligned views.

    ``warped`` is resampled along the flow onto the reference; both are high-passed
    (minus a Gaussian of ``2 half_window``, which removes shading differences) and the
    second is scaled to the first by least squares. The views share the texture but not the
    noise, so ``1.4826 MAD(difference) / √2`` estimates the noise of one view whatever its
    spectrum (e.g. correlated noise of a resampled image, where single-image estimators
    see almost none); mis-registered edges are outliers of the MAD.
    """
    import cv2

    hgt, wid = ref_img.shape
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float32)
    al = cv2.remap(warped, xx + fwd[..., 0], yy + fwd[..., 1], cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_REFLECT)
    a = np.asarray(ref_img, np.float32)
    sig = 2.0 * half_window
    ha = a - cv2.GaussianBlur(a, (0, 0), sig)
    hb = al - cv2.GaussianBlur(al, (0, 0), sig)
    m = 2 * half_window
    ha, hb = ha[m:-m, m:-m], hb[m:-m, m:-m]
    g = float((ha * hb).sum() / max(float((hb * hb).sum()), 1e-30))
    d = (ha - g * hb).ravel()
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _field_jacobian(field, pts):
    """Jacobian (n, 2, 2) ``[[∂u/∂x, ∂u/∂y], [∂v/∂x, ∂v/∂y]]`` of an (H, W, 2) float32
    field ``(u, v)`` at (x, y) points (central differences, bilinear sampling)."""
    import cv2

    dx = _sample(cv2.Sobel(field, cv2.CV_32F, 1, 0, ksize=1, scale=0.5), pts)   # (n, 2)
    dy = _sample(cv2.Sobel(field, cv2.CV_32F, 0, 1, ksize=1, scale=0.5), pts)
    return np.stack([dx, dy], axis=2)


def _flow_guess(M, fwd, bwd, grid, half_window):
    """Initial guesses of grid points from the flow of :func:`_flow_field`.

    The guess of grid point ``x`` is ``M(x + f(x))`` and its initial warp gradient
    ``A (I + ∇f) − I`` (``A`` the linear part of ``M``, ``∇f`` of the flow smoothed over a
    subset).

    Returns
    -------
    guess : (n, 2) array of (x, y) pixels in the view.
    init_warp : (n, 6) array ``(0, du/dx, du/dy, 0, dv/dx, dv/dy)``.
    fb_err : (n,) array
        Forward–backward inconsistency ``|f(x) + b(x + f(x))|`` of the flow (pixels): large
        where the flow is unreliable (occlusions, no texture).
    """
    import cv2

    f = _sample(fwd, grid)
    fb_err = np.hypot(*(f + _sample(bwd, grid + f)).T)
    if np.shape(M) == (2, 3):
        guess = _apply_affine(M, grid + f)
        A = np.broadcast_to(M[:, :2], (len(grid), 2, 2))
    else:   # dense prior map Φ: guess Φ(x + f), Jacobian ∇Φ there
        guess = _sample(M, grid + f)
        A = _field_jacobian(M, grid + f)
    # flow gradient over a subset (Gaussian-smoothed central differences)
    J = _field_jacobian(cv2.GaussianBlur(fwd, (0, 0), max(1.0, half_window / 2)), grid)
    G = np.einsum("nij,njk->nik", A, np.eye(2) + J) - np.eye(2)
    G = np.clip(G, -0.8, 0.8)
    z = np.zeros(len(grid))
    init = np.column_stack([z, G[:, 0, 0], G[:, 0, 1], z, G[:, 1, 0], G[:, 1, 1]])
    return guess, init, fb_err


def _dense_prior(src, dst, shape, half_window, k=9, thresh_px=3.0, step_px=8):
    """Dense map (H, W, 2) float32: where each reference pixel lies in the other view,
    interpolated from the sparse feature matches.

    For views that no global affine map describes (a tall object: parallax of hundreds of
    pixels varying over the image, so that only a small part of the matches fits one
    affine), the matches are filtered by local consistency (a match whose displacement
    differs by more than ``thresh_px`` from the median of its ``k − 1`` nearest neighbours
    is dropped, twice), linearly interpolated between them (nearest value outside their
    convex hull) on a grid of ``step_px`` and smoothed over a subset.
    """
    import cv2
    from scipy.interpolate import griddata

    s, d = np.asarray(src, float), np.asarray(dst, float) - np.asarray(src, float)
    for _ in range(2):
        if len(s) <= k:
            break
        _, nb = cKDTree(s).query(s, k=k)
        med = np.median(d[nb[:, 1:]], axis=1)
        good = np.hypot(*(d - med).T) < thresh_px
        s, d = s[good], d[good]
    if len(s) < 6:
        raise GeometryError("too few consistent feature matches for a dense parallax prior")
    hgt, wid = shape
    gx = np.arange(0, wid + step_px, step_px, dtype=float)
    gy = np.arange(0, hgt + step_px, step_px, dtype=float)
    GX, GY = np.meshgrid(gx, gy)
    q = np.column_stack([GX.ravel(), GY.ravel()])
    lin = np.column_stack([griddata(s, d[:, c], q, method="linear") for c in (0, 1)])
    near = np.column_stack([griddata(s, d[:, c], q, method="nearest") for c in (0, 1)])
    D = np.where(np.isfinite(lin), lin, near).reshape(len(gy), len(gx), 2).astype(np.float32)
    D = cv2.resize(D, (int(gx[-1]) + 1, int(gy[-1]) + 1), interpolation=cv2.INTER_LINEAR)
    D = cv2.GaussianBlur(D[:hgt, :wid], (0, 0), max(1.0, float(half_window)))
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(np.float32)
    return np.ascontiguousarray(np.stack([xx + D[..., 0], yy + D[..., 1]], -1))


def _backward_distance(img, ref_img, pts, pts_ref, warp, half_window, smooth_sigma_px,
                       img_coef, ref_coef, max_iter, tol_px):
    """Distance (pixels) between ``pts_ref`` and the backward IC-GN match of ``pts`` (in
    ``img``) into ``ref_img``, started at ``pts_ref`` with the inverse of the forward warp
    gradient (NaN where the backward match fails)."""
    g = np.where(np.isfinite(warp), warp, 0.0)
    A = np.stack([np.stack([1 + g[:, 1], g[:, 2]], 1), np.stack([g[:, 4], 1 + g[:, 5]], 1)], 1)
    det = np.linalg.det(A)
    A[np.abs(det) < 1e-6] = np.eye(2)
    B = np.linalg.inv(A) - np.eye(2)
    z = np.zeros(len(pts))
    init = np.column_stack([z, B[:, 0, 0], B[:, 0, 1], z, B[:, 1, 0], B[:, 1, 1]])
    r = icgn_refine(img, ref_img, pts, pts_ref, half_window=half_window, init_warp=init,
                    smooth_sigma_px=smooth_sigma_px, ref_prefiltered=img_coef,
                    cur_prefiltered=ref_coef, max_iter=max_iter, tol_px=tol_px)
    return np.hypot(*(r.pts - pts_ref).T)


def _multiview_residual(pts, ref, mask, n_iter=3, n_mad=4.0, floor_px=0.0):
    """Per-point residual (pixels) of the multi-view x coordinates to a rank-2 model.

    For an affine camera tilted about an axis near the image y axis, the x coordinates of a
    point in V views are ``u_i = cos θ_i x + sin θ_i z + ε_i y + t_i``: after removing the
    linear dependence on the reference-view y (a slightly rotated tilt axis) and the means,
    the N × V matrix of x coordinates has rank 2 (Tomasi & Kanade 1992; Hartley & Zisserman
    2nd ed. section 18.2). The rank-2 fit is made on ``mask`` points, re-fitted without
    the points beyond ``max(n_mad · 1.4826 MAD, floor_px)``; each point's residual is the
    RMS over views of its distance to the fitted model. Needs V >= 3 (else zeros).

    Returns
    -------
    res : (N,) array of residuals in pixels (NaN where a coordinate is NaN).
    rms : float, RMS residual over the final inliers.
    """
    n, v = pts.shape[:2]
    res = np.zeros(n)
    if v < 3 or mask.sum() < 8:
        return res, 0.0
    U = pts[:, :, 0]
    y = pts[:, ref, 1]
    D = np.column_stack([U, y])                 # (N, V+1)
    fin = np.all(np.isfinite(D), 1)
    use = mask & fin
    for _ in range(n_iter):
        mu = D[use].mean(0)
        Dc = D - mu
        # remove the y dependence (regression of each u_i on y), then rank 2
        yc = Dc[:, -1]
        beta = (Dc[use, :-1] * yc[use, None]).sum(0) / max((yc[use] ** 2).sum(), 1e-12)
        R = Dc[:, :-1] - yc[:, None] * beta
        _, _, vt = np.linalg.svd(R[use], full_matrices=False)
        P = vt[:2].T @ vt[:2]
        E = R - R @ P
        res = np.sqrt(np.mean(E ** 2, axis=1))
        r_in = res[use]
        thr = max(n_mad * 1.4826 * np.median(np.abs(r_in - np.median(r_in))) + np.median(r_in),
                  floor_px)
        new = mask & fin & (res <= thr)
        if new.sum() < 8 or np.array_equal(new, use):
            break
        use = new
    res[~fin] = np.nan
    return res, float(np.sqrt(np.mean(res[use] ** 2)))


def _choose_smoothing(ref_img, img, pts_ref, guess, guess0, init_w, half_window, min_zncc,
                      seed, n_trial=200, sigma_px=1.0):
    """Gaussian pre-smoothing for noisy views: 0 if unsmoothed IC-GN converges with
    ``zncc >= min_zncc`` on at least half of a random sample of ``n_trial`` points, else
    ``sigma_px`` (on noisy SEM images the unsmoothed ZNSSD cost is too rough to converge;
    Pan 2013, Opt. Lasers Eng. 51(10))."""
    n = len(pts_ref)
    rng = np.random.default_rng(seed)
    k = rng.choice(n, min(n, n_trial), replace=False)
    g = np.where(np.isfinite(guess[k]), guess[k], guess0[k])
    r = icgn_refine(ref_img, img, pts_ref[k], g, half_window=half_window, init_warp=init_w[k],
                    max_iter=30, tol_px=1e-3)
    ok = r.converged & (r.zncc >= min_zncc)
    return 0.0 if ok.mean() >= 0.5 else float(sigma_px)


def auto_match(images, ref_view=0, spacing_px=8, detector="sift", ratio=0.8, half_window=10,
               min_zncc=0.9, max_points=None, seed=0, progress=True, *, search_px=3,
               smooth_sigma_px=None, consistency_px=0.3, band_aware=True,
               band_half_width_px=3, kappa=1.0, max_roughness_px=0.08, dense_init=True,
               wide_search_px=10, min_texture_snr=1.0, multiview_px=0.3, max_iter=60,
               tol_px=1e-3, max_features=5000, backward_px=0.1, dense_prior_below=0.5,
               target_sigma_px=None, max_half_window=28):
    """Automatic dense correspondences between SEM views.

    1. Sparse features (SIFT, Lowe 2004 IJCV 60(2); or Shi–Tomasi corners 1994 described by
       SIFT; or both) matched with Lowe's ratio test.
    2. A global 2D affine map per view by RANSAC (``cv2.estimateAffine2D``; Fischler &
       Bolles 1981), threshold 3 px, then a second test on the residual across the parallax
       direction (the affine epipolar constraint, Hartley & Zisserman 2nd ed. section 14.2):
       matches more than 1 px off the principal direction of the inlier residuals are
       dropped and the affine map is re-fitted.
    3. A regular grid (``spacing_px``) in the reference view. Points whose subset has too
       little texture (featureless background: subset standard deviation, noise removed,
       below ``min_texture_snr`` times the image noise) are flagged ``"low texture"`` and
       not matched. The noise is estimated from the difference of the first view pair
       aligned by the flow of step 4 (whatever its spectrum), or without ``dense_init``
       by Immerkær's white-noise estimator.
    4. Dense initial guess (``dense_init``): the view is mapped into the reference frame by
       the affine, both are contrast-normalised and DIS optical flow (Kroeger et al. 2016,
       coarse to fine) gives each grid point its position and local warp gradient, to about
       a pixel even where the parallax reaches hundreds of pixels and varies strongly. Where
       the forward and backward flows disagree by more than 1 px the ZNCC search radius is
       ``wide_search_px`` instead of ``search_px``. (With ``dense_init=False`` the guess is
       the affine plus the median parallax of the 8 nearest sparse matches: only good for
       small, slowly varying parallax.)
    5. ZNCC search, then IC-GN refinement (:func:`semlab.subset.icgn_refine`) of an affine
       subset started from the flow's warp gradient.
    6. Band-aware refinement (``band_aware``): each point is matched again with a thin
       subset along the local direction of the parallax bands (structure tensor of the
       dense parallax field) and that estimate is kept where the square subset disagrees
       with it (see :func:`refine_correspondences`).
    7. Outlier filter: convergence, ``zncc >= min_zncc`` in every view, local consistency
       of the parallax and cross-parallax residuals against the 8 nearest grid neighbours
       (median ± max(4 × 1.4826 MAD, ``consistency_px``)), repeated once, a local
       planarity test of the parallax (``max_roughness_px``), and with 3 or more views the
       multi-view test: the x coordinates of a point in all views must fit the rank-2
       affine model of a tilt series (see ``multiview_px``).
    8. Forward–backward test (``backward_px``): the accepted points matched back from each
       view must return to their reference position.

    Parameters
    ----------
    images : sequence of V (H, W) arrays
        The views (same shape), V >= 2.
    ref_view : int
        Reference view (grid points are placed in it and kept exactly).
    spacing_px : float
        Grid spacing in the reference view, pixels.
    detector : {"sift", "shi-tomasi", "both"}
        Sparse feature detector.
    ratio : float
        Lowe ratio-test threshold (0 < ratio < 1).
    half_window : int
        Subset half size for IC-GN.
    min_zncc : float
        Minimum ZNCC in every view.
    max_points : int, optional
        Keep at most this many grid points (a random subset drawn with ``seed``).
    seed : int
        Seed of RANSAC and of the ``max_points`` subsampling.
    progress : bool
        Show progress bars.
    search_px : int
        ZNCC search radius around the predicted position.
    smooth_sigma_px : float or None
        Gaussian pre-smoothing for IC-GN (see :func:`semlab.subset.icgn_refine`). None
        (default) chooses it on the first view pair: 0 when unsmoothed IC-GN converges with
        ``zncc >= min_zncc`` on at least half of 200 random textured grid points, else
        1.0 px (noisy real SEM images, where the unsmoothed cost is too rough).
    consistency_px : float
        Floor of the local-consistency threshold, pixels.
    band_aware, band_half_width_px, kappa
        Band-aligned thin subsets near parallax edges, as in
        :func:`refine_correspondences`.
    max_roughness_px : float or None
        Points where the parallax field is not locally planar are marked invalid: the RMS
        residual (pixels) of a least-squares plane (a quadric for views matched with the
        dense prior, whose parallax is curved) through the parallax of the point and
        its 11 nearest accepted neighbours (about ±1.5 grid spacings) must not exceed
        ``max(max_roughness_px, 2 × median sigma_px)`` (the second term keeps the test
        above the random matching error of noisy images). Near the sharp flanks of
        extrusions the parallax is not affine within any subset and heights come out biased
        by tens of nm; these points are dropped here (they remain reachable with
        :func:`refine_correspondences`). None keeps them.
    dense_init : bool
        Initial guesses from dense optical flow (step 4); False uses the sparse prior.
    wide_search_px : int
        ZNCC search radius where the flow is uncertain.
    min_texture_snr : float
        Texture threshold of step 3 (0 matches every point).
    multiview_px : float or None
        With V >= 3 views: points whose rank-2 residual (RMS over views, pixels) exceeds
        ``max(median + 4 × 1.4826 MAD, multiview_px)`` of the accepted points are marked
        invalid. None skips the test.
    max_iter, tol_px
        IC-GN iteration limit and convergence tolerance (pixels).
    backward_px : float or None
        Forward–backward check: each accepted point is matched back from the view to the
        reference (IC-GN started at the reference position with the inverse warp) and
        marked invalid when it does not return to within ``backward_px`` pixels (a second
        IC-GN pass over the accepted points; None skips it). It removes points whose match
        depends on the direction, e.g. subsets straddling occlusions or parallax edges.
    max_features : int
        At most this many sparse features per view (the strongest; they only fix the
        global affine and, without ``dense_init``, the parallax prior).
    dense_prior_below : float
        When fewer than this fraction of the feature matches fit the global affine map
        (tall objects: hundreds of pixels of parallax varying over the view), the optical
        flow starts from a dense map interpolated from the consistent matches
        (:func:`_dense_prior`) instead of the affine. 0 disables it.
    target_sigma_px, max_half_window : float or None, int
        Size each grid point's subset by its information, from ``half_window`` up to
        ``max_half_window`` (see :func:`refine_correspondences`); the forward–backward
        check uses each point's own subset. None: one fixed ``half_window``.

    Returns
    -------
    MatchResult
        All grid points, ``kind = "auto"``, with ``valid`` and ``reason``; use
        ``result.only_valid()`` to keep the accepted ones.

    Raises
    ------
    ImageError
        On bad images.
    GeometryError
        If no global affine map is found or the grid is empty.
    """
    ims = _check_images(images)
    v = len(ims)
    ref = _check_ref_view(ref_view, v)
    if detector not in ("sift", "shi-tomasi", "both"):
        raise SemlabError(f"detector must be 'sift', 'shi-tomasi' or 'both', got {detector!r}")
    if not 0 < ratio < 1:
        raise SemlabError(f"ratio must be in (0, 1), got {ratio!r}")
    if not spacing_px > 0:
        raise SemlabError(f"spacing_px must be > 0, got {spacing_px!r}")
    if smooth_sigma_px is not None and not smooth_sigma_px >= 0:
        raise SemlabError(f"smooth_sigma_px must be None or >= 0, got {smooth_sigma_px!r}")
    if backward_px is not None and not backward_px > 0:
        raise SemlabError(f"backward_px must be None or > 0 pixels, got {backward_px!r}")
    if not min_texture_snr >= 0:
        raise SemlabError(f"min_texture_snr must be >= 0, got {min_texture_snr!r}")
    hgt, wid = ims[0].shape
    margin = half_window + search_px + 3
    xs = np.arange(margin, wid - margin, spacing_px, dtype=float)
    ys = np.arange(margin, hgt - margin, spacing_px, dtype=float)
    if len(xs) == 0 or len(ys) == 0:
        raise GeometryError(f"images of {wid}×{hgt} px are too small for half_window="
                            f"{half_window} and search_px={search_px}")
    gx, gy = np.meshgrid(xs, ys)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    gidx = np.arange(len(grid))
    if max_points is not None and len(grid) > max_points:
        rng = np.random.default_rng(seed)
        gidx = np.sort(rng.choice(len(grid), int(max_points), replace=False))
        grid = grid[gidx]
    n = len(grid)

    out = np.full((n, v, 2), np.nan)
    out[:, ref] = grid
    zn = np.ones((n, v))
    zn[:, [j for j in range(v) if j != ref]] = -1.0
    sig_x = np.zeros((n, v))
    valid = np.ones(n, bool)
    reason = np.full(n, "", dtype=object)
    side = np.zeros(n, int)

    noise0 = image_noise_sigma(ims[ref])   # white-noise estimate, regulariser of the flow
    eps = max(noise0, 1e-3 * float(np.ptp(ims[ref])) + 1e-12)
    sub_std = _subset_std(ims[ref], half_window, grid)
    work = None

    ref8 = _to_uint8(ims[ref])
    ref_coef = None if smooth_sigma_px is None else prefilter_image(ims[ref], smooth_sigma_px)
    resid = {}
    curved = set()            # views matched with the dense prior (tall objects)
    ref_cache = {}
    fwd_state = {}
    for j in range(v):
        if j == ref:
            continue
        src, dst = match_features(ref8, _to_uint8(ims[j]), ratio=ratio, detector=detector,
                                  n_max=max_features, cache=ref_cache)
        if len(src) < 6:
            raise GeometryError(f"only {len(src)} feature matches between views {ref} and {j}; "
                                "the views do not overlap or have too little texture")
        M, inl = _robust_affine(src, dst, 3.0, seed)
        res = dst[inl] - _apply_affine(M, src[inl])
        # parallax direction = principal direction of the inlier residuals
        rc = res - np.median(res, axis=0)
        _, _, vt = np.linalg.svd(rc, full_matrices=False)
        e = vt[0] * np.sign(vt[0][0] if abs(vt[0][0]) > 1e-12 else 1.0)
        eperp = np.array([-e[1], e[0]])
        keep = np.abs(rc @ eperp) < 1.0
        s_src = src[inl][keep]
        if len(s_src) < 6:
            raise GeometryError(f"too few consistent feature matches between views {ref} and {j}")
        s_dst = dst[inl][keep]
        M = fit_affine(s_src, s_dst)
        s_res = s_dst - _apply_affine(M, s_src)
        L = M[:, :2] - np.eye(2)
        grad = np.array([0, L[0, 0], L[0, 1], 0, L[1, 0], L[1, 1]])
        # no global affine describes the pair when most matches disagree with it (a tall
        # object): then the flow starts from a dense map interpolated from the matches
        prior = M
        if dense_init and inl.mean() < dense_prior_below:
            try:
                prior = _dense_prior(src, dst, ims[ref].shape, half_window)
                curved.add(j)
            except GeometryError:
                prior = M
        if dense_init:
            warped, fwd, bwd = _flow_field(ims[ref], ims[j], prior, half_window, eps)
        if work is None:
            # texture test on the reference view, with the noise seen between the views
            noise = _aligned_noise(ims[ref], warped, fwd, half_window) if dense_init \
                else noise0
            contrast = np.sqrt(np.maximum(sub_std ** 2 - noise ** 2, 0.0))
            textured = contrast >= min_texture_snr * noise
            for i in np.flatnonzero(~textured):
                reason[i] = (f"low texture: subset contrast {contrast[i]:.2f} < "
                             f"min_texture_snr × noise = {min_texture_snr * noise:.2f} "
                             "(featureless background?)")
            valid &= textured
            work = np.flatnonzero(textured)
            gw = grid[work]
        nw = len(work)
        if nw == 0:       # every point flagged "low texture"
            break
        if dense_init:
            guess0, init_w, fb = _flow_guess(prior, fwd, bwd, gw, half_window)
            # parallax direction from the dense field where the flow is reliable
            d = guess0 - _apply_affine(M, gw)
            rel = fb < 1.0
            if rel.sum() >= 6:
                dc = d[rel] - np.median(d[rel], axis=0)
                _, _, vt = np.linalg.svd(dc, full_matrices=False)
                e = vt[0] * np.sign(vt[0][0] if abs(vt[0][0]) > 1e-12 else 1.0)
                eperp = np.array([-e[1], e[0]])
        else:
            # smooth parallax field from the sparse inliers (median of nearest residuals)
            kk = min(8, len(s_src))
            _, nb = cKDTree(s_src).query(gw, k=kk)
            par = np.median(s_res[nb.reshape(nw, kk)] @ e, axis=1)
            guess0 = _apply_affine(M, gw) + par[:, None] * e
            init_w = np.broadcast_to(grad, (nw, 6))
            fb = np.zeros(nw)
        guess = np.full((nw, 2), np.nan)
        near = fb <= 1.0
        for sel, rad in ((near, search_px), (~near, max(search_px, wide_search_px))):
            if sel.any():
                guess[sel], _ = zncc_match(ims[ref], ims[j], gw[sel], guess0[sel],
                                           half_window=half_window, search_px=rad)
        if smooth_sigma_px is None:
            smooth_sigma_px = _choose_smoothing(ims[ref], ims[j], gw, guess, guess0, init_w,
                                                half_window, min_zncc, seed)
            ref_coef = prefilter_image(ims[ref], smooth_sigma_px)
        cur_coef = prefilter_image(ims[j], smooth_sigma_px)
        r, hw_j = _grid_icgn(ims[ref], ims[j], gw, np.where(np.isfinite(guess), guess, guess0),
                             half_window, "affine", init_w, smooth_sigma_px, ref_coef,
                             cur_coef, target_sigma_px, max_half_window, progress=progress,
                             max_iter=max_iter, tol_px=tol_px)
        side[work] = np.maximum(side[work], np.where(r.converged, 2 * hw_j + 1, 0))
        ok_j = r.converged & (r.zncc >= min_zncc)
        pts_j, sig_j = r.pts, r.sigma_px[:, 0]
        if band_aware and ok_j.sum() >= 6:
            par = np.where(ok_j, (r.pts - _apply_affine(M, gw)) @ e, np.nan)
            ang, _, _ = _band_orientation(gw, gw, par, 2.0 * half_window)
            sel = np.flatnonzero(ok_j)
            warp_sel = np.where(np.isfinite(r.warp[sel]), r.warp[sel], init_w[sel])
            o_pts, o_sig, o_zn = _oriented_refine(
                ims[ref], ims[j], gw[sel], r.pts[sel], warp_sel, ang[sel], 2 * half_window,
                band_half_width_px, smooth_sigma_px, ref_coef, cur_coef)
            c_pts, c_sig, _ = _combine(r.pts[sel], sig_j[sel], o_pts, o_sig, o_zn, min_zncc,
                                       kappa)
            pts_j, sig_j = pts_j.copy(), sig_j.copy()
            pts_j[sel], sig_j[sel] = c_pts, c_sig
        out[work, j] = pts_j
        zn[work, j] = r.zncc
        sig_x[work, j] = sig_j
        for k in np.flatnonzero(~ok_j):
            i = work[k]
            if not r.converged[k]:
                why = r.reason[k]
            else:
                why = f"zncc {r.zncc[k]:.2f} < min_zncc {min_zncc}"
            if valid[i]:
                reason[i] = f"view {j}: {why}"
        valid[work[~ok_j]] = False
        rr = out[:, j] - _apply_affine(M, grid)
        resid[j] = (rr @ e, rr @ eperp)
        if backward_px is not None:
            warp_full = np.full((n, 6), np.nan)
            warp_full[work] = np.where(np.isfinite(r.warp), r.warp, init_w)
            hw_full = np.full(n, int(half_window))
            hw_full[work] = np.where(hw_j > 0, hw_j, half_window)
            fwd_state[j] = (cur_coef, warp_full, hw_full)

    # local consistency of parallax and cross-parallax against grid neighbours (twice)
    for _ in range(2):
        idx = np.flatnonzero(valid)
        if len(idx) < 4:
            break
        for j, (pa, pe) in resid.items():
            for name, val in (("parallax", pa), ("cross-parallax", pe)):
                out_l = _local_outliers(grid[idx], val[idx], 8, consistency_px)
                for i in idx[out_l]:
                    if valid[i]:
                        reason[i] = f"view {j}: {name} inconsistent with its neighbours"
                valid[idx[out_l]] = False
    others = [j for j in range(v) if j != ref]
    sigma = np.sqrt(np.mean(sig_x[:, others] ** 2, axis=1))
    if max_roughness_px is not None and valid.sum() >= 12:
        idx = np.flatnonzero(valid)
        thr = max(max_roughness_px, 2.0 * float(np.median(sigma[idx])))
        for j, (pa, _) in resid.items():
            # with the dense prior (a tall object) the parallax is curved on the scale of the
            # neighbourhood: test against local quadrics, which still reject steps
            _, rough = _parallax_gradients(grid[idx], pa[idx], return_residual=True,
                                           quadratic=j in curved)
            bad = rough > thr
            for i, rr in zip(idx[bad], rough[bad]):
                if valid[i]:
                    reason[i] = (f"view {j}: parallax not locally planar (plane RMS {rr:.2f} px "
                                 f"> {thr:.2f} px: steep flank)")
            valid[idx[bad]] = False
    if backward_px is not None:
        for j, (coef_j, warp_j, hw_full) in fwd_state.items():
            idx = np.flatnonzero(valid)
            if len(idx) == 0:
                break
            fb_d = np.full(len(idx), np.nan)
            for h in np.unique(hw_full[idx]):      # the backward match uses the same subset
                k = hw_full[idx] == h
                fb_d[k] = _backward_distance(ims[j], ims[ref], out[idx[k], j], grid[idx[k]],
                                             warp_j[idx[k]], int(h), smooth_sigma_px, coef_j,
                                             ref_coef, max_iter, tol_px)
            bad = ~(fb_d <= backward_px)
            for i, dd in zip(idx[bad], fb_d[bad]):
                reason[i] = (f"view {j}: forward–backward mismatch "
                             + ("(backward match failed)" if np.isnan(dd) else
                                f"{dd:.2f} px > backward_px {backward_px}"))
            valid[idx[bad]] = False
    if multiview_px is not None and v >= 3 and valid.sum() >= 8:
        mres, _ = _multiview_residual(out, ref, valid)
        r_in = mres[valid]
        thr = max(np.median(r_in) + 4 * 1.4826 * np.median(np.abs(r_in - np.median(r_in))),
                  multiview_px)
        bad = valid & ~(mres <= thr)
        for i in np.flatnonzero(bad):
            reason[i] = (f"views inconsistent: x coordinates off the rank-2 tilt-series model "
                         f"by {mres[i]:.2f} px > {thr:.2f} px")
        valid &= ~bad
    sigma[~valid] = np.nan
    if progress:
        from tqdm.auto import tqdm
        tqdm.write(f"auto_match: {valid.sum()} of {n} grid points accepted")
    return MatchResult(pts=out, zncc=zn, valid=valid, sigma_px=sigma, reason=reason.astype(str),
                       ref_view=ref, kind=np.full(n, "auto"), source_index=gidx,
                       subset_px=side)


# --------------------------------------------------------------------------- merge
def merge_matches(a, b, min_separation_px=3):
    """Merge two :class:`MatchResult` (e.g. refined clicks and automatic matches).

    Points whose reference-view positions are closer than ``min_separation_px`` are
    duplicates; of each group the best one is kept: valid before invalid, then the smaller
    ``sigma_px``, then the higher mean ZNCC (ties keep ``a``'s point).

    Parameters
    ----------
    a, b : MatchResult
        Same number of views and the same reference view.
    min_separation_px : float
        Duplicate distance in the reference view, pixels.

    Returns
    -------
    MatchResult
        ``a``'s kept points first, then ``b``'s, each in their original order.

    Raises
    ------
    GeometryError
        If the results have different numbers of views or reference views.
    """
    for r, name in ((a, "a"), (b, "b")):
        if not isinstance(r, MatchResult):
            raise SemlabError(f"{name} must be a MatchResult, got {type(r).__name__}")
    if a.n_views != b.n_views:
        raise GeometryError(f"cannot merge results with {a.n_views} and {b.n_views} views")
    if a.ref_view != b.ref_view:
        raise GeometryError(f"cannot merge results with reference views {a.ref_view} and "
                            f"{b.ref_view}")
    pts = np.concatenate([a.pts, b.pts])
    n = len(pts)
    if n == 0:
        return a
    valid = np.concatenate([a.valid, b.valid])
    sig = np.concatenate([a.sigma_px, b.sigma_px])
    zmean = np.concatenate([a.zncc, b.zncc]).mean(1)
    origin = np.r_[np.zeros(len(a)), np.ones(len(b))]
    order = np.lexsort((origin, -zmean, np.where(np.isfinite(sig), sig, np.inf), ~valid))
    xy = pts[:, a.ref_view]
    tree = cKDTree(xy)
    taken = np.zeros(n, bool)
    keep = np.zeros(n, bool)
    for i in order:            # greedy non-maximum suppression by quality
        if taken[i]:
            continue
        keep[i] = True
        taken[tree.query_ball_point(xy[i], r=min_separation_px)] = True
    ka, kb = keep[:len(a)], keep[len(a):]
    return MatchResult(pts=np.concatenate([a.pts[ka], b.pts[kb]]),
                       zncc=np.concatenate([a.zncc[ka], b.zncc[kb]]),
                       valid=np.concatenate([a.valid[ka], b.valid[kb]]),
                       sigma_px=np.concatenate([a.sigma_px[ka], b.sigma_px[kb]]),
                       reason=np.concatenate([a.reason[ka], b.reason[kb]]),
                       ref_view=a.ref_view,
                       kind=np.concatenate([a.kind[ka], b.kind[kb]]),
                       source_index=np.concatenate([a.source_index[ka], b.source_index[kb]]),
                       subset_px=_merge_subset_px(a, ka, b, kb))


def _merge_subset_px(a, ka, b, kb):
    if a.subset_px is None and b.subset_px is None:
        return None
    def side(r, k):
        return np.full(k.sum(), -1) if r.subset_px is None else r.subset_px[k]
    return np.concatenate([side(a, ka), side(b, kb)])
