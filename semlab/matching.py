"""Stereo correspondences between SEM views of the same surface.

Two or more end-state views taken at stage tilts (e.g. ±5°) differ by a near-identity
affine map (x scaling ``cos θ1 / cos θ0``, small shifts) plus a local parallax along the
epipolar direction (x for a tilt about the image y axis) proportional to the height
(``u = cx + (x cos θ + z sin θ) / s``). At ±5° and 0.03 µm/px one pixel of parallax is
about 0.17 µm of height, so the 8 nm height target needs ~0.05 px matching accuracy:
sub-pixel subset matching (:mod:`semlab.subset`, ZNCC search then IC-GN with ZNSSD).

- :func:`refine_correspondences` (in :mod:`semlab.refine`) refines hand clicks: the
  reference-view click defines the material point; the clicks in the other views are only
  starting guesses (~0.5 px error).
- :func:`auto_match` finds correspondences automatically: SIFT features, Lowe's ratio test,
  a global affine RANSAC, dense optical flow for the initial guess (parallax of hundreds of
  pixels on tall objects), then a dense grid refined by IC-GN with robust outlier filters
  (texture, neighbours, forward–backward, multi-view rank 2).
- :func:`merge_matches` merges two results (e.g. clicks and automatic matches).

:func:`auto_match` is a chain of named stages, each in its own module: the prior
(:mod:`semlab.match_prior`: features, global affine, dense flow), grid matching
(:func:`semlab.adaptive.adaptive_icgn` or fixed subsets, :mod:`semlab.match_band`), and
the filters (:mod:`semlab.match_filters`); all its parameters are one frozen
:class:`AutoMatchParams`, recorded in the result.

Conventions: images are 2D arrays indexed ``[row, col]``; points are ``(x, y)`` pixels,
x right, y down, origin at the centre of the top-left pixel. ``pts`` arrays are
``(N, V, 2)``: N points seen in V views.
"""

from __future__ import annotations

from dataclasses import astuple, dataclass, fields, replace

import numpy as np
from scipy.spatial import cKDTree

from .adaptive import _grid_icgn
from .errors import GeometryError, SemlabError
from .match_result import MatchResult, _check_images, _check_ref_view, merge_matches
from .match_sigma import aposteriori_sigma, model_error_from_fit
from .match_band import _band_orientation, _combine, _oriented_refine
from .match_epipolar import epipolar_refine
from .match_filters import (_backward_distance, _local_outliers, _multiview_residual,
                            _parallax_gradients)
from .match_prior import (_aligned_noise, _apply_affine, _dense_prior, _field_jacobian,  # noqa: F401
                          _highpass,
                          _flow_field, _flow_guess, _norm8, _robust_affine, _subset_std,
                          _to_uint8, fit_affine)
from .noise import image_noise_sigma
from .refine import refine_correspondences
from .registration import match_features
from .subset import icgn_refine, prefilter_image, zncc_match

__all__ = ["MatchResult", "AutoMatchParams", "refine_correspondences", "auto_match",
           "merge_matches", "fit_affine"]


# --------------------------------------------------------------------------- automatic
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


@dataclass(frozen=True)
class AutoMatchParams:
    """Every parameter of :func:`auto_match`, in one recorded object.

    The fields are the keyword arguments of :func:`auto_match` (documented there), with
    their defaults; ``dataclasses.asdict(params)`` is what a results file records.
    Stages: prior (``detector``, ``ratio``, ``max_features``, ``dense_init``,
    ``dense_prior_below``, ``wide_search_px``), grid matching (``spacing_px``,
    ``half_window``, ``search_px``, ``smooth_sigma_px``, ``max_iter``, ``tol_px``,
    ``target_sigma_px``, ``max_half_window``, ``band_aware``, ``band_half_width_px``,
    ``kappa``, ``epipolar``), filters (``min_texture_snr``, ``min_zncc``, ``consistency_px``,
    ``max_roughness_px``, ``backward_px``, ``multiview_px``).
    """

    ref_view: int = 0
    spacing_px: float = 8
    detector: str = "sift"
    ratio: float = 0.8
    half_window: int = 10
    min_zncc: float = 0.9
    max_points: int = None
    seed: int = 0
    search_px: int = 3
    smooth_sigma_px: float = None
    consistency_px: float = 0.3
    band_aware: bool = True
    band_half_width_px: int = 3
    kappa: float = 1.0
    max_roughness_px: float = 0.08
    dense_init: bool = True
    wide_search_px: int = 10
    min_texture_snr: float = 1.0
    multiview_px: float = 0.3
    max_iter: int = 60
    tol_px: float = 1e-3
    max_features: int = 5000
    backward_px: float = 0.1
    dense_prior_below: float = 0.5
    target_sigma_px: float = None
    max_half_window: int = 28
    epipolar: bool = True


def auto_match(images, params=None, *, progress=True, features=None, **overrides):
    """Automatic dense correspondences between SEM views.

    Called as ``auto_match(images, params)`` with an :class:`AutoMatchParams`, or with
    its fields as keywords (``auto_match(images, spacing_px=6)``), or both (the keywords
    override ``params``). The parameters used are in ``result.params``.

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
       aligned by the flow of step 4 (whatever its spectrum), locally (the 64×64 tile of
       each point: SEM noise depends on the signal, and relief the flow misses inflates a
       whole-view estimate), with the subset contrast taken on the same high-passed image
       (minus a Gaussian of ``2 half_window``: smooth shading is not texture), or without
       ``dense_init`` by Immerkær's white-noise estimator.
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
    6b. Epipolar stage (``epipolar``): points the 2D subsets failed on (diverged, not
       converged, ZNCC below ``min_zncc``) are matched along the parallax direction only
       (:func:`semlab.match_epipolar.epipolar_refine`: the cross-parallax position held
       on the global affine map's epipolar line, the shift searched within
       ``±max(search_px, wide_search_px)`` and refined with its gradient). Texture that
       constrains only the parallax direction (machined grooves, scratches across it)
       makes the 2D Hessian nearly singular; the shift stereo needs is still defined. On
       ``pollen_pot1`` the grooved substrate is matched this way.
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
    features : dict, optional
        ``{j: (src, dst)}``: feature matches ``(M, 2)`` of ``(x, y)`` pixels between the
        reference view and view ``j`` to use instead of detecting them (stage 1); the
        tiles of :func:`semlab.tiled_stereo.tiled_auto_match` share the whole views'.
    search_px : int
        ZNCC search radius around the predicted position.
    smooth_sigma_px : float or None
        Gaussian pre-smoothing for IC-GN (see :func:`semlab.subset.icgn_refine`). None
        (default) chooses it on the first view pair: 0 when unsmoothed IC-GN converges with
        ``zncc >= min_zncc`` on at least half of 200 random textured grid points, else
        1.0 px (noisy real SEM images, where the unsmoothed cost is too rough).
    consistency_px : float or None
        Floor of the local-consistency threshold, pixels. None skips the test. Its
        evidence is weak: on the real-texture (FEI) 192×256 cells of
        ``benchmarks/accuracy_matrix.py`` (seeds 0 / 1 / 2) it keeps 185 / 183 / 170
        points against 174 / 181 / 160 without it (the outliers it removes otherwise spoil
        their neighbours' roughness test), at a height RMSE of 25.9 / 22.5 / 35.5 nm
        against 28.2 / 26.0 / 31.6 nm; on small synthetic scenes it changed nothing.
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
        :func:`refine_correspondences`). Where most of the view is rough (its median
        roughness above the threshold: a pollen grain's reticulum), the threshold rises to
        that median plus 4 × 1.4826 MAD, so that only roughness standing out of the
        surface's own is rejected (steep flanks are a minority). None keeps them.
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
        IC-GN pass over the accepted points; None skips it; points of the epipolar stage
        are matched back along the epipolar direction). A threshold growing with each
        point's σ (``max(backward_px, 3√2 σ)``) tripled the accepted grain points of
        ``pollen_pot1`` but let worse points in on the accuracy matrix (quick real:fei
        cell: 58 % coverage at 0.99× DeepFlow's RMSE instead of 37 % at 0.80×). It removes points whose match
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
    epipolar : bool
        Run the epipolar stage 6b (the forward–backward check of its points is along the
        epipolar direction too).

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
    params = _auto_params(params, overrides)
    (ref_view, spacing_px, detector, ratio, half_window, min_zncc, max_points, seed, search_px,
     smooth_sigma_px, consistency_px, band_aware, band_half_width_px, kappa, max_roughness_px,
     dense_init, wide_search_px, min_texture_snr, multiview_px, max_iter, tol_px, max_features,
     backward_px, dense_prior_below, target_sigma_px, max_half_window,
     epipolar) = astuple(params)
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
    sig_ap = np.zeros((n, v))     # sig_x with the a posteriori variance factor
    valid = np.ones(n, bool)
    reason = np.full(n, "", dtype=object)
    side = np.zeros(n, int)
    epi = np.zeros((n, v), bool)     # matched along the epipolar direction only

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
        if features is not None and j in features:       # given (tiles: the whole view's)
            src, dst = (np.asarray(a, float) for a in features[j])
        else:
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
            noise = _aligned_noise(ims[ref], warped, fwd, half_window, pts=grid) \
                if dense_init else noise0
            if dense_init:   # contrast of the image the noise is measured on (high-passed)
                sub_std = _subset_std(_highpass(ims[ref], half_window), half_window, grid)
            contrast = np.sqrt(np.maximum(sub_std ** 2 - noise ** 2, 0.0))
            textured = contrast >= min_texture_snr * noise
            noise_i = np.broadcast_to(noise, contrast.shape)
            for i in np.flatnonzero(~textured):
                reason[i] = (f"low texture: subset contrast {contrast[i]:.2f} < "
                             f"min_texture_snr × noise = {min_texture_snr * noise_i[i]:.2f} "
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
        pts_j, sig_j, rr_j = r.pts, r.sigma_px[:, 0], r.residual_ratio
        if band_aware and ok_j.sum() >= 6:
            par = np.where(ok_j, (r.pts - _apply_affine(M, gw)) @ e, np.nan)
            ang, _, _ = _band_orientation(gw, gw, par, 2.0 * half_window)
            sel = np.flatnonzero(ok_j)
            warp_sel = np.where(np.isfinite(r.warp[sel]), r.warp[sel], init_w[sel])
            o_pts, o_sig, o_zn, o_rr = _oriented_refine(
                ims[ref], ims[j], gw[sel], r.pts[sel], warp_sel, ang[sel], 2 * half_window,
                band_half_width_px, smooth_sigma_px, ref_coef, cur_coef,
                return_residual_ratio=True)
            c_pts, c_sig, use = _combine(r.pts[sel], sig_j[sel], o_pts, o_sig, o_zn, min_zncc,
                                         kappa)
            pts_j, sig_j, rr_j = pts_j.copy(), sig_j.copy(), rr_j.copy()
            pts_j[sel], sig_j[sel] = c_pts, c_sig
            rr_j[sel] = np.where(use, o_rr, rr_j[sel])
        zn_j = r.zncc
        epi_j = np.zeros(nw, bool)
        epi_coef = None
        if epipolar and not ok_j.all():
            pts_j, sig_j, rr_j, zn_j, ok_j, epi_j, r, epi_coef = _epipolar_stage(
                ims[ref], ims[j], gw, M, e, np.where(np.isfinite(guess), guess, guess0),
                pts_j, sig_j, rr_j, ok_j, r, half_window, grad, init_w, min_zncc,
                smooth_sigma_px, ref_coef, cur_coef, max_iter, tol_px,
                max(search_px, wide_search_px), seed)
            epi[work, j] = epi_j
        out[work, j] = pts_j
        zn[work, j] = zn_j
        sig_x[work, j] = sig_j
        sig_ap[work, j] = aposteriori_sigma(sig_j, rr_j)
        for k in np.flatnonzero(~ok_j):
            i = work[k]
            if not r.converged[k]:
                why = r.reason[k]
            else:
                why = f"zncc {zn_j[k]:.2f} < min_zncc {min_zncc}"
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
            fwd_state[j] = (cur_coef, warp_full, hw_full, e, epi_coef)

    # local consistency of parallax and cross-parallax against grid neighbours (twice)
    for _ in range(2 if consistency_px is not None else 0):
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
    model_x = np.zeros((n, v))
    if valid.sum() >= 12:
        idx = np.flatnonzero(valid)
        thr = max(max_roughness_px or 0.0, 2.0 * float(np.median(sigma[idx])))
        for j, (pa, _) in resid.items():
            # with the dense prior (a tall object) the parallax is curved on the scale of the
            # neighbourhood: test against local quadrics, which still reject steps
            _, rough = _parallax_gradients(grid[idx], pa[idx], return_residual=True,
                                           quadratic=j in curved)
            # the non-affine part of the parallax around each point: its model error
            # the neighbourhood of each fit covers the point's subset (information-sized
            # subsets grow past 12 grid neighbours)
            hs = (side[idx] - 1) // 2
            for h in np.unique(hs):
                k_h = int(min(len(idx), max(12, min(64, round((2 * h + 1) ** 2 / spacing_px ** 2)))))
                rough_h = rough if k_h == 12 else _parallax_gradients(
                    grid[idx], pa[idx], k=k_h, return_residual=True, quadratic=j in curved)[1]
                m = hs == h
                model_x[idx[m], j] = model_error_from_fit(
                    grid[idx], rough_h, sig_x[idx, j], h, k_h, 6 if j in curved else 3)[m]
            if max_roughness_px is None:
                continue
            # a surface rough all over (a pollen grain's reticulum) is not a steep flank:
            # only roughness that stands out of the view's own distribution is rejected
            med = float(np.median(rough))
            thr_j = thr if med <= thr else \
                max(thr, med + 4 * 1.4826 * float(np.median(np.abs(rough - med))))
            bad = rough > thr_j
            for i, rr in zip(idx[bad], rough[bad]):
                if valid[i]:
                    reason[i] = (f"view {j}: parallax not locally planar (plane RMS {rr:.2f} px "
                                 f"> {thr_j:.2f} px: steep flank)")
            valid[idx[bad]] = False
    if backward_px is not None:
        for j, (coef_j, warp_j, hw_full, e_j, epi_coef) in fwd_state.items():
            idx = np.flatnonzero(valid)
            if len(idx) == 0:
                break
            fb_d = np.full(len(idx), np.nan)
            for h in np.unique(hw_full[idx]):      # the backward match uses the same subset
                for one_d in (False, True):        # ... and the same shape function
                    k = (hw_full[idx] == h) & (epi[idx, j] == one_d)
                    if not k.any():
                        continue
                    sm, rc, cc = epi_coef if one_d else (smooth_sigma_px, ref_coef, coef_j)
                    fb_d[k] = _backward_distance(ims[j], ims[ref], out[idx[k], j],
                                                 grid[idx[k]], warp_j[idx[k]], int(h), sm,
                                                 cc, rc, max_iter, tol_px,
                                                 direction=e_j if one_d else None)
            bad = ~(fb_d <= backward_px)
            for i, dd in zip(idx[bad], fb_d[bad]):
                reason[i] = (f"view {j}: forward–backward mismatch "
                             + ("(backward match failed)" if np.isnan(dd) else
                                f"{dd:.2f} px > backward_px {backward_px}"))
            valid[idx[bad]] = False
    if multiview_px is not None and v >= 3 and valid.sum() >= 8:
        mres, _ = _multiview_residual(out, ref, valid, seed=seed)
        r_in = mres[valid]
        thr = max(np.median(r_in) + 4 * 1.4826 * np.median(np.abs(r_in - np.median(r_in))),
                  multiview_px)
        bad = valid & ~(mres <= thr)
        for i in np.flatnonzero(bad):
            reason[i] = (f"views inconsistent: x coordinates off the rank-2 tilt-series model "
                         f"by {mres[i]:.2f} px > {thr:.2f} px")
        valid &= ~bad
    # error bars: noise σ with the a posteriori factor, plus the model error
    sigma = np.sqrt(np.mean(sig_ap[:, others] ** 2 + model_x[:, others] ** 2, axis=1))
    sigma[~valid] = np.nan
    if progress:
        from tqdm.auto import tqdm
        tqdm.write(f"auto_match: {valid.sum()} of {n} grid points accepted")
    return MatchResult(pts=out, zncc=zn, valid=valid, sigma_px=sigma, reason=reason.astype(str),
                       ref_view=ref, kind=np.full(n, "auto"), source_index=gidx,
                       subset_px=side, params=params)


def _epipolar_stage(ref_img, img, gw, M, e, start, pts_j, sig_j, rr_j, ok_j, r, half_window,
                    grad, init_w, min_zncc, smooth_sigma_px, ref_coef, cur_coef, max_iter, tol_px,
                    search_px, seed, n_trial=200, smooth_px=1.0):
    """Grid points the 2D subsets failed on, matched along the epipolar direction only.

    Where a subset's texture constrains only the parallax direction ``e`` (grooves or
    scratches across it), the 2D IC-GN diverges along the texture; the affine epipolar
    constraint fixes the cross-parallax position and gradient at the global affine map
    ``M``'s (the parallax gradient starts at the flow's, ``init_w``), and
    :func:`semlab.match_epipolar.epipolar_refine` finds the shift along ``e`` (searched
    within ``±search_px``) and its gradient. Pre-smoothing as :func:`_choose_smoothing`
    decides for 2D subsets: unsmoothed unless fewer than half of ``n_trial`` random
    points then reach ``min_zncc`` (JPEG-compressed views), else ``smooth_px``. Returns the
    updated ``(pts, sigma, residual_ratio, zncc, ok, one_d, result)`` of the view, ``one_d`` marking the
    points taken from this stage (their warp replaces ``r.warp``), and the stage's
    ``(smooth_sigma_px, ref_coef, cur_coef)`` for the backward check.
    """
    fail = np.flatnonzero(~ok_j & np.all(np.isfinite(start), 1))
    zn_j = r.zncc.copy()
    one_d = np.zeros(len(gw), bool)
    coefs = (smooth_sigma_px, ref_coef, cur_coef)
    if len(fail) == 0:
        return pts_j, sig_j, rr_j, zn_j, ok_j, one_d, r, coefs
    base = _apply_affine(M, gw[fail])
    guess = base + ((start[fail] - base) @ e)[:, None] * e
    gm = np.array([[grad[1], grad[2]], [grad[4], grad[5]]])
    iw = np.broadcast_to(init_w, (len(gw), 6))[fail]
    gf = np.stack([np.stack([iw[:, 1], iw[:, 2]], 1), np.stack([iw[:, 4], iw[:, 5]], 1)], 1)
    G = gm + e[:, None] * np.einsum("i,nij->nj", e, gf - gm)[:, None, :]
    z = np.zeros(len(fail))
    held = np.column_stack([z, G[:, 0, 0], G[:, 0, 1], z, G[:, 1, 0], G[:, 1, 1]])

    def run(k, sm, rc, cc):
        return epipolar_refine(ref_img, img, gw[fail[k]], guess[k], e, half_window, held[k],
                               search_px=search_px, max_iter=max_iter, tol_px=tol_px,
                               smooth_sigma_px=sm, ref_prefiltered=rc, cur_prefiltered=cc)

    if not smooth_sigma_px:
        k = np.random.default_rng(seed).choice(len(fail), min(len(fail), n_trial), False)
        t = run(k, 0.0, ref_coef, cur_coef)
        if np.mean(t.converged & (t.zncc >= min_zncc)) < 0.5:
            coefs = (smooth_px, prefilter_image(ref_img, smooth_px),
                     prefilter_image(img, smooth_px))
    q = run(slice(None), *coefs)
    use = q.converged & (q.zncc >= min_zncc) & np.isfinite(q.sigma_px[:, 0])
    k = fail[use]
    pts_j, sig_j, rr_j, ok_j = pts_j.copy(), sig_j.copy(), rr_j.copy(), ok_j.copy()
    pts_j[k], sig_j[k], zn_j[k], ok_j[k], one_d[k] = q.pts[use], q.sigma_px[use, 0], \
        q.zncc[use], True, True
    rr_j[k] = q.residual_ratio[use]
    # an unaccepted 1-D match with a better ZNCC explains the failure better
    better = fail[~use & q.converged & (q.zncc > zn_j[fail])]
    zn_j[better] = q.zncc[np.searchsorted(fail, better)]
    warp = r.warp.copy()
    warp[k] = q.warp[use]
    conv = r.converged.copy()
    conv[k] = True
    conv[better] = True
    return (pts_j, sig_j, rr_j, zn_j, ok_j, one_d, replace(r, warp=warp, converged=conv),
            coefs)


def _auto_params(params, overrides):
    p = AutoMatchParams() if params is None else params
    if not isinstance(p, AutoMatchParams):
        raise SemlabError(f"params must be an AutoMatchParams, got {type(p).__name__}")
    unknown = set(overrides) - {f.name for f in fields(AutoMatchParams)}
    if unknown:
        raise SemlabError(f"auto_match has no parameter {', '.join(sorted(unknown))}; see "
                          "semlab.matching.AutoMatchParams for the parameters")
    return replace(p, **overrides) if overrides else p


# --------------------------------------------------------------------------- merge