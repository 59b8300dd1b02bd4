"""Planes ``z = a x + b y + c`` fitted to 3D points: robust, RANSAC, through three points.

A leaf module (numpy only) shared by :mod:`semlab.reconstruct` (levelling the estimated
tilts) and :mod:`semlab.surface` (the reference surface of the heights). Points are
``xyz`` : ``(N, 3)`` arrays of ``(x, y, z)`` in one unit (µm in semlab); planes are
``(3,)`` arrays ``(a, b, c)``.
"""

from __future__ import annotations

import numpy as np

from .errors import GeometryError
from .stats import robust_sd

__all__ = [
    "fit_reference_plane",
    "heights_above_plane",
    "plane_through_points",
    "ransac_plane",
]

_TUKEY_C = 4.685  # 95 % efficiency at the normal model
#: Without a given σ, the scale of the best RANSAC sample is this quantile of its |residuals|
#: (so the plane may hold as little as 20 % of the points), divided by the same quantile of
#: |N(0, 1)|, Φ⁻¹((1 + 0.2) / 2).
_SCALE_QUANTILE = 0.2
_HALF_NORMAL_Q = 0.2533


def _as_xyz(xyz, min_points=3):
    p = np.asarray(xyz, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise GeometryError(f"xyz_um must be an (N, 3) array of (x, y, z) µm, got shape {p.shape}")
    if p.shape[0] < min_points:
        raise GeometryError(f"need at least {min_points} points, got {p.shape[0]}")
    if not np.all(np.isfinite(p)):
        raise GeometryError("xyz_um holds NaN/inf: drop the points that failed to reconstruct")
    return p


def _wls_plane(a, z, w):
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(a * sw[:, None], z * sw, rcond=None)
    return coef


def _design(p):
    """Centred design matrix ``[x - x̄, y - ȳ, 1]`` and the centre, raising if collinear."""
    xy0 = p[:, :2].mean(axis=0)
    a = np.column_stack([p[:, 0] - xy0[0], p[:, 1] - xy0[1], np.ones(len(p))])
    sv = np.linalg.svd(a[:, :2], compute_uv=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-300):
        raise GeometryError("the points are collinear in (x, y): a plane needs points spread in 2D")
    return a, xy0


def _uncentre(coef, xy0):
    return np.array([coef[0], coef[1], coef[2] - coef[0] * xy0[0] - coef[1] * xy0[1]])


def fit_reference_plane(xyz_um, robust=True, max_iter=100, weights=None):
    """Fit the plane ``z = a x + b y + c`` of a surface.

    Robust fit (``robust=True``): an L1 fit (iteratively reweighted least squares, weights
    ``1/|r|``) as a start insensitive to one-sided extrusions, then Tukey-biweight IRLS
    with scale ``1.4826 · MAD`` of the residuals and ``c = 4.685`` (Huber & Ronchetti,
    *Robust Statistics*, 2nd ed., §7.8; Holland & Welsch 1977). Points far above or below
    the surface (extrusions, intrusions, bad matches) get zero weight, so up to roughly
    40 % of them do not tilt the plane; a tall object covering more of the view does: use
    :func:`ransac_plane` for the dominant flat surface. ``robust=False``: (weighted) least
    squares.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points ``(x, y, z)`` µm (any common unit works), N >= 3, not collinear in (x, y).
    robust : bool
        Robust (default) or least-squares fit.
    max_iter : int
        Iterations of each IRLS stage.
    weights : (N,) array_like, optional
        Least-squares weights (e.g. ``1/σ²``), only with ``robust=False``.

    Returns
    -------
    plane : (3,) array
        ``(a, b, c)`` with ``z = a x + b y + c`` (a, b dimensionless slopes).

    Raises
    ------
    GeometryError
        Wrong shape, NaNs, fewer than 3 points, or collinear (x, y).
    """
    p = _as_xyz(xyz_um)
    a, xy0 = _design(p)
    z = p[:, 2]
    w0 = np.ones(len(z)) if weights is None else np.asarray(weights, float).ravel()
    if w0.shape != z.shape or not np.all(np.isfinite(w0)) or np.any(w0 < 0):
        raise GeometryError(f"weights must be ({len(z)},) finite and >= 0")
    coef = _wls_plane(a, z, w0)
    if robust:
        zscale = np.std(z - a @ coef)
        if zscale > 0:
            eps = 1e-6 * zscale
            for _ in range(min(max_iter, 20)):  # L1 start: only needs to be near
                r = z - a @ coef
                new = _wls_plane(a, z, 1.0 / np.maximum(np.abs(r), eps))
                done = np.abs(new - coef).max() <= 1e-6 * (np.abs(coef).max() + 1e-300)
                coef = new
                if done:
                    break
            floor = 1e-9 * zscale
            for _ in range(max_iter):  # Tukey biweight
                r = z - a @ coef
                scale = max(robust_sd(r), floor)
                t = r / (_TUKEY_C * scale)
                w = np.where(np.abs(t) < 1, (1 - t ** 2) ** 2, 0.0)
                if np.count_nonzero(w) < 3:
                    break
                new = _wls_plane(a, z, w)
                done = np.abs(new - coef).max() <= 1e-12 * (np.abs(coef).max() + 1e-300)
                coef = new
                if done:
                    break
    return _uncentre(coef, xy0)


def heights_above_plane(xyz_um, plane):
    """Vertical height of each point above a plane ``z = a x + b y + c``.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points ``(x, y, z)`` µm.
    plane : (3,) array_like
        ``(a, b, c)`` from :func:`fit_reference_plane`.

    Returns
    -------
    z_um : (N,) array
        ``z - (a x + b y + c)`` µm; positive = extrusion, negative = intrusion.
    """
    p = _as_xyz(xyz_um, min_points=1)
    a, b, c = np.asarray(plane, float).ravel()[:3]
    return p[:, 2] - (a * p[:, 0] + b * p[:, 1] + c)


def plane_through_points(xyz3_um):
    """The plane ``z = a x + b y + c`` through three points (Gwyddion's three-point levelling).

    Parameters
    ----------
    xyz3_um : (3, 3) array
        Three points ``(x, y, z)``, not collinear in (x, y).

    Returns
    -------
    plane : (3,) array
        ``(a, b, c)``.
    """
    p = _as_xyz(xyz3_um)
    if len(p) != 3:
        raise GeometryError(f"a plane through three points needs exactly 3 points, got {len(p)}")
    a = np.column_stack([p[:, :2], np.ones(3)])
    if abs(np.linalg.det(a)) <= 1e-12 * max(np.abs(p[:, :2]).max(), 1.0) ** 2:
        raise GeometryError("the three points are collinear in (x, y): pick points that span "
                            "a triangle")
    return np.linalg.solve(a, p[:, 2])


def _sample_planes(a, z, samples):
    """Planes (S, 3) in centred coordinates through each triple of ``samples`` (S, 3)."""
    A = a[samples]                                     # (S, 3, 3)
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-12 * np.abs(A[:, :, :2]).max(axis=(1, 2)) ** 2
    coef = np.full((len(samples), 3), np.nan)
    coef[ok] = np.linalg.solve(A[ok], z[samples[ok]][..., None])[..., 0]
    return coef


def ransac_plane(xyz_um, sigma_um=None, k_sigma=3.0, n_iter=1000, seed=0, min_inliers=3):
    """The dominant plane of a point set: the largest set of points consistent with one plane.

    RANSAC (Fischler & Bolles 1981) over random point triples, each scored by the number of
    points within ``k_sigma · σ_i`` of its plane (ties broken by the smaller sum of squared
    normalised residuals, MSAC, Torr & Zisserman 2000), then weighted least squares
    (``1/σ_i²``) on the inliers, re-selecting the inliers until they no longer change.
    Unlike a robust fit through everything, a tall object or a rough region covering most
    of the view does not tilt the plane, as long as the flat surface is the largest
    *consistent* set.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Points ``(x, y, z)`` µm, N >= 3.
    sigma_um : None, float or (N,) array_like
        1σ height error of each point (e.g. :func:`semlab.surface.height_sigma`). None:
        estimated from the points: first as the smallest 20 %-quantile of ``|r|`` over the
        samples (a least-quantile scale, Rousseeuw & Leroy 1987 §5.1, with the quantile
        lowered from the median so that the plane may hold only 20 % of the points), then
        as the RMS residual of the inliers while they are re-selected.
    k_sigma : float
        Inlier threshold in σ.
    n_iter : int
        Random triples tried.
    seed : int
        Random seed.
    min_inliers : int
        Fewer inliers than this raise.

    Returns
    -------
    plane : (3,) array
        ``(a, b, c)``.
    inliers : (N,) bool array
    sigma_um : (N,) array
        The σ used (given or estimated).

    Raises
    ------
    GeometryError
        Bad input, all samples degenerate, or fewer than ``min_inliers`` inliers.
    """
    p = _as_xyz(xyz_um)
    n = len(p)
    a, xy0 = _design(p)
    z = p[:, 2]
    rng = np.random.default_rng(seed)
    samples = np.array([rng.choice(n, 3, replace=False) for _ in range(int(n_iter))]) \
        if n > 3 else np.arange(3)[None, :]
    coef = _sample_planes(a, z, samples)
    good = np.all(np.isfinite(coef), axis=1)
    if not good.any():
        raise GeometryError("every RANSAC sample was collinear in (x, y): spread the points in 2D")
    coef = coef[good]
    chunks = [slice(i, i + 64) for i in range(0, len(coef), 64)]  # (64, N) at a time
    if sigma_um is None:  # the q-quantile of |r| of the best sample, as a normal σ
        qr = np.concatenate([np.quantile(np.abs(z[None, :] - coef[c] @ a.T), _SCALE_QUANTILE,
                                         axis=1) for c in chunks])
        scale = qr.min() / _HALF_NORMAL_Q
        sig = np.full(n, max(scale, 1e-12 * (np.abs(z).max() + 1e-300)))
    else:
        sig = np.broadcast_to(np.asarray(sigma_um, float), (n,)).astype(float)
        if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            raise GeometryError("sigma_um must be positive and finite")
    count = np.empty(len(coef), int)
    cost = np.empty(len(coef))
    for c in chunks:
        t = ((z[None, :] - coef[c] @ a.T) / sig[None, :]) ** 2
        count[c] = (t <= k_sigma ** 2).sum(axis=1)
        cost[c] = np.minimum(t, k_sigma ** 2).sum(axis=1)
    cand = np.flatnonzero(count == count.max())
    best = coef[cand[np.argmin(cost[cand])]]
    mask = np.abs(z - a @ best) <= k_sigma * sig
    for _ in range(20):
        if mask.sum() < max(3, int(min_inliers)):
            break
        c = _wls_plane(a[mask], z[mask], 1.0 / sig[mask] ** 2)
        r = z - a @ c
        if sigma_um is None:  # σ of the inliers (a ±kσ-truncated normal: ~1 % low at 3σ)
            sig = np.full(n, max(np.sqrt(np.mean(r[mask] ** 2)), sig[0] * 1e-3))
        new = np.abs(r) <= k_sigma * sig
        if np.array_equal(new, mask):
            break
        mask = new
    if mask.sum() < max(3, int(min_inliers)):
        raise GeometryError(
            f"only {int(mask.sum())} of {n} points lie on a common plane within {k_sigma:g}σ: "
            "no dominant flat surface; give a reference_region")
    c = _wls_plane(a[mask], z[mask], 1.0 / sig[mask] ** 2)
    return _uncentre(c, xy0), mask, sig
