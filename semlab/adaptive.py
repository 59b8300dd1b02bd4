"""Subsets sized by the information they hold: the smallest that reaches a target error.

:func:`adaptive_icgn` runs :func:`semlab.subset.icgn_refine` over growing square subsets
and keeps, per point, the first (smallest) subset whose predicted 1σ (from the
Gauss–Newton covariance and the measured image noise, see
:attr:`semlab.subset.SubsetResult.sigma_px`) reaches ``target_sigma_px``. The shape
function is chosen by what the information supports:

- **affine** where the affine fit alone reaches the target: it resolves the local
  deformation gradient and has no model bias;
- otherwise **translation**, with the gradient terms held at ``init_warp`` (e.g. the
  known x-scaling of a tilt pair or a registration's affine part): two parameters instead
  of six, so a smaller predicted error from the same pixels. It is accepted only when the
  held gradient costs less than it saves: the translation's squared position bias,
  estimated from its disagreement with the affine fit of the same subset, plus its
  variance must stay below the affine fit's variance (:func:`_gradient_holds`, a
  Hausman-type comparison of the two estimates); otherwise the subset grows or stays
  affine. (Comparing the two residuals instead, within the chi-square scatter of one
  residual variance, let held gradients 0.02–0.04 off pass and doubled the error.)

With ``curvature_neighbours`` the sizing also accounts for the displacement's curvature
(:func:`_total_error_select`): with an affine shape function a curved displacement biases
the matched centre by ``∇²u · h (h + 1) / 6`` (the mean of the quadratic term over the
subset), which grows with the subset while the noise falls. Every size of the ladder is
matched, the bias coefficient of each point is estimated from how its estimates move with
the size (weighted least squares of ``u_h`` on ``h (h + 1) / 6``), averaged over its
nearest neighbours and de-biased by its variance, and the subset chosen is the smallest
whose predicted total error ``√(σ_h² + b_h²)`` reaches the target, else the one with the
smallest total error (``target_sigma_px=0``: always the smallest total error).

A subset whose residual exceeds what the measured noise explains (by more than the same
chi-square scatter) does not fit its shape function (curved parallax, a step): it never
counts as reaching the target. A point grows only where more pixels can help: a match
above the target that fits, or whose excess residual the largest subset could dilute
below its scatter (a local misfit falls at best as the area grows; a curvature misfit
grows), or a subset too poor in texture to converge (singular Hessian; ``max_iter`` or
divergence at most at two sizes in a row). Others stop at their size.
Points that do not reach the target keep their best match (the smallest predicted error among the fitting ones, else
the smallest subset that converged: misfit grows with the subset),
``target_met = False`` and a reason; they are never dropped silently. Each point reports its subset half size, so the caller can give its spatial
resolution ``(2 h + 1) × pixel_size_um``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .errors import SemlabError
from .subset import (DIVERGED, MAX_ITER, NO_TEXTURE, NO_TEXTURE_CUR, SubsetResult, _as_image,
                     icgn_refine, prefilter_image)

__all__ = ["AdaptiveResult", "adaptive_icgn", "TARGET_MISSED"]

TARGET_MISSED = "target_sigma_px not reached with the largest subset"
_POOR = (NO_TEXTURE, NO_TEXTURE_CUR)   # IC-GN failures a larger subset can cure
_RETRY = (MAX_ITER, DIVERGED)           # ... or may: tried at one more size


@dataclass(frozen=True)
class AdaptiveResult:
    """Result of :func:`adaptive_icgn` for ``N`` points.

    Attributes
    ----------
    subset : SubsetResult
        The chosen match of every point (``subset.reason`` is empty where the target was
        met, :data:`TARGET_MISSED` plus the reached σ where only the target was missed,
        and IC-GN's reason where no subset converged).
    half_window : (N,) int array
        Half size ``h`` of the chosen square subset, pixels (``(2h+1)²`` pixels); 0 where
        no subset converged.
    shape_function : (N,) str array
        ``"affine"``, ``"translation"`` or ``""`` (no match).
    target_met : (N,) bool array
        True where ``max(sigma_px) <= target_sigma_px`` (with ``curvature_neighbours``: the
        predicted total error; with the target 0: where a size that fits was chosen).
    target_sigma_px : float
        The target.
    bias_px : (N,) float array or None
        With ``curvature_neighbours``: the predicted curvature bias of the chosen match
        (the larger of x and y), pixels; the predicted total error is
        ``√(sigma² + bias²)``. None otherwise.
    bias_rms_px : (N,) float array or None
        With ``curvature_neighbours``: the root of the expected squared curvature bias of
        the chosen match given the ladder (:func:`_nested_bias`: ``√(β̂² + var β̂) c_h``
        from the independent increments of the nested subsets' matches), the larger of x
        and y, pixels: the bias term of an error bar of the uncorrected match (``bias_px``
        is the de-biased point estimate that sizes the subset, 0 wherever the bias is
        below its noise). None otherwise.
    """

    subset: SubsetResult
    half_window: np.ndarray
    shape_function: np.ndarray
    target_met: np.ndarray
    target_sigma_px: float
    bias_px: np.ndarray = None
    bias_rms_px: np.ndarray = None

    def __len__(self):
        return len(self.half_window)

    def subset_size_um(self, pixel_size_um):
        """(N,) side of each point's subset in µm (its spatial resolution); NaN if none."""
        s = (2.0 * self.half_window + 1.0) * float(pixel_size_um)
        return np.where(self.half_window > 0, s, np.nan)


def adaptive_icgn(ref_img, cur_img, pts_ref, pts_guess, target_sigma_px=0.05,
                  half_windows=(7, 10, 14, 20, 28), warp="auto", init_warp=None, *,
                  smooth_sigma_px=0.0, noise_sigma=None, max_iter=30, tol_px=1e-4,
                  ref_prefiltered=None, cur_prefiltered=None, curvature_neighbours=None):
    """IC-GN matching with per-point subset size and shape function chosen by information.

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current grey images.
    pts_ref, pts_guess : (N, 2) arrays
        Reference points and guesses ``(x, y)`` in pixels (see
        :func:`semlab.subset.icgn_refine`).
    target_sigma_px : float
        Wanted predicted 1σ of the matched position (the larger of x and y), pixels. With
        ``curvature_neighbours``, 0 means no target: each point takes the size with the
        smallest predicted total error (its mean-square-error optimum over the ladder).
    half_windows : sequence of int
        Subset half sizes tried, increasing; the last is the largest allowed.
    warp : {"auto", "affine", "translation"}
        Shape function: ``"auto"`` as in the module docstring, or one fixed.
    init_warp : (N, 6) or (6,) array, optional
        Starting (and, for translation, held) gradient terms, as in ``icgn_refine``.
    smooth_sigma_px, noise_sigma, max_iter, tol_px, ref_prefiltered, cur_prefiltered
        As in :func:`semlab.subset.icgn_refine`.
    curvature_neighbours : int or None
        Size by the predicted total error, noise and curvature bias (module docstring),
        the bias coefficient averaged over this many nearest points (itself included; 1:
        each point alone). Needs a single shape function (``"auto"`` means affine here).
        None: by the noise alone.

    Returns
    -------
    AdaptiveResult

    Raises
    ------
    SemlabError
        On an invalid target, sizes or ``warp``.
    """
    total = curvature_neighbours is not None
    if not (np.isfinite(target_sigma_px) and (target_sigma_px > 0
                                              or (total and target_sigma_px == 0))):
        raise SemlabError(f"target_sigma_px must be > 0 (or 0 with curvature_neighbours: "
                          f"the smallest total error), got {target_sigma_px!r}")
    hs = [int(h) for h in half_windows]
    if not hs or any(b <= a for a, b in zip(hs, hs[1:])) or hs[0] < 2:
        raise SemlabError(f"half_windows must be increasing integers >= 2, got {half_windows!r}")
    if warp not in ("auto", "affine", "translation"):
        raise SemlabError(f"warp must be 'auto', 'affine' or 'translation', got {warp!r}")
    ref = _as_image(ref_img, "ref_img")
    cur = _as_image(cur_img, "cur_img")
    pr = np.asarray(pts_ref, float).reshape(-1, 2)
    pg = np.asarray(pts_guess, float).reshape(-1, 2)
    n = len(pr)
    rc = prefilter_image(ref, smooth_sigma_px) if ref_prefiltered is None else ref_prefiltered
    cc = prefilter_image(cur, smooth_sigma_px) if cur_prefiltered is None else cur_prefiltered
    iw = np.zeros((n, 6)) if init_warp is None else np.broadcast_to(
        np.asarray(init_warp, float), (n, 6)).copy()
    kw = dict(smooth_sigma_px=smooth_sigma_px, noise_sigma=noise_sigma, max_iter=max_iter,
              tol_px=tol_px, ref_prefiltered=rc, cur_prefiltered=cc)
    if curvature_neighbours is not None:
        k_nb = int(curvature_neighbours)
        if k_nb < 1:
            raise SemlabError(f"curvature_neighbours must be None or >= 1, got "
                              f"{curvature_neighbours!r}")
        return _total_error_select(ref, cur, pr, pg, float(target_sigma_px), hs,
                                   "translation" if warp == "translation" else "affine",
                                   iw, kw, k_nb, noise_sigma)

    best = _empty(n, noise_sigma)     # best result so far of every point
    best_sig = np.full(n, np.inf)
    hw = np.zeros(n, int)
    shape = np.full(n, "", dtype=object)
    met = np.zeros(n, bool)
    best_fits = np.zeros(n, bool)
    todo = np.arange(n)
    guess = pg.copy()
    slow = np.zeros(n, int)           # successive sizes whose first fit failed (_RETRY)
    for h in hs:
        if len(todo) == 0:
            break
        grow = np.zeros(len(todo), bool)    # where a larger subset can still help
        cand = []
        if warp in ("auto", "affine"):
            cand.append(("affine", icgn_refine(ref, cur, pr[todo], guess[todo], half_window=h,
                                               warp="affine", init_warp=iw[todo], **kw)))
        if warp in ("auto", "translation"):
            cand.append(("translation", icgn_refine(
                ref, cur, pr[todo], guess[todo], half_window=h, warp="translation",
                init_warp=iw[todo], **kw)))
        dof = (2 * h + 1) ** 2 - 6
        scatter = 3 * np.sqrt(2.0 / dof)     # chi-square scatter of a residual variance
        # a local misfit (a particle, an edge) is at best diluted by the area of a larger
        # subset: the excess residual ratio falls as (2h+1)² / (2H+1)²; a subset that
        # could not fit even so at the largest size H stops (a curvature misfit grows)
        dilute = ((2 * h + 1) / (2 * hs[-1] + 1)) ** 2
        scatter_max = 3 * np.sqrt(2.0 / ((2 * hs[-1] + 1) ** 2 - 6))
        for name, r in cand:
            # a subset whose residual exceeds the noise by more than the scatter does not
            # fit its shape function (curved parallax, a step); a translation must fit as
            # well as the affine fit: such a match is only a fallback, never "target met"
            fits = r.converged & (r.residual_ratio <= 1 + scatter)
            s = np.where(r.converged, np.nanmax(r.sigma_px, axis=1, initial=-np.inf), np.inf)
            s = np.where(np.isnan(s), np.inf, s)
            ok_now = (s <= target_sigma_px) & fits
            if name == "translation" and warp == "auto":
                ra = cand[0][1]
                holds, bias2 = _gradient_holds(ra, r)
                fits &= holds
                s = np.sqrt(s ** 2 + bias2)   # its target counts the estimated bias too
                # unverified (no affine fit to compare with): a candidate, never the target
                ok_now = (s <= target_sigma_px) & fits & ra.converged
            bf = best_fits[todo]
            better = ~met[todo] & (ok_now | (fits & (~bf | (s < best_sig[todo])))
                                   | (~fits & ~bf & ~np.isfinite(best_sig[todo])
                                      & np.isfinite(s)))
            k = np.flatnonzero(better)
            best = _assign(best, todo[k], r, k)
            best_sig[todo[k]] = s[k]
            best_fits[todo[k]] = fits[k]
            hw[todo[k]] = h
            shape[todo[k]] = name
            met[todo[k]] |= ok_now[k]
            # a converged match is the next size's starting point
            good = np.isfinite(r.pts[:, 0])
            guess[todo[good]] = r.pts[good]
            grow |= ~ok_now & (fits | (r.converged
                                       & ((r.residual_ratio - 1) * dilute <= scatter_max)))
        # grow only where more pixels can help: a match above the target that fits, or
        # whose misfit a larger subset could dilute, or a most general fit (the first
        # candidate) that failed for lack of information (singular Hessian; max_iter or
        # divergence, at most at two sizes in a row); a subset whose misfit no size can
        # dilute, or that left the image, stops here (on the 1200² quartz views, where
        # most subsets' residual exceeds the noise, the whole ladder for every point cost
        # 9× the fixed subsets' IC-GN)
        why = np.asarray(cand[0][1].reason)
        retry = np.isin(why, _RETRY)
        slow[todo] = np.where(retry, slow[todo] + 1, 0)
        poor = np.isin(why, _POOR) | (retry & (slow[todo] < 2))
        todo = todo[~met[todo] & (grow | poor)]
    # never converged: keep IC-GN's reason; converged but above the target: say so
    conv = best.converged
    reason = np.array(best.reason, dtype=object)
    miss = conv & ~met
    for i in np.flatnonzero(miss):
        reason[i] = f"{TARGET_MISSED} (sigma {best_sig[i]:.3f} px at h={hw[i]}" + (
            ")" if best_fits[i] else "; its residual exceeds the noise: shape misfit)")
    hw[~conv] = 0
    shape[~conv] = ""
    best = replace(best, reason=reason.astype(str) if n else best.reason)
    return AdaptiveResult(subset=best, half_window=hw, shape_function=shape.astype(str),
                          target_met=met, target_sigma_px=float(target_sigma_px))


def _gradient_holds(ra, rt):
    """(N,) bool where the held gradient of translation ``rt`` costs less than the affine
    fit ``ra`` of the same subsets, by estimated mean-square error of the position, and
    (N,) the translation's estimated squared bias (px², 0 where there is no affine fit).

    Under a right held gradient both estimate the same position, the translation with the
    smaller variance, so their difference ``d`` has variance ``σ_a² − σ_t²`` (Hausman
    1978); the translation's squared bias is estimated without bias by
    ``|d|² − Σ(σ_a² − σ_t²)`` and its MSE stays below the affine's while
    ``|d|² <= 2 Σ(σ_a² − σ_t²)`` (x and y summed). Where the affine fit did not converge
    there is nothing to compare with: the translation holds, but does not count as
    reaching the target (the subset grows to find a comparison). A translation reaches
    the target only with its bias: ``sqrt(σ_t² + bias²) <= target_sigma_px``.
    """
    d2 = np.sum((rt.pts - ra.pts) ** 2, axis=1)
    with np.errstate(invalid="ignore"):       # both σ infinite (texture below the noise)
        dv = np.sum(ra.sigma_px ** 2 - rt.sigma_px ** 2, axis=1)
        ok = d2 <= 2 * np.maximum(dv, 0)
        bias2 = np.where(np.isfinite(d2) & np.isfinite(dv), np.maximum(d2 - dv, 0), 0.0)
    return ~ra.converged | (~np.isfinite(dv) & np.isfinite(d2)) | ok, bias2


def _total_error_select(ref, cur, pr, pg, target, hs, warp, iw, kw, k_nb, noise_sigma):
    """:func:`adaptive_icgn` sized by the predicted total error (noise and curvature bias).

    Stages: every size matched (each started from the previous size's match); the bias
    coefficient β of ``u_h ≈ u + β c_h``, ``c_h = h (h + 1) / 6``, per point and component by
    least squares weighted by ``1 / σ_h²``; its variance from the nested smallest and largest
    subsets, ``(σ_first² − σ_last²) / (c_last − c_first)²``; both averaged over the
    ``k_nb`` nearest points; ``b_h² = max(β² − var β, 0) c_h²``; the choice.
    """
    from scipy.spatial import cKDTree

    n, nh = len(pr), len(hs)
    c = np.array([h * (h + 1) / 6.0 for h in hs])
    runs = []
    guess = pg.copy()
    for h in hs:
        r = icgn_refine(ref, cur, pr, guess, half_window=h, warp=warp, init_warp=iw, **kw)
        runs.append(r)
        good = np.isfinite(r.pts[:, 0])
        guess[good] = r.pts[good]
    U = np.stack([r.pts for r in runs])                          # (H, N, 2)
    S = np.stack([np.asarray(r.sigma_px, float) for r in runs])  # (H, N, 2)
    fin = np.stack([r.converged for r in runs])[..., None] & np.isfinite(U) \
        & np.isfinite(S) & (S > 0)
    w = np.where(fin, 1.0 / np.where(fin, S, 1.0) ** 2, 0.0)
    Uz = np.where(fin, U, 0.0)
    cc = c[:, None, None]
    sw, swc, swcc = w.sum(0), (w * cc).sum(0), (w * cc ** 2).sum(0)
    swu, swcu = (w * Uz).sum(0), (w * cc * Uz).sum(0)
    det = sw * swcc - swc ** 2
    two = fin.sum(0) >= 2
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(two & (det > 0), (sw * swcu - swc * swu) / np.where(det > 0, det, 1),
                        np.nan)
        first = np.argmax(fin, axis=0)                           # smallest converged size
        last = nh - 1 - np.argmax(fin[::-1], axis=0)             # largest converged size
        s_f = np.take_along_axis(S, first[None], 0)[0]
        s_l = np.take_along_axis(S, last[None], 0)[0]
        dc = c[last] - c[first]
        var_b = np.where(two & (dc > 0), np.abs(s_f ** 2 - s_l ** 2)
                         / np.where(dc > 0, dc, 1) ** 2, np.nan)
    kk = min(k_nb, n)
    if kk > 1:
        _, nb = cKDTree(pr).query(pr, k=kk)
        nb = nb.reshape(n, kk)
        cnt = np.isfinite(beta[nb]).sum(1)                        # (N, 2)
        beta = _nanmean(beta[nb], axis=1)
        var_b = _nanmean(var_b[nb], axis=1) / np.maximum(cnt, 1)
    b2 = np.where(np.isfinite(beta) & np.isfinite(var_b),
                  np.maximum(beta ** 2 - var_b, 0.0), 0.0)       # (N, 2)
    bias = np.sqrt(b2[None] * cc ** 2)                            # (H, N, 2)
    tot = np.where(fin, np.sqrt(S ** 2 + bias ** 2), np.inf).max(-1)   # (H, N)
    # a subset whose residual exceeds the noise by more than the chi-square scatter does
    # not fit an affine map even with the bias (a step, a crack): chosen only when no
    # size fits, then the smallest converged one (its misfit is the least)
    scatter = np.array([3 * np.sqrt(2.0 / max((2 * h + 1) ** 2 - 6, 1)) for h in hs])
    fits = np.stack([r.residual_ratio for r in runs]) <= 1 + scatter[:, None]
    tot_fit = np.where(fits, tot, np.inf)
    ok = tot_fit <= target
    conv = np.isfinite(tot).any(0)
    any_fit = np.isfinite(tot_fit).any(0)
    choice = np.where(ok.any(0), np.argmax(ok, 0),
                      np.where(any_fit, np.argmin(tot_fit, 0), np.argmax(np.isfinite(tot), 0)))
    best = _empty(n, noise_sigma)
    for k in range(nh):
        rows = np.flatnonzero(conv & (choice == k))
        if len(rows):
            best = _assign(best, rows, runs[k], rows)
    idx = np.arange(n)
    # no target (0): a point is at its optimum where a fitting size was chosen
    met = conv & (any_fit if target == 0 else ok[choice, idx])
    t_ch = tot[choice, idx]
    reason = np.array(best.reason, dtype=object)
    for i in np.flatnonzero(~conv):     # IC-GN's own reason at the largest size
        why = runs[-1].reason[i] or ("its texture does not stand above the image noise "
                                     "(predicted σ infinite)")
        reason[i] = f"no subset converged (half sizes {hs[0]}–{hs[-1]} px; at {hs[-1]}: {why})"
    for i in np.flatnonzero(conv & ~met):
        reason[i] = (f"{TARGET_MISSED} (total error {t_ch[i]:.3f} px: sigma and curvature "
                     f"bias, at h={hs[choice[i]]}" + (")" if any_fit[i] else
                                                      "; its residual exceeds the noise "
                                                      "at every size: shape misfit)"))
    if n:
        best = replace(best, reason=reason.astype(str))
    hw = np.where(conv, np.asarray(hs)[choice], 0)
    b_ch = np.where(conv, bias[choice, idx].max(-1), np.nan)
    # the error bar's bias term: expected squared bias given the ladder, at the chosen size
    beta_n, var_n = _nested_bias(U, S, fin, c)
    if kk > 1:
        cnt_n = np.isfinite(beta_n[nb]).sum(1)
        beta_n = _nanmean(beta_n[nb], axis=1)
        var_n = _nanmean(var_n[nb], axis=1) / np.maximum(cnt_n, 1)
    ms = np.where(np.isfinite(beta_n) & np.isfinite(var_n), beta_n ** 2 + var_n, 0.0)
    b_rms = np.where(conv, np.sqrt(ms).max(-1) * c[choice], np.nan)
    return AdaptiveResult(subset=best, half_window=hw,
                          shape_function=np.where(conv, warp, "").astype(str),
                          target_met=met, target_sigma_px=target, bias_px=b_ch,
                          bias_rms_px=b_rms)


def _nested_bias(U, S, fin, c):
    """Bias coefficient of nested subsets' matches from their increments, and its variance.

    For nested subsets the match of the larger one shares the smaller one's pixels: under
    noise alone (and information spread like the pixels) the matches behave like
    cumulative means, whose increments between successive sizes are independent with
    variance ``σ_k² − σ_{k+1}²``. With ``u_h = u + β c_h + noise`` the increments are
    ``β Δc_k + ε_k``, and the generalised least-squares estimate is
    ``β̂ = Σ Δc_k Δu_k / v_k / Σ Δc_k² / v_k``, ``var β̂ = 1 / Σ Δc_k² / v_k``
    (``v_k = σ_k² − σ_{k+1}²``; increments with ``v_k <= 0`` or between unconverged sizes
    are skipped; a skipped size joins the next converged one). Treating the matches as
    independent (as the weighted fit of :func:`_total_error_select` does) spreads its
    variance estimate over the whole ladder: ``(σ_first² − σ_last²) / Δc²`` is several
    times this one.

    Parameters
    ----------
    U, S : (H, N, 2) arrays
        Matches (px) and their noise σ (px) over the H sizes of the ladder.
    fin : (H, N, 2) bool array
        Usable entries.
    c : (H,) array
        ``h (h + 1) / 6`` of each size.

    Returns
    -------
    beta, var : (N, 2) arrays (NaN where fewer than two usable sizes).
    """
    nh = len(c)
    a = np.zeros(U.shape[1:])
    b = np.zeros(U.shape[1:])
    # the previous usable size of every point and component, walking up the ladder
    prev_u = np.where(fin[0], U[0], np.nan)
    prev_s = np.where(fin[0], S[0], np.nan)
    prev_c = np.where(fin[0], c[0], np.nan)
    for k in range(1, nh):
        with np.errstate(invalid="ignore"):
            v = prev_s ** 2 - S[k] ** 2
            use = fin[k] & np.isfinite(prev_u) & (v > 0)
        dc = np.where(use, c[k] - prev_c, 0.0)
        vv = np.where(use, v, 1.0)
        a += np.where(use, dc ** 2 / vv, 0.0)
        b += np.where(use, dc * (np.where(use, U[k], 0.0) - np.where(use, prev_u, 0.0)) / vv,
                      0.0)
        prev_u = np.where(fin[k], U[k], prev_u)
        prev_s = np.where(fin[k], S[k], prev_s)
        prev_c = np.where(fin[k], c[k], prev_c)
    ok = a > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        return (np.where(ok, b / np.where(ok, a, 1.0), np.nan),
                np.where(ok, 1.0 / np.where(ok, a, 1.0), np.nan))


def _nanmean(a, axis):
    """Mean along ``axis`` ignoring NaN; NaN where all are NaN (no warning)."""
    f = np.isfinite(a)
    cnt = f.sum(axis)
    return np.where(cnt > 0, np.where(f, a, 0.0).sum(axis) / np.maximum(cnt, 1), np.nan)


def _empty(n, noise_sigma):
    return SubsetResult(pts=np.full((n, 2), np.nan), warp=np.full((n, 6), np.nan),
                        zncc=np.full(n, -1.0), converged=np.zeros(n, bool),
                        n_iter=np.zeros(n, int), sigma_px=np.full((n, 2), np.nan),
                        reason=np.full(n, "no subset tried", dtype=object),
                        residual_ratio=np.full(n, np.nan),
                        noise_sigma=np.full(2, np.nan))


def _assign(best, rows, r, k):
    """best with rows ``rows`` replaced by rows ``k`` of r (a new object)."""
    out = {"noise_sigma": r.noise_sigma}
    for f in ("pts", "warp", "zncc", "converged", "n_iter", "sigma_px", "reason",
              "residual_ratio"):
        a = np.array(getattr(best, f), dtype=object if f == "reason" else None)
        a[rows] = getattr(r, f)[k]
        out[f] = a
    return replace(best, **out)


def _ladder(h_min, h_max):
    """Subset half sizes from h_min to h_max growing by ~1.4 (√2: twice the pixels)."""
    hs = [int(h_min)]
    while hs[-1] < h_max:
        nxt = min(int(h_max), max(hs[-1] + 1, int(round(hs[-1] * 1.4))))
        # no step of a few percent at the top (39 then 40): go straight to h_max
        hs.append(int(h_max) if nxt * 1.15 >= h_max else nxt)
    return tuple(hs)


def _grid_icgn(ref_img, img, pts, guess, half_window, warp, init_warp, smooth_sigma_px,
               ref_coef, cur_coef, target_sigma_px, max_half_window, bias="none", **kw):
    """IC-GN of the square subsets, fixed or sized by ``target_sigma_px``.

    Returns the SubsetResult and the (N,) half sizes used, and unless ``bias`` is
    ``"none"`` the (N,) curvature bias in pixels of :func:`adaptive_icgn` with
    ``curvature_neighbours`` (0 without): ``"signed"`` its ``AdaptiveResult.bias_px``,
    ``"rms"`` its ``bias_rms_px``.
    """
    if bias not in ("none", "signed", "rms"):
        raise SemlabError(f"bias must be 'none', 'signed' or 'rms', got {bias!r}")
    if target_sigma_px is None:
        r = icgn_refine(ref_img, img, pts, guess, half_window=half_window, warp=warp,
                        init_warp=init_warp, smooth_sigma_px=smooth_sigma_px,
                        ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, **kw)
        hw = np.full(len(pts), int(half_window))
        return (r, hw) if bias == "none" else (r, hw, np.zeros(len(pts)))
    kw.pop("progress", None)
    a = adaptive_icgn(ref_img, img, pts, guess, target_sigma_px,
                      half_windows=_ladder(half_window, max(half_window, max_half_window)),
                      init_warp=init_warp, smooth_sigma_px=smooth_sigma_px,
                      ref_prefiltered=ref_coef, cur_prefiltered=cur_coef, **kw)
    # a point that missed the target is still a match (its sigma says how good)
    reason = np.where(a.subset.converged, "", a.subset.reason)
    if bias != "none":
        b = a.bias_rms_px if bias == "rms" else a.bias_px
        bias_px = np.zeros(len(pts)) if b is None else np.nan_to_num(b)
        return replace(a.subset, reason=reason), np.maximum(a.half_window, 0), bias_px
    return replace(a.subset, reason=reason), np.maximum(a.half_window, 0)
