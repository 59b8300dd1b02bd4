"""Sub-pixel refinement of hand-clicked stereo correspondences.

:func:`refine_correspondences` keeps the reference-view clicks (they define the material
point) and refines the clicks in the other views, which are only starting guesses (~0.5 px
error): ZNCC search, IC-GN of an affine or information-sized subset
(:func:`semlab.adaptive.adaptive_icgn`), and band-aware thin subsets near parallax edges
(:mod:`semlab.match_band`). Imported by :mod:`semlab.matching` (``from semlab.matching
import refine_correspondences`` keeps working).

Conventions: images are 2D arrays indexed ``[row, col]``; points are ``(x, y)`` pixels;
``pts`` arrays are ``(N, V, 2)``: N points seen in V views.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .adaptive import _grid_icgn
from .errors import GeometryError, SemlabError
from .match_band import _band_orientation, _coarse_parallax, _combine, _oriented_refine
from .match_prior import fit_affine
from .match_result import MatchResult, _check_images, _check_ref_view
from .match_sigma import match_sigma, model_error_at
from .subset import prefilter_image, zncc_match

SQRT2 = float(np.sqrt(2.0))

__all__ = ["refine_correspondences", "information_offset"]


def refine_correspondences(images, pts, ref_view=0, half_window=10, search_px=4,
                           warp="affine", min_zncc=0.8, *, smooth_sigma_px=None,
                           band_aware=True, band_half_width_px=3, kappa=SQRT2,
                           target_sigma_px=0.05, min_half_window=7, max_half_window=28,
                           curvature_neighbours=1, max_info_offset=2 / 3, progress=False):
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
        Also match each point with a thin rectangular subset (``4h+1`` long, ``h`` the
        half size of the point's square subset, ``2 band_half_width_px + 1`` wide) along
        the local direction of the parallax bands,
        estimated from the structure tensor of a coarse dense parallax field (every
        ``h`` pixels), and keep it where the square subset disagrees with it by more than
        ``kappa`` of its σ: near the edges of extrusions the parallax changes within a
        square subset and biases it, while a subset along the band sees a nearly constant
        parallax.
    band_half_width_px, kappa : float
        See ``band_aware``. ``kappa = √2`` (default) keeps the estimate of smaller estimated
        mean-square error: the square's squared bias estimated without bias from the
        disagreement ``d`` as ``d² − σ_d²`` with ``σ_d² ≈ σ_band² + σ_square²``, its MSE
        ``d² − σ_band²`` exceeds the band's ``σ_band²`` where ``|d| > √2 σ_band``. With
        ``kappa = 1`` noise alone picked the noisier band subset at about a third of the
        points. On the clicks of 15 realistic-noise accuracy-matrix runs (polished,
        real:fei, real:quartz, seeds 0-2) √2 lowered the height RMSE in 11 (geometric mean
        −2 %, from 0.758× to 0.742× ECC 15px's) and on 12 low-noise runs raised it by 3 %
        (at most 14 %; 0.726× to 0.748× ECC's).
    target_sigma_px : float or None
        Size each point's square subset by its information: the smallest from
        ``min_half_window`` up to ``max_half_window`` whose predicted σ reaches this target
        (pixels), with the shape function it supports
        (:func:`semlab.adaptive.adaptive_icgn`; ``warp`` and ``half_window`` are then
        ignored; each point's band-aware subset is as long as its square is wide). None: one fixed
        ``half_window``. On the
        192×256 accuracy-matrix cells (realistic noise, ±5°) 0.05 px gave height RMSE
        35.9 / 25.2 / 15.4 nm (polished / real:fei / speckle) against 41.6 / 38.8 / 18.6 nm
        with a fixed 21×21 subset and 43.1 / 49.7 / 27.3 nm for ECC.
    min_half_window, max_half_window : int
        Smallest and largest subset half sizes with ``target_sigma_px``.
    curvature_neighbours : int or None
        With ``target_sigma_px``: size each click's subset by its predicted total error,
        noise and curvature bias, the bias measured from the drift of the click's own match
        across the subset sizes (:func:`semlab.adaptive.adaptive_icgn`; 1: each click
        alone, clicks being sparse), and add that bias to its σ as a model error. The
        model error of the coarse parallax grid (:func:`semlab.match_sigma.model_error_at`)
        misses it: on the real:fei cells the grid's 15×15 subsets have σ ~0.2 px, which
        buries the subset-averaging bias (−5/+5° noise-free: |error| up to 79 nm at σ
        4-20 nm, model error 0 at 9 of the 10 worst clicks, the error correlated 0.6-0.8
        with the truth's subset mean minus its centre). None: sized by the noise alone.
        The model error is the expected squared bias given the size ladder,
        ``(β̂² + var β̂) c_h²`` from the independent increments of the nested subsets'
        matches (:func:`semlab.adaptive._nested_bias`): the match is not corrected, so its
        error bar holds the bias as far as the ladder leaves it unknown. The de-biased
        estimate ``max(β̂² − var β̂, 0) c_h²`` that sizes the subset (the σ's model error
        before 2026-12-02) is 0 wherever the bias is below the ladder's noise, which is
        where the subsets grow to the largest size: on the 9 accuracy-matrix cells whose
        clicks were below 93 % within 2σ (seeds 0-2, 1258 clicks) the clicks with
        ``h >= 14`` were 87 % within 2σ (misses at σ 0.02-0.04 px with errors 0.07-0.34 px,
        far from the slip-band flanks, predicted model error 0), those with ``h <= 10``
        93 % (``benchmarks/clicks_sigma.py --diagnose``).
    max_info_offset : float or None
        Invalidate (with the reason) clicks whose square subset's x information (``gx²``
        of the reference view) is centred more than this fraction of its half size away
        from the click (:func:`information_offset`): texture-free around the click, e.g.
        on flat background beside an edge, the match gives the parallax of the texture
        over there with a small σ (aperture problem across the edge; on a 0.2 µm step,
        background clicks 3-12 px from the edge had 0.7-1.0 px errors at σ 0.02-0.07
        px, offsets 0.79-0.87 of the half size 5-12 px from the edge). 2/3: the
        information in the outer third of the subset on one side; clicks on textured
        synthetic scenes reach 0.52, but clicks on an intrusion beside an extrusion's bright
        flank reach 0.67–0.92 and are right (seed 1's crack clicks: all 30 it left out of
        three experiments within 1.4σ of the truth without it,
        ``benchmarks/results/info_offset_clicks.md``). None: keep them.
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
    ref_gx2 = np.gradient(ndimage.gaussian_filter(ims[ref], max(smooth_sigma_px, 0.5)),
                          axis=1) ** 2
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
        r, hw_j, bias_j = _grid_icgn(
            ims[ref], ims[j], pr, np.where(np.isfinite(guess), guess, p[:, j]), half_window,
            warp, grad, smooth_sigma_px, ref_coef, cur_coef, target_sigma_px,
            max_half_window, bias="rms",
            progress=progress,
            **({} if curvature_neighbours is None or target_sigma_px is None
               else {"curvature_neighbours": curvature_neighbours}))
        side = np.maximum(side, np.where(r.converged, 2 * hw_j + 1, 0))
        pts_j, sig_j, zn_j = r.pts.copy(), r.sigma_px[:, 0].copy(), r.zncc.copy()
        rr_j, model_j = r.residual_ratio.copy(), None
        ok_j = r.converged & (r.zncc >= min_zncc)
        nosearch = ~np.all(np.isfinite(guess), 1)
        if band_aware:
            Mj = fit_affine(pr, p[:, j]) if n >= 3 else np.column_stack(
                [np.eye(2), np.median(p[:, j] - pr, axis=0)])
            gxy, gpar, gsig = _coarse_parallax(ims[ref], ims[j], Mj, half_window, search_px,
                                               smooth_sigma_px, ref_coef, cur_coef,
                                               return_sigma=True)
            ang, _, _ = _band_orientation(pr, gxy, gpar, 2.0 * half_window)
            # every point with a usable start: square result, else the ZNCC peak
            start = np.where(np.isfinite(r.pts), r.pts, guess)
            sel = np.flatnonzero(np.all(np.isfinite(start), 1))
            if len(sel):
                # each band subset as long as its point's square is wide (the square sized
                # by information): a thin subset of the smallest square's length beside a
                # grown square is the noisier estimate, chosen by noise alone
                o_len = 2 * np.where(hw_j > 0, hw_j, half_window)[sel]
                o_pts, o_sig, o_zn, o_rr = _oriented_refine(
                    ims[ref], ims[j], pr[sel], start[sel], grad, ang[sel], o_len,
                    band_half_width_px, smooth_sigma_px, ref_coef, cur_coef,
                    return_residual_ratio=True)
                sq = np.where(ok_j[sel, None], r.pts[sel], np.nan)
                c_pts, c_sig, use = _combine(sq, sig_j[sel], o_pts, o_sig, o_zn, min_zncc,
                                             kappa)
                pts_j[sel], sig_j[sel] = c_pts, c_sig
                rr_j[sel] = np.where(use, o_rr, rr_j[sel])
                zn_j[sel] = np.where(use, o_zn, zn_j[sel])
                ok_j[sel] |= use
            # model error: the non-affine part of the coarse parallax around each click
            model_j = model_error_at(pr, gxy, gpar, gsig, np.where(hw_j > 0, hw_j, half_window),
                                     half_window)
        # the click's own curvature bias: the drift of its match with the subset size
        # (adaptive_icgn's total-error sizing), where the coarse grid is too noisy to see it
        model_j = bias_j if model_j is None else np.fmax(model_j, bias_j)
        # error bar: noise σ with the a posteriori factor, plus the model error
        sig_j = match_sigma(sig_j, rr_j, model_j)
        # a click whose subset's parallax information lies off its centre (texture-free
        # around it, beside an edge) measures the parallax of that texture, not its own
        off_j = np.full(n, np.nan)
        if max_info_offset is not None:
            hw_sq = np.where(hw_j > 0, hw_j, half_window)
            # at the chosen size and at the smallest one (a grown subset can dilute the
            # edge that the click's immediate neighbourhood is made of)
            off_j = np.fmax(information_offset(ref_gx2, pr, hw_sq) / hw_sq,
                            information_offset(ref_gx2, pr, half_window) / half_window)
            off_bad = ok_j & (off_j > max_info_offset)
        else:
            off_bad = np.zeros(n, bool)
        ok_j &= ~off_bad
        pts_j[~ok_j] = np.nan
        out[:, j] = pts_j
        zn[:, j] = zn_j
        sig_x[:, j] = sig_j
        for i in np.flatnonzero(~ok_j):
            if off_bad[i]:
                why = (f"its subset's parallax information is centred {off_j[i]:.2f} of the "
                       f"half size from the click: texture-free around the click, "
                       "e.g. beside an edge, the match would give that texture's parallax; "
                       "click on texture")
            elif not r.converged[i]:
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


def information_offset(gx2, pts, half_window):
    """Distance from each point to the centroid of its subset's parallax information, px.

    The x shift of a subset is, to first order, the average of the local shifts weighted
    by the x information ``gx²`` of its pixels (parallax is along x, the tilt axis being
    y; the cross-parallax is held by the epipolar geometry). Where that weight sits off
    the subset's centre (no texture around the point, an edge or particle a few pixels
    away) the match measures the parallax there, not at the point, and no image noise σ
    or residual says so (the aperture problem across the edge).

    Parameters
    ----------
    gx2 : (H, W) array
        Squared x gradient of the reference image.
    pts : (N, 2) array of (x, y) pixels
    half_window : int or (N,) array
        Half size of each point's square subset.

    Returns
    -------
    (N,) array of pixels; NaN where the subset has no x gradient at all.
    """
    g = np.asarray(gx2, float)
    p = np.asarray(pts, float).reshape(-1, 2)
    hs = np.broadcast_to(np.asarray(half_window, int), (len(p),))
    out = np.full(len(p), np.nan)
    hgt, wid = g.shape
    for i, ((x, y), h) in enumerate(zip(p, hs)):
        c, r = int(round(x)), int(round(y))
        r0, r1, c0, c1 = max(r - h, 0), min(r + h + 1, hgt), max(c - h, 0), min(c + h + 1, wid)
        w = g[r0:r1, c0:c1]
        tot = w.sum()
        if tot > 0:
            yy, xx = np.mgrid[r0:r1, c0:c1]
            out[i] = np.hypot((w * xx).sum() / tot - x, (w * yy).sum() / tot - y)
    return out
