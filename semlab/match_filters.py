"""Outlier filters of automatic matching (stage 3 of :func:`semlab.matching.auto_match`).

One local-median outlier test (:func:`_local_outliers`), a local-plane roughness test
(:func:`_parallax_gradients`), the forward–backward IC-GN distance
(:func:`_backward_distance`) and the multi-view rank-2 residual
(:func:`_multiview_residual`).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .match_epipolar import epipolar_refine
from .subset import icgn_refine
from .stats import MAD_TO_SIGMA, robust_sd


def _parallax_gradients(xy, par, k=12, return_residual=False, quadratic=False):
    """Gradient of a scattered parallax field by local least-squares planes (k neighbours).

    Returns (n, 2) gradients, and with ``return_residual`` also the RMS residual (n,) of
    each local plane. ``quadratic``: fit local quadrics instead (curved parallax fields of
    tall objects), residuals of those; the first output is then (n, 5): the gradient and
    the coefficients ``(a, b, c)`` of ``a dx² + b dx dy + c dy²`` (per pixel²)."""
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
    coef = sol[:, 1:].copy()
    if quadratic:
        coef[:, 2:] /= sc ** 2                                     # per pixel²
    if return_residual:
        res = y - np.einsum("nki,ni->nk", X, sol)
        return coef, np.sqrt(np.mean(res ** 2, axis=1))
    return coef


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
    return np.abs(values - med) > np.maximum(n_mad * MAD_TO_SIGMA * mad, thresh_floor)


def _backward_distance(img, ref_img, pts, pts_ref, warp, half_window, smooth_sigma_px,
                       img_coef, ref_coef, max_iter, tol_px, direction=None,
                       return_sigma=False):
    """Distance (pixels) between ``pts_ref`` and the backward IC-GN match of ``pts`` (in
    ``img``) into ``ref_img``, started at ``pts_ref`` with the inverse of the forward warp
    gradient (NaN where the backward match fails). With ``return_sigma`` also the backward
    match's predicted 1σ (pixels, the larger of its x and y, a posteriori: see
    :func:`semlab.match_sigma.aposteriori_sigma`). With ``direction`` (the forward
    epipolar direction ``e``) the backward match is along the epipolar direction only
    (:func:`semlab.match_epipolar.epipolar_refine`, direction ``A⁻¹ e`` in the reference),
    as the forward one was."""
    g = np.where(np.isfinite(warp), warp, 0.0)
    A = np.stack([np.stack([1 + g[:, 1], g[:, 2]], 1), np.stack([g[:, 4], 1 + g[:, 5]], 1)], 1)
    det = np.linalg.det(A)
    A[np.abs(det) < 1e-6] = np.eye(2)
    B = np.linalg.inv(A) - np.eye(2)
    z = np.zeros(len(pts))
    init = np.column_stack([z, B[:, 0, 0], B[:, 0, 1], z, B[:, 1, 0], B[:, 1, 1]])
    if direction is not None:

        d = np.einsum("nij,j->ni", np.linalg.inv(A), np.asarray(direction, float))
        r = epipolar_refine(img, ref_img, pts, pts_ref, d, half_window, init,
                            max_iter=max_iter, tol_px=tol_px, smooth_sigma_px=smooth_sigma_px,
                            ref_prefiltered=img_coef, cur_prefiltered=ref_coef)
    else:
        r = icgn_refine(img, ref_img, pts, pts_ref, half_window=half_window, init_warp=init,
                        smooth_sigma_px=smooth_sigma_px, ref_prefiltered=img_coef,
                        cur_prefiltered=ref_coef, max_iter=max_iter, tol_px=tol_px)
    dist = np.hypot(*(r.pts - pts_ref).T)
    if not return_sigma:
        return dist
    from .match_sigma import aposteriori_sigma   # match_sigma imports this module

    sig = np.fmax(r.sigma_px[:, 0], r.sigma_px[:, 1]) if len(r.pts) else np.zeros(0)
    return dist, aposteriori_sigma(sig, r.residual_ratio)


def _multiview_residual(pts, ref, mask, n_iter=3, n_mad=4.0, floor_px=0.0, seed=0,
                        view_mask=None):
    """Per-point residual (pixels) of the multi-view x coordinates to a rank-2 model.

    For an affine camera tilted about an axis near the image y axis, the x coordinates of a
    point in V views are ``u_i = cos θ_i x + sin θ_i z + ε_i y + t_i``: after removing the
    linear dependence on the reference-view y (a slightly rotated tilt axis) and the means,
    the N × V matrix of x coordinates has rank 2 (Tomasi & Kanade 1992; Hartley & Zisserman
    2nd ed. section 18.2). The rank-2 fit starts from the least-median-of-squares subspace
    of ``mask`` points (:func:`_lmeds_rank2`: the height direction is spanned by the small
    parallax, so a least-squares fit turns it towards a group of points wrong in one view
    and hides them), and is re-fitted without the points beyond
    ``max(n_mad · 1.4826 MAD, floor_px)``; each point's residual is the RMS over views of
    its distance to the fitted model. Needs V >= 3 (else zeros).

    ``view_mask`` (N, V) bool, optional: rows valid in only some views (at least 3, the
    reference among them) are tested against the model fitted on ``mask``: their ``(x, z)``
    fitted to their own views, the residual scaled to the full rows' (its sum of squares per
    degree of freedom, ``|S| - 2`` of them, times ``(V - 2) / V``); rows with fewer views
    get NaN.

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
    use = _lmeds_rank2(D, use, seed)
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
        thr = max(n_mad * robust_sd(r_in) + np.median(r_in), floor_px)
        new = mask & fin & (res <= thr)
        if new.sum() < 8 or np.array_equal(new, use):
            break
        use = new
    res[~fin] = np.nan
    if view_mask is not None:
        vm = np.asarray(view_mask, bool)
        part = ~vm.all(axis=1)
        res[part] = np.nan
        basis = vt[:2].T                        # (V, 2) the fitted rank-2 subspace
        for pattern in np.unique(vm[part & (vm.sum(1) >= 3) & vm[:, ref]], axis=0):
            rows = np.flatnonzero((vm == pattern).all(axis=1))
            dc = np.where(pattern, U[rows], 0.0) - mu[:-1]
            rr = (dc - (y[rows] - mu[-1])[:, None] * beta)[:, pattern]
            coef = np.linalg.lstsq(basis[pattern], rr.T, rcond=None)[0]
            e2 = np.sum((rr - (basis[pattern] @ coef).T) ** 2, axis=1)
            res[rows] = np.sqrt(e2 / (pattern.sum() - 2) * (v - 2) / v)
    return res, float(np.sqrt(np.mean(res[use] ** 2)))


def _lmeds_rank2(D, use, seed, n_trial=300, quantile=0.8):
    """Inliers of the least-quantile-of-squares rank-2 model of the rows of ``D`` (N, V+1):
    x coordinates in V views and the reference y (Rousseeuw 1984, J. Am. Stat. Assoc.
    79(388), with the ``quantile`` instead of the median: where most of the surface is flat
    the median points carry no parallax and do not fix the height direction). The linear
    dependence on y is removed by least squares over the ``use`` rows (on a grid, y is
    independent of the material x); each trial is the plane through three sampled rows
    (its offset included: the median of grid coordinates jumps by a grid step when a few
    points move), the one with the smallest ``quantile`` of squared residuals wins and
    its inliers are the rows within 3 σ, σ² from that quantile as of a χ² with V − 2
    degrees of freedom. Returns ``use`` itself when there are under 8 rows."""
    from scipy.stats import chi2

    idx = np.flatnonzero(use)
    if len(idx) < 8:
        return use
    X = D[idx] - D[idx].mean(axis=0)
    yc = X[:, -1]
    beta = (X[:, :-1] * yc[:, None]).sum(0) / max((yc ** 2).sum(), 1e-12)
    R = X[:, :-1] - yc[:, None] * beta
    rng = np.random.default_rng(seed)
    best, best_q = None, np.inf
    for _ in range(n_trial):
        a, b, c = R[rng.choice(len(idx), 3, replace=False)]
        q, rr = np.linalg.qr(np.stack([b - a, c - a], 1))
        if abs(rr[1, 1]) < 1e-9 * max(abs(rr[0, 0]), 1e-12):
            continue
        Ra = R - a
        e2 = np.sum((Ra - (Ra @ q) @ q.T) ** 2, 1)
        qv = float(np.quantile(e2, quantile))
        if qv < best_q:
            best, best_q = e2, qv
    if best is None:
        return use
    dof = R.shape[1] - 2
    sig2 = best_q / chi2.ppf(quantile, dof)
    out = np.zeros_like(use)
    out[idx] = best <= chi2.ppf(0.997, dof) * sig2
    return out if out.sum() >= 8 else use
