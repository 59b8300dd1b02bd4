"""Subsets matched along the epipolar direction only (one unknown shift, plus its gradient).

In affine SEM views of a tilt series, every surface point moves between two views along
one direction ``e`` (the parallax direction: x for a tilt about the image y axis); the
component across it is fixed by the global affine map of the pair (the affine epipolar
constraint, Hartley & Zisserman 2nd ed. section 14.2). Where a subset's texture only
constrains one direction (machined grooves, scratches, slip bands running across ``e``)
the 2D IC-GN of :mod:`semlab.subset` has a singular or ill-conditioned Hessian and wanders
along the grooves, although the quantity stereo needs, the shift along ``e``, is well
defined. :func:`epipolar_refine` estimates only that: the subset is
``W(ξ) = c + A ξ + (s + a·ξ) e`` with the cross-parallax position ``c`` and the linear
part ``A`` held at the prior (e.g. the global affine map's, with the flow's gradient), and
``s`` (shift along ``e``) and ``a = (a_x, a_y)`` (its gradient, the parallax slope)
estimated by Gauss–Newton on the zero-normalised SSD (Lucas–Kanade, with the reference
gradients as Jacobian). Three parameters instead of six: the information along ``e``
alone decides.

The predicted 1σ of ``s`` is the Gauss–Newton covariance of :func:`semlab.subset.icgn_refine`
reduced to these three parameters: ``s² H0⁻¹ Hk H0⁻¹`` with ``H0`` the Hessian of the
reference gradients along ``e`` less their noise energy, ``Hk`` that of the smoothed
gradients, and ``s² = s_f² + (Δf/Δg)² s_g²`` from the measured image noise; for white noise,
noise-free gradients and a translation this is ``2σ² / Σ (∂f/∂e)²``, Pan's SSSIG bound
(Opt. Express 16(10), 2008). The residual variance over the noise's is returned as
``residual_ratio`` (above 1 where the shift is not affine over the subset), for the a
posteriori factor of :func:`semlab.match_sigma.aposteriori_sigma`.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ._validate import _as_image, _as_points, _check_int
from .bspline import _smooth, _smoothing_variance_gain, _spline_gradients, prefilter_image
from .errors import SemlabError
from .subset import (DIVERGED, MAX_ITER, NO_TEXTURE, OUTSIDE, SubsetResult,
                     _gradient_noise_gain, _interp_noise_gain, _noise_variances)

__all__ = ["epipolar_refine"]

_CHUNK = 256     # subsets per vectorised block


def epipolar_refine(ref_img, cur_img, pts_ref, pts_guess, direction, half_window=10,
                    init_warp=None, *, shape="auto", search_px=0, max_iter=40, tol_px=1e-3,
                    smooth_sigma_px=0.0,
                    noise_sigma=None, ref_prefiltered=None, cur_prefiltered=None):
    """Match subsets along the epipolar direction only (1-D shift with its gradient).

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current grey images.
    pts_ref : (N, 2) array of (x, y) in pixels
        Subset centres in ``ref_img`` (rounded to the nearest pixel for the subset; the
        sub-pixel offset is carried by the warp).
    pts_guess : (N, 2) array of (x, y) in pixels
        Prior positions in ``cur_img``. Their component across ``direction`` is kept (it
        is the epipolar line); along it they are the starting point.
    direction : (2,) or (N, 2) array
        Epipolar direction ``e`` (x, y) in ``cur_img``, normalised here.
    half_window : int
        Subset half size ``h``: ``(2h+1)²`` pixels.
    init_warp : (N, 6) or (6,) array, optional
        ``(u, du/dx, du/dy, v, dv/dx, dv/dy)``; its gradient terms give the held linear part
        ``A = I + ∇u`` (e.g. the x-scale of a tilt pair). Default: identity.
    shape : {"auto", "gradient", "translation"}
        Shape function along ``e``: ``"gradient"`` estimates the shift and its gradient
        (3 parameters), ``"translation"`` the shift alone (the gradient held at
        ``init_warp``'s); ``"auto"`` the first, then the second where it fails
        (diverged, not converged, singular: a parallax slope the subset cannot resolve,
        e.g. the x-scale of nearly periodic grooves).
    search_px : int
        First an integer search along ``e`` within ``±search_px`` of the guess (ZNCC of
        the subset warped by the held linear part, bilinear samples); Gauss–Newton starts
        at the best. 0: start at the guess.
    max_iter : int
        Gauss–Newton iterations.
    tol_px : float
        Convergence when the RMS change of the subset's warped positions is below this.
    smooth_sigma_px : float
        Gaussian pre-smoothing of both images (as :func:`semlab.subset.icgn_refine`).
    noise_sigma : None, float or (σ_ref, σ_cur)
        White-noise standard deviation of the unsmoothed images (grey units) for
        ``sigma_px``; None measures it from each image
        (:func:`semlab.noise.image_noise_sigma`).
    ref_prefiltered, cur_prefiltered : (H, W) arrays, optional
        B-spline coefficients from :func:`semlab.bspline.prefilter_image` with the same
        ``smooth_sigma_px``.

    Returns
    -------
    SubsetResult
        ``pts`` (N, 2) matched (x, y) in ``cur_img``; ``warp`` the full affine warp
        (gradient along ``e`` included); ``sigma_px`` (N, 2) the predicted 1σ of the shift
        along ``e`` projected on x and y (``|e_x| σ_s``, ``|e_y| σ_s``); ``zncc``;
        ``converged`` and ``reason`` (leaves the image, no texture along ``e``, diverged:
        moved more than ``h`` along ``e`` or a parallax slope beyond ±0.5, or not converged
        within ``max_iter``); ``residual_ratio`` the subset's residual variance (÷ the
        smoothing and interpolation gains) over the noise-predicted ``s²``; ``noise_sigma``
        the (σ_ref, σ_cur) used.

    Raises
    ------
    SemlabError
        On wrong shapes or parameters.
    """
    ref = _as_image(ref_img, "ref_img")
    cur = _as_image(cur_img, "cur_img")
    h = _check_int(half_window, "half_window", 2)
    max_iter = _check_int(max_iter, "max_iter", 1)
    pr = _as_points(pts_ref, "pts_ref")
    n = len(pr)
    pg = _as_points(pts_guess, "pts_guess", n)
    e = np.asarray(direction, float)
    e = np.broadcast_to(e, (n, 2)) if e.shape == (2,) else e
    if e.shape != (n, 2):
        raise SemlabError(f"direction must be (2,) or (N, 2) = ({n}, 2), got {np.shape(direction)}")
    nrm = np.hypot(e[:, 0], e[:, 1])
    if not np.all(nrm > 0):
        raise SemlabError("direction must be a non-zero (x, y) vector")
    e = e / nrm[:, None]
    A0 = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    if init_warp is not None:
        iw = np.broadcast_to(np.asarray(init_warp, float), (n, 6))
        g = np.where(np.isfinite(iw), iw, 0.0)
        A0 += np.stack([np.stack([g[:, 1], g[:, 2]], 1), np.stack([g[:, 4], g[:, 5]], 1)], 1)
    rcoef = prefilter_image(ref, smooth_sigma_px) if ref_prefiltered is None else \
        np.asarray(ref_prefiltered, float)
    ccoef = prefilter_image(cur, smooth_sigma_px) if cur_prefiltered is None else \
        np.asarray(cur_prefiltered, float)
    rgx, rgy = _spline_gradients(rcoef)
    kg = (rgx, rgy) if not smooth_sigma_px else tuple(_smooth(g, smooth_sigma_px)
                                                       for g in (rgx, rgy))
    sf2, sg2 = _noise_variances(noise_sigma, ref, cur)
    noise = dict(sf2=sf2, sg2=sg2, grad_gain=_gradient_noise_gain(smooth_sigma_px),
                 gain=_smoothing_variance_gain(smooth_sigma_px) * _interp_noise_gain())
    rval = ndimage.correlate1d(ndimage.correlate1d(rcoef, [1 / 6, 4 / 6, 1 / 6], axis=0,
                                                   mode="mirror"),
                               [1 / 6, 4 / 6, 1 / 6], axis=1, mode="mirror")
    off = np.arange(-h, h + 1, dtype=float)
    oy, ox = np.meshgrid(off, off, indexing="ij")
    xi = np.stack([ox.ravel(), oy.ravel()])                  # (2, P)

    pts = np.full((n, 2), np.nan)
    warp = np.full((n, 6), np.nan)
    zncc = np.full(n, -1.0)
    conv = np.zeros(n, bool)
    nit = np.zeros(n, int)
    sig = np.full((n, 2), np.nan)
    rres = np.full(n, np.nan)
    reason = np.full(n, "NaN input point", dtype=object)
    finite = np.all(np.isfinite(pr), 1) & np.all(np.isfinite(pg), 1)
    X0 = np.zeros((n, 2), int)
    X0[finite] = np.rint(pr[finite]).astype(int)
    H, W = ref.shape
    inside = finite & np.all(X0 >= h, 1) & (X0[:, 0] <= W - 1 - h) & (X0[:, 1] <= H - 1 - h)
    reason[finite & ~inside] = OUTSIDE
    if shape not in ("auto", "gradient", "translation"):
        raise SemlabError(f"shape must be 'auto', 'gradient' or 'translation', got {shape!r}")
    idx = np.flatnonzero(inside)
    for nb in ((3, 1) if shape == "auto" else (3,) if shape == "gradient" else (1,)):
        for k in range(0, len(idx), _CHUNK):
            ii = idx[k:k + _CHUNK]
            out = _chunk(rval, rgx, rgy, kg, noise, ccoef, xi, X0[ii], pr[ii], pg[ii], e[ii],
                         A0[ii], h, max_iter, tol_px, int(search_px), nb)
            pts[ii], warp[ii], zncc[ii], conv[ii], nit[ii], sig[ii], reason[ii], rres[ii] = out
        idx = idx[~conv[idx] & (reason[idx] != OUTSIDE)]
    return SubsetResult(pts=pts, warp=warp, zncc=zncc, converged=conv, n_iter=nit,
                        sigma_px=sig, reason=reason.astype(str),
                        residual_ratio=rres, noise_sigma=np.sqrt(np.array([sf2, sg2])))


def _search(ccoef, base, Axi, e, fz, df, search):
    """Best integer shift along ``e`` (ZNCC, bilinear samples of the spline coefficients,
    enough to pick the peak) within ±search, refined by a
    parabola through the peak and its neighbours; 0 where every candidate leaves the image."""
    m, _, P = Axi.shape
    Hc, Wc = ccoef.shape
    ts = np.arange(-search, search + 1, dtype=float)
    zs = np.full((m, len(ts)), -2.0)
    for k, t in enumerate(ts):
        X = base[:, :, None] + Axi + (t * e)[:, :, None]
        inside = (X[:, 0].min(1) >= 1) & (X[:, 1].min(1) >= 1) & (X[:, 0].max(1) <= Wc - 2) & \
            (X[:, 1].max(1) <= Hc - 2)
        if not inside.any():
            continue
        Xi = X[inside]
        g = ndimage.map_coordinates(ccoef, [Xi[:, 1].ravel(), Xi[:, 0].ravel()], order=1,
                                    prefilter=False, mode="mirror").reshape(len(Xi), P)
        gz = g - g.mean(1, keepdims=True)
        dg = np.sqrt(np.einsum("np,np->n", gz, gz)) + 1e-300
        zs[inside, k] = np.einsum("np,np->n", fz[inside], gz) / (df[inside] * dg)
    best = np.argmax(zs, 1)
    s = ts[best].copy()
    inner = (best > 0) & (best < len(ts) - 1)
    i = np.flatnonzero(inner)
    zl, zc, zr = zs[i, best[i] - 1], zs[i, best[i]], zs[i, best[i] + 1]
    den = zl - 2 * zc + zr
    okp = (den < 0) & (zl > -2) & (zr > -2)
    s[i[okp]] += 0.5 * (zl[okp] - zr[okp]) / den[okp]
    s[zs.max(1) <= -2] = 0.0
    return s


def _chunk(rval, rgx, rgy, kg, noise, ccoef, xi, X0, pr, pg, e, A0, h, max_iter, tol, search,
           nb=3):
    """Gauss–Newton along ``e`` for one block of m subsets (see :func:`epipolar_refine`)."""
    m, P = len(X0), xi.shape[1]
    ry = X0[:, 1, None] + xi[1].astype(int)[None]
    rx = X0[:, 0, None] + xi[0].astype(int)[None]
    f = rval[ry, rx]
    fz = f - f.mean(1, keepdims=True)
    df = np.sqrt(np.einsum("np,np->n", fz, fz))
    # ∂g(W)/∂s ≈ ∇f · A⁻¹ e (at the match ∇f = Aᵀ ∇g)
    ep = np.linalg.solve(A0, e[:, :, None])[:, :, 0]
    ge = rgx[ry, rx] * ep[:, :1] + rgy[ry, rx] * ep[:, 1:]
    B = np.stack([np.ones(P), xi[0], xi[1]], 1)[:, :nb]      # (P, nb) shape basis
    J = ge[:, :, None] * B[None]                              # (m, P, 3)
    J -= J.mean(1, keepdims=True)
    Hs = np.einsum("npi,npj->nij", J, J)
    kge = kg[0][ry, rx] * ep[:, :1] + kg[1][ry, rx] * ep[:, 1:]
    Jk = kge[:, :, None] * B[None]
    Jk -= Jk.mean(1, keepdims=True)
    Hk = np.einsum("npi,npj->nij", Jk, Jk)
    scale = np.sqrt(np.einsum("nii->ni", Hs)) + 1e-300
    ev = np.linalg.eigvalsh(Hs / scale[:, :, None] / scale[:, None, :])[:, 0]
    textured = (df > 1e-8) & (scale[:, 0] > 1e-8 * (np.abs(f).max(1) + 1)) & (ev > 1e-6)
    Hinv = np.zeros_like(Hs)
    Hinv[textured] = np.linalg.inv(Hs[textured])
    o = pr - X0
    base = pg - np.einsum("nij,nj->ni", A0, o)               # guess of the integer centre
    Axi = np.einsum("nij,jp->nip", A0, xi)                   # (m, 2, P)
    s = _search(ccoef, base, Axi, e, fz, df, search) if search > 0 else np.zeros(m)
    s0 = s.copy()
    a = np.zeros((m, 2))
    status = np.where(textured, 0, 2)                        # 0 active, 1 done, 2 failed
    why = np.where(textured, "", NO_TEXTURE).astype(object)
    nit = np.zeros(m, int)
    zn = np.full(m, -1.0)
    r_var = np.full(m, np.nan)
    dgs = np.full(m, np.nan)
    Hc, Wc = ccoef.shape
    for it in range(max_iter):
        act = np.flatnonzero(status == 0)
        if len(act) == 0:
            break
        d = s[act, None] + a[act] @ xi                        # (k, P) shift along e
        X = base[act, :, None] + Axi[act] + d[:, None, :] * e[act, :, None]
        out = (X[:, 0].min(1) < 1) | (X[:, 1].min(1) < 1) | (X[:, 0].max(1) > Wc - 2) | \
            (X[:, 1].max(1) > Hc - 2)
        status[act[out]], why[act[out]] = 2, OUTSIDE
        keep = ~out
        act, X = act[keep], X[keep]
        if len(act) == 0:
            break
        g = ndimage.map_coordinates(ccoef, [X[:, 1].ravel(), X[:, 0].ravel()], order=3,
                                    prefilter=False, mode="mirror").reshape(len(act), P)
        gz = g - g.mean(1, keepdims=True)
        dg = np.sqrt(np.einsum("np,np->n", gz, gz)) + 1e-300
        dgs[act] = dg
        r = gz * (df[act] / dg)[:, None] - fz[act]           # residual in reference units
        zn[act] = np.einsum("np,np->n", fz[act], gz) / (df[act] * dg)
        r_var[act] = np.einsum("np,np->n", r, r) / max(P - nb - 2, 1)
        dp = -np.einsum("nij,nj->ni", Hinv[act], np.einsum("npi,np->ni", J[act], r))
        s[act] += dp[:, 0]
        if nb == 3:
            a[act] += dp[:, 1:]
        nit[act] = it + 1
        step = np.sqrt(dp[:, 0] ** 2 + (dp[:, 1:] ** 2) @ np.mean(xi ** 2, 1)) \
            if nb == 3 else np.abs(dp[:, 0])
        bad = (np.abs(s[act] - s0[act]) > h) | np.any(np.abs(a[act]) > 0.5, 1) | ~np.isfinite(step)
        status[act[bad]], why[act[bad]] = 2, DIVERGED
        done = ~bad & (step < tol)
        status[act[done]] = 1
    why[status == 0] = MAX_ITER
    ok = status == 1
    # final position of the sub-pixel reference point and the full warp
    cen = base + np.einsum("nij,nj->ni", A0, o) + (s + np.einsum("ni,ni->n", a, o))[:, None] * e
    A = A0 + e[:, :, None] * a[:, None, :]
    wout = np.column_stack([cen[:, 0] - pr[:, 0], A[:, 0, 0] - 1, A[:, 0, 1],
                            cen[:, 1] - pr[:, 1], A[:, 1, 0], A[:, 1, 1] - 1])
    # covariance s² H0⁻¹ Hk H0⁻¹ (see the module docstring); the noise energy of the
    # centred gradient columns is s_f² γ |A⁻¹e|² Bcᵀ Bc (P − 1 for the constant column)
    Bc = B - B.mean(0)
    BtB = Bc.T @ Bc
    BtB[0, 0] = P - 1
    H0 = Hs - (noise["sf2"] * noise["grad_gain"] * np.sum(ep ** 2, 1))[:, None, None] * BtB
    good = ok & np.all(np.isfinite(H0), axis=(1, 2))
    good[good] &= np.linalg.eigvalsh(H0[good])[:, 0] > 0
    H0i = np.zeros_like(Hs)
    H0i[good] = np.linalg.inv(H0[good])
    C = H0i @ Hk @ H0i
    s2 = noise["sf2"] + (df / dgs) ** 2 * noise["sg2"]
    rr = np.where(ok, r_var / noise["gain"] / np.maximum(s2, 1e-300), np.nan)
    var_s = np.where(good, C[:, 0, 0] * s2, np.inf)
    fin = np.isfinite(var_s)
    sig = np.full((m, 2), np.inf)
    sig[fin] = np.sqrt(np.maximum(var_s[fin], 0))[:, None] * np.abs(e[fin])
    nan2 = np.full((m, 2), np.nan)
    return (np.where(ok[:, None], cen, nan2), np.where(ok[:, None], wout, np.nan),
            zn, ok, nit, np.where(ok[:, None], sig, nan2), why, rr)
