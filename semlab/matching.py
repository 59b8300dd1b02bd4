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
  a global affine RANSAC, then a dense grid refined by IC-GN with a robust outlier filter.
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
    """

    pts: np.ndarray
    zncc: np.ndarray
    valid: np.ndarray
    sigma_px: np.ndarray
    reason: np.ndarray
    ref_view: int
    kind: np.ndarray
    source_index: np.ndarray

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
                       source_index=self.source_index[m])

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
def _parallax_gradients(xy, par, k=12, return_residual=False):
    """Gradient of a scattered parallax field by local least-squares planes (k neighbours).

    Returns (n, 2) gradients, and with ``return_residual`` also the RMS residual (n,) of
    each local plane."""
    n = len(xy)
    kk = min(k, n)
    _, nb = cKDTree(xy).query(xy, k=kk)
    nb = nb.reshape(n, kk)
    d = xy[nb] - xy[:, None, :]                                    # (n, k, 2)
    X = np.concatenate([np.ones((n, kk, 1)), d], axis=2)          # (n, k, 3)
    y = par[nb]
    XtX = np.einsum("nki,nkj->nij", X, X) + 1e-9 * np.eye(3)
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
    """IC-GN with thin rectangular subsets along the band direction of each point."""
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
        r = icgn_refine(ref_img, img, pts_ref[sel], guess[sel], half_window=half_length,
                        init_warp=grad, smooth_sigma_px=smooth_sigma_px, subset_offsets=off,
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
                           warp="affine", min_zncc=0.8, *, smooth_sigma_px=0.0,
                           band_aware=True, band_half_width_px=3, kappa=1.0,
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
    smooth_sigma_px : float
        Gaussian pre-smoothing of the views for IC-GN (see
        :func:`semlab.subset.icgn_refine`); reduces noise-induced bias on noisy images.
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
    pr = p[:, ref]
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
        r = icgn_refine(ims[ref], ims[j], pr, np.where(np.isfinite(guess), guess, p[:, j]),
                        half_window=half_window, warp=warp, init_warp=grad,
                        smooth_sigma_px=smooth_sigma_px, ref_prefiltered=ref_coef,
                        cur_prefiltered=cur_coef, progress=progress)
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
                       kind=np.full(n, "click"), source_index=np.arange(n))


# --------------------------------------------------------------------------- automatic
def _to_uint8(img):
    lo, hi = np.percentile(img, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    return np.clip((img - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)


def _features(img8, detector, n_max=20000):
    import cv2

    sift = cv2.SIFT_create(nfeatures=n_max)
    if detector == "sift":
        kp, des = sift.detectAndCompute(img8, None)
    else:   # Shi–Tomasi corners described by SIFT
        pts = cv2.goodFeaturesToTrack(img8, maxCorners=n_max, qualityLevel=0.01, minDistance=4)
        if pts is None:
            return np.zeros((0, 2)), None
        kp = [cv2.KeyPoint(float(x), float(y), 8.0) for x, y in pts.reshape(-1, 2)]
        kp, des = sift.compute(img8, kp)
    xy = np.array([k.pt for k in kp], dtype=np.float64).reshape(-1, 2)
    return xy, des


def _sparse_matches(img_ref8, img8, detector, ratio):
    """Ratio-tested descriptor matches (N, 2) ref positions and (N, 2) positions in img."""
    import cv2

    dets = ["sift", "shi-tomasi"] if detector == "both" else [detector]
    src, dst = [], []
    for d in dets:
        xa, da = _features(img_ref8, d)
        xb, db = _features(img8, d)
        if da is None or db is None or len(xa) < 2 or len(xb) < 2:
            continue
        knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(da, db, k=2)
        for m in knn:
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                src.append(xa[m[0].queryIdx])
                dst.append(xb[m[0].trainIdx])
    return np.array(src).reshape(-1, 2), np.array(dst).reshape(-1, 2)


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


def auto_match(images, ref_view=0, spacing_px=8, detector="sift", ratio=0.8, half_window=10,
               min_zncc=0.9, max_points=None, seed=0, progress=True, *, search_px=3,
               smooth_sigma_px=0.0, consistency_px=0.3, band_aware=True,
               band_half_width_px=3, kappa=1.0, max_roughness_px=0.08):
    """Automatic dense correspondences between SEM views.

    1. Sparse features (SIFT, Lowe 2004 IJCV 60(2); or Shi–Tomasi corners 1994 described by
       SIFT; or both) matched with Lowe's ratio test.
    2. A global 2D affine map per view by RANSAC (``cv2.estimateAffine2D``; Fischler &
       Bolles 1981), threshold 3 px (it must pass the parallax of the heights), then a second
       test on the residual across the parallax direction (the affine epipolar constraint,
       Hartley & Zisserman 2nd ed. section 14.2): the parallax direction is the principal
       direction of the inlier residuals and matches more than 1 px off it are dropped.
       The affine fundamental matrix alone is nearly degenerate with ≤ 2 px of parallax and
       accepts mismatches along the band direction, hence the dense step:
    3. A regular grid (``spacing_px``) in the reference view; initial guesses from the
       global affine plus a smooth parallax (median of the residuals of the 8 nearest sparse
       inliers), ZNCC search ``±search_px``, IC-GN refinement.
    4. Band-aware refinement (``band_aware``): each point is matched again with a thin
       subset along the local direction of the parallax bands (structure tensor of the
       dense parallax field) and that estimate is kept where the square subset disagrees
       with it (see :func:`refine_correspondences`).
    5. Outlier filter: convergence, ``zncc >= min_zncc`` in every view, local consistency
       of the parallax and cross-parallax residuals against the 8 nearest grid neighbours
       (median ± max(4 × 1.4826 MAD, ``consistency_px``)), repeated once, and a local
       planarity test of the parallax (``max_roughness_px``).

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
    smooth_sigma_px : float
        Gaussian pre-smoothing for IC-GN (see :func:`semlab.subset.icgn_refine`).
    consistency_px : float
        Floor of the local-consistency threshold, pixels.
    band_aware, band_half_width_px, kappa
        Band-aligned thin subsets near parallax edges, as in
        :func:`refine_correspondences`.
    max_roughness_px : float or None
        Points where the parallax field is not locally planar are marked invalid: the RMS
        residual (pixels) of a least-squares plane through the parallax of the point and
        its 11 nearest accepted neighbours (about ±1.5 grid spacings) must not exceed this.
        Near the sharp flanks of extrusions the parallax is not affine within any subset and
        heights come out biased by tens of nm; these points are dropped here (they remain
        reachable with :func:`refine_correspondences`). None keeps them.

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

    ref8 = _to_uint8(ims[ref])
    ref_coef = prefilter_image(ims[ref], smooth_sigma_px)
    out = np.full((n, v, 2), np.nan)
    out[:, ref] = grid
    zn = np.ones((n, v))
    sig_x = np.zeros((n, v))
    valid = np.ones(n, bool)
    reason = np.full(n, "", dtype=object)
    resid = {}
    for j in range(v):
        if j == ref:
            continue
        src, dst = _sparse_matches(ref8, _to_uint8(ims[j]), detector, ratio)
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
        s_src, s_res = src[inl][keep], res[keep]
        if len(s_src) < 6:
            raise GeometryError(f"too few consistent feature matches between views {ref} and {j}")
        s_dst = dst[inl][keep]
        M = fit_affine(s_src, s_dst)
        s_res = s_dst - _apply_affine(M, s_src)
        # smooth parallax field from the sparse inliers (median of nearest residuals)
        kk = min(8, len(s_src))
        _, nb = cKDTree(s_src).query(grid, k=kk)
        nb = nb.reshape(n, kk)
        par = np.median(s_res[nb] @ e, axis=1)
        guess0 = _apply_affine(M, grid) + par[:, None] * e
        L = M[:, :2] - np.eye(2)
        grad = np.array([0, L[0, 0], L[0, 1], 0, L[1, 0], L[1, 1]])
        guess, _ = zncc_match(ims[ref], ims[j], grid, guess0, half_window=half_window,
                              search_px=search_px)
        cur_coef = prefilter_image(ims[j], smooth_sigma_px)
        r = icgn_refine(ims[ref], ims[j], grid, np.where(np.isfinite(guess), guess, guess0),
                        half_window=half_window, init_warp=grad, smooth_sigma_px=smooth_sigma_px,
                        ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, progress=progress)
        ok_j = r.converged & (r.zncc >= min_zncc)
        pts_j, sig_j = r.pts, r.sigma_px[:, 0]
        if band_aware and ok_j.sum() >= 6:
            par = np.where(ok_j, (r.pts - _apply_affine(M, grid)) @ e, np.nan)
            ang, _, _ = _band_orientation(grid, grid, par, 2.0 * half_window)
            sel = np.flatnonzero(ok_j)
            o_pts, o_sig, o_zn = _oriented_refine(
                ims[ref], ims[j], grid[sel], r.pts[sel], grad, ang[sel], 2 * half_window,
                band_half_width_px, smooth_sigma_px, ref_coef, cur_coef)
            c_pts, c_sig, _ = _combine(r.pts[sel], sig_j[sel], o_pts, o_sig, o_zn, min_zncc,
                                       kappa)
            pts_j, sig_j = pts_j.copy(), sig_j.copy()
            pts_j[sel], sig_j[sel] = c_pts, c_sig
        out[:, j] = pts_j
        zn[:, j] = r.zncc
        sig_x[:, j] = sig_j
        bad = ~r.converged
        reason[bad] = [f"view {j}: {w}" for w in r.reason[bad]]
        low = r.converged & (r.zncc < min_zncc)
        reason[low] = [f"view {j}: zncc {z:.2f} < min_zncc {min_zncc}" for z in r.zncc[low]]
        valid &= ok_j
        rr = pts_j - _apply_affine(M, grid)
        resid[j] = (rr @ e, rr @ eperp)

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
    if max_roughness_px is not None and valid.sum() >= 12:
        idx = np.flatnonzero(valid)
        for j, (pa, _) in resid.items():
            _, rough = _parallax_gradients(grid[idx], pa[idx], return_residual=True)
            bad = rough > max_roughness_px
            for i, rr in zip(idx[bad], rough[bad]):
                if valid[i]:
                    reason[i] = (f"view {j}: parallax not locally planar (plane RMS {rr:.2f} px "
                                 f"> max_roughness_px {max_roughness_px}: steep flank)")
            valid[idx[bad]] = False
    others = [j for j in range(v) if j != ref]
    sigma = np.sqrt(np.mean(sig_x[:, others] ** 2, axis=1))
    sigma[~valid] = np.nan
    if progress:
        from tqdm.auto import tqdm
        tqdm.write(f"auto_match: {valid.sum()} of {n} grid points accepted")
    return MatchResult(pts=out, zncc=zn, valid=valid, sigma_px=sigma, reason=reason.astype(str),
                       ref_view=ref, kind=np.full(n, "auto"), source_index=gidx)


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
                       source_index=np.concatenate([a.source_index[ka], b.source_index[kb]]))
