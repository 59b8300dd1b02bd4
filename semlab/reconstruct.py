"""3D points from matched SEM views: affine factorization, tilt parallax, tilt recovery.

All public functions take matches as ``pts`` : ``(N, V, 2)`` arrays — point, view,
``(x, y)`` in pixels (OpenCV convention: origin at the centre of the top-left pixel, x right,
y down), the layout of :mod:`semlab.matching`. Lengths are µm (``_um``), people's angles
degrees (``_deg``), radians inside.

Camera model (see :mod:`semlab.camera`): view ``i`` at eucentric stage tilt ``θ_i`` about the
image y axis sees a material point ``(x, y, z)`` µm at::

    u_i = c_i + (x cos θ_i + z sin θ_i) / s,     v_i = d_i + y / s

with ``s`` the pixel size (µm/px), ``z > 0`` an extrusion and ``(c_i, d_i)`` the pixel position
of the tilt axis in view ``i``. In practice the stage shifts between views so ``(c_i, d_i)`` are
unknown; the functions here absorb them as one constant per view (see
:func:`heights_from_tilts`).

References
----------
- C. Tomasi, T. Kanade, "Shape and motion from image streams under orthography: a
  factorization method", IJCV 9(2), 1992.
- R. Hartley, A. Zisserman, *Multiple View Geometry*, 2nd ed. (H&Z): Alg. 18.1 (affine
  factorization), §9.6 (essential matrix), §12.2 (linear triangulation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from .camera import _check_pixel_size
from .errors import GeometryError
from .perspective import (PERSPECTIVE_GAIN_MIN, check_perspective_visible,  # noqa: F401
                          heights_perspective, perspective_height_sigma, tilt_from_rotation,
                          triangulate_perspective)
from .plane import fit_reference_plane

__all__ = [
    "AffineFactorization",
    "HeightResult",
    "TiltEstimate",
    "TWO_VIEW_MESSAGE",
    "factorize_affine",
    "parallax_height",
    "heights_from_tilts",
    "estimate_tilts",
    "tilt_from_rotation",
    "triangulate_perspective",
    "heights_perspective",
    "perspective_height_sigma",
    "check_perspective_visible",
]

TWO_VIEW_MESSAGE = (
    "two affine views leave the depth scale undetermined (bas-relief ambiguity): give tilt_deg "
    "in experiment.toml, a third view, or vanishing-point lines"
)


# ----------------------------------------------------------------------------- input checks

def _as_pts(pts, min_views=2, min_points=1):
    """Validate matches and return them as a float ``(N, V, 2)`` array."""
    p = np.asarray(pts, dtype=float)
    if p.ndim != 3 or p.shape[2] != 2:
        raise GeometryError(
            f"pts must be an (N, V, 2) array (point, view, xy) in pixels, got shape {p.shape}")
    n, v = p.shape[:2]
    hint = (" — pts must be (N, V, 2) (point, view, xy); if you have (V, N, 2) use "
            "pts.transpose(1, 0, 2)") if n < v else ""
    if v < min_views:
        raise GeometryError(f"need at least {min_views} views, got {v} (pts shape {p.shape}){hint}")
    if n < min_points:
        raise GeometryError(
            f"need at least {min_points} matched points, got {n} (pts shape {p.shape}){hint}")
    if not np.all(np.isfinite(p)):
        bad = np.unique(np.nonzero(~np.isfinite(p))[0])
        raise GeometryError(
            f"pts holds NaN/inf for {bad.size} point(s) (first: {bad[:5].tolist()}); drop the "
            "points that are not matched in every view")
    return p


def _as_tilts(tilt_deg, n_views):
    t = np.asarray(tilt_deg, dtype=float).ravel()
    if t.size != n_views:
        raise GeometryError(f"tilt_deg has {t.size} value(s) but pts has {n_views} views")
    if not np.all(np.isfinite(t)):
        raise GeometryError(f"tilt_deg must be finite numbers, got {t.tolist()}")
    if np.ptp(np.sin(np.deg2rad(t))) < 1e-6:
        raise GeometryError(
            f"the views have the same tilt ({t.tolist()} deg): heights need at least two "
            "different stage tilts")
    return t


def _check_view_mask(mask, th):
    """Raise unless every point has at least two valid views of different tilts."""
    sn = np.sin(th)
    hi = np.max(np.where(mask, sn, -np.inf), axis=1)
    lo = np.min(np.where(mask, sn, np.inf), axis=1)
    bad = np.flatnonzero(~(hi - lo >= 1e-6))
    if bad.size:
        raise GeometryError(
            f"{bad.size} point(s) (first: {bad[:5].tolist()}) have fewer than two valid views "
            "of different tilts in view_valid; select them out first (MatchResult.seen_in)")


def _check_not_collinear(xy, what="points"):
    """Raise if the ``(N, 2)`` image points are (nearly) on one line."""
    c = xy - xy.mean(axis=0)
    sv = np.linalg.svd(c, compute_uv=False)
    if sv[0] == 0 or sv[1] <= 1e-9 * sv[0] or sv[1] < 1e-9:
        raise GeometryError(
            f"the {what} are collinear in the image: spread matches over the field of view")


def _rot2(a):
    return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])


def _rotate_to_vertical_axis(pts, tilt_axis_deg, center):
    """Rotate image points about ``center`` so that the tilt axis direction maps to +y."""
    if tilt_axis_deg == 90.0:
        return pts
    return (pts - center) @ _rot2(np.deg2rad(90.0 - float(tilt_axis_deg))).T + center


# ----------------------------------------------------------------------------- factorization

@dataclass
class AffineFactorization:
    """Result of :func:`factorize_affine`; unpacks as ``M, X, t = factorize_affine(pts)``.

    Attributes
    ----------
    M : (2V, 3) array
        Stacked affine cameras, rows ``(u_0, v_0, u_1, v_1, ...)`` (up to a 3×3 affine
        transform of the world frame).
    X : (3, N) array
        Affine structure.
    t : (2V,) array
        Per-view image centroid, pixels (the translation part of each camera).
    residual_px : float
        RMS of the measurement matrix minus its rank-3 reconstruction, pixels per
        coordinate (≈ the matching noise when the affine model holds).
    singular_values : (min(2V, N),) array
        Singular values of the centred measurement matrix.
    """

    M: np.ndarray
    X: np.ndarray
    t: np.ndarray
    residual_px: float
    singular_values: np.ndarray

    def __iter__(self):
        return iter((self.M, self.X, self.t))


def factorize_affine(pts):
    """Tomasi–Kanade affine factorization of matched points.

    Builds the ``2V × N`` measurement matrix, subtracts each row's centroid and truncates its
    SVD to rank 3 (Tomasi & Kanade 1992; H&Z 2nd ed. Alg. 18.1). The result is defined up
    to a 3×3 affine transform ``M → M A, X → A⁻¹ X``; the metric upgrade needs camera
    constraints (see :func:`estimate_tilts`).

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels of N points in V >= 2 views; N >= 4, not all collinear.

    Returns
    -------
    AffineFactorization
        Unpacks as ``(M (2V, 3), X (3, N), t (2V,))``; also carries ``residual_px`` (RMS
        rank-3 residual, px) and ``singular_values``.

    Raises
    ------
    GeometryError
        Fewer than 2 views or 4 points, NaNs, or collinear points.
    """
    p = _as_pts(pts, min_views=2, min_points=4)
    _check_not_collinear(p[:, 0, :], "matched points")
    n, v = p.shape[:2]
    w = p.transpose(1, 2, 0).reshape(2 * v, n)  # rows u0, v0, u1, v1, ...
    t = w.mean(axis=1)
    wc = w - t[:, None]
    u, sv, vt = np.linalg.svd(wc, full_matrices=False)
    root = np.sqrt(sv[:3])  # 2V >= 4 and N >= 4, so there are >= 4 singular values
    m = u[:, :3] * root
    x = root[:, None] * vt[:3]
    resid = float(np.sqrt(np.mean((wc - m @ x) ** 2)))
    return AffineFactorization(M=m, X=x, t=t, residual_px=resid, singular_values=sv)


# ----------------------------------------------------------------------------- known tilts

def parallax_height(u0, u1, tilt0_deg, tilt1_deg, pixel_size_um, c0=0.0, c1=0.0):
    """Height from the x-parallax of a eucentric tilt pair (closed form).

    From ``u_i - c_i = (x cos θ_i + z sin θ_i) / s`` for two views, eliminating ``x``::

        z = s [(u1 - c1) cos θ0 - (u0 - c0) cos θ1] / sin(θ1 - θ0)

    Parameters
    ----------
    u0, u1 : array_like
        x pixel coordinates of the same points in views 0 and 1 (any common shape).
    tilt0_deg, tilt1_deg : float
        Stage tilts of the two views, degrees (must differ).
    pixel_size_um : float
        Pixel size, µm/px.
    c0, c1 : float or array_like
        x pixel position of the tilt axis in each view (unknown: z up to a constant).

    Returns
    -------
    z_um : ndarray
        Height in µm, same shape as ``u0``; z > 0 toward the detector (extrusion).
    """
    s = _check_pixel_size(pixel_size_um)
    t0, t1 = np.deg2rad(float(tilt0_deg)), np.deg2rad(float(tilt1_deg))
    if abs(np.sin(t1 - t0)) < 1e-9:
        raise GeometryError(f"the two tilts are equal ({tilt0_deg} deg): no parallax")
    a0, a1 = np.asarray(u0, float) - c0, np.asarray(u1, float) - c1
    return s * (a1 * np.cos(t0) - a0 * np.cos(t1)) / np.sin(t1 - t0)


@dataclass
class HeightResult:
    """Result of :func:`heights_from_tilts`.

    Attributes
    ----------
    xyz_um : (N, 3) array
        Material points ``(x, y, z)`` µm (in the frame rotated so the tilt axis is y).
    residual_px : (N,) array
        Per-point RMS reprojection distance over the views, pixels.
    tilt_deg : (V,) array
        Tilts used.
    offsets_px : (V, 2) array
        Tilt-axis pixel position ``(c_i, d_i)`` per view, estimated (in the gauge mean
        z = 0, mean x at the mean view position) or as given; in the rotated image frame
        when ``tilt_axis_deg != 90``.
    offsets_known : bool
        Whether the offsets were given (z absolute) or estimated (z up to a constant).
    """

    xyz_um: np.ndarray
    residual_px: np.ndarray
    tilt_deg: np.ndarray
    offsets_px: np.ndarray
    offsets_known: bool


def heights_from_tilts(pts, tilt_deg, pixel_size_um, tilt_axis_deg=90.0, center_px=None,
                       view_valid=None):
    """Linear least-squares 3D points from views at known stage tilts.

    For each point, ``(x, z)`` solve ``u_i - c_i = (x cos θ_i + z sin θ_i)/s`` over all views
    (2 views: the parallax closed form of :func:`parallax_height`; V views: least squares),
    and ``y = s · mean_i(v_i - d_i)``.

    Unknown offsets: the tilt-axis positions ``(c_i, d_i)`` move between views when the
    stage shifts. With ``center_px=None`` they are one unknown constant per view, solved by
    centring each view's coordinates over the points (gauge: mean x = mean z = 0, then the
    mean-view position added back). A per-view constant moves *all* points by one
    ``(Δx, Δz)``, so heights are known up to a constant, removed with the reference surface
    (:func:`semlab.surface.reference_surface`).

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels of N >= 2 points in V >= 2 views.
    tilt_deg : (V,) array_like
        Stage tilt of each view, degrees (at least two different).
    pixel_size_um : float
        Pixel size, µm/px.
    tilt_axis_deg : float, optional
        Direction of the tilt axis in the image, degrees from +x toward +y (y down).
        90 (default) = axis along image y, the camera.py convention. Otherwise the image
        coordinates are first rotated by ``90 - tilt_axis_deg`` about ``center_px`` (or the
        origin) so the axis is vertical; ``xyz_um`` is then in that rotated frame. ``φ`` and
        ``φ + 180`` give the same axis with opposite sense, which flips the sign of z.
    center_px : None, (2,) or (V, 2) array_like, optional
        Known tilt-axis pixel position ``(cx, cy)`` (all views or per view). None: unknown,
        estimated as described above.
    view_valid : (N, V) bool array, optional
        Which views of each point were matched (:attr:`semlab.matching.MatchResult.view_valid`):
        each point is solved over its own valid views (at least two, of different tilts);
        its other views' entries of ``pts`` are ignored (may be NaN). The unknown offsets
        are estimated from the points valid in every view (at least two), so all points
        share one gauge. None: every view of every point.

    Returns
    -------
    HeightResult
        ``xyz_um`` (N, 3), ``residual_px`` (N,), ``tilt_deg``, ``offsets_px`` (V, 2).

    Raises
    ------
    GeometryError
        Bad shapes, NaNs, fewer than 2 views or points, equal tilts, bad pixel size.
    """
    mask = None
    if view_valid is not None:
        raw = np.asarray(pts, dtype=float)
        mask = np.asarray(view_valid, bool)
        if raw.ndim != 3 or mask.shape != raw.shape[:2]:
            raise GeometryError(f"view_valid must be (N, V) like pts {raw.shape[:2]}, got "
                                f"shape {mask.shape}")
        pts = np.where(mask[..., None], raw, 0.0)
    p = _as_pts(pts, min_views=2, min_points=2)
    n, v = p.shape[:2]
    th = np.deg2rad(_as_tilts(tilt_deg, v))
    s = _check_pixel_size(pixel_size_um)
    if mask is None:
        mask = np.ones((n, v), bool)
    _check_view_mask(mask, th)
    full = mask.all(axis=1)
    known = center_px is not None
    if known:
        c = np.asarray(center_px, float)
        if c.shape not in ((2,), (v, 2)) or not np.all(np.isfinite(c)):
            raise GeometryError(
                f"center_px must be (2,) or ({v}, 2) finite pixels, got {center_px!r}")
        c = np.broadcast_to(c, (v, 2)).copy()
    else:
        c = np.zeros((v, 2))
    p = np.stack([_rotate_to_vertical_axis(p[:, i], tilt_axis_deg, c[i]) for i in range(v)], 1)

    a = np.column_stack([np.cos(th), np.sin(th)])  # (V, 2), u - c = a @ (x, z) / s
    u = p[:, :, 0].T  # (V, N)
    vv = p[:, :, 1].T
    if known:
        uc = u - c[:, 0:1]
        vc = vv - c[:, 1:2]
    else:
        if full.sum() < 2:
            raise GeometryError(f"only {int(full.sum())} point(s) are valid in every view: the "
                                "per-view offsets need at least 2 (or give center_px)")
        mu = u[:, full].mean(axis=1, keepdims=True)
        mv = vv[:, full].mean(axis=1, keepdims=True)
        uc, vc = u - mu, vv - mv
    xz = np.zeros((2, n))
    for pattern in np.unique(mask, axis=0):   # one least-squares solve per set of views
        cols = np.flatnonzero((mask == pattern).all(axis=1))
        xz[:, cols] = np.linalg.lstsq(a[pattern], uc[np.ix_(pattern, cols)], rcond=None)[0]
    mt = mask.T
    y = np.sum(np.where(mt, vc, 0.0), axis=0) / mt.sum(axis=0)
    ru = np.where(mt, uc - a @ xz, 0.0)
    rv = np.where(mt, vc - y, 0.0)
    if not known:
        # gauge: put x (and y) back at the mean-view position, mean z = 0
        x0 = float(np.mean(mu[:, 0] / np.cos(th)))
        y0 = float(np.mean(mv[:, 0]))
        xz[0] += x0
        y = y + y0
        c = np.column_stack([mu[:, 0] - x0 * np.cos(th), mv[:, 0] - y0])
    xyz = np.column_stack([xz[0], y, xz[1]]) * s
    resid = np.sqrt(np.sum(ru ** 2 + rv ** 2, axis=0) / mt.sum(axis=0))
    return HeightResult(xyz_um=xyz, residual_px=resid, tilt_deg=np.rad2deg(th),
                        offsets_px=c, offsets_known=known)


# ----------------------------------------------------------------------------- unknown tilts

@dataclass
class TiltEstimate:
    """Result of :func:`estimate_tilts`.

    Attributes
    ----------
    tilt_deg : (V,) array
        Stage tilts, degrees, in the conventions of :func:`estimate_tilts`.
    tilt_sigma_deg : (V,) array
        1σ bootstrap uncertainty of each tilt (0 for a view whose tilt was given).
    xyz : (N, 3) array
        Points ``(x, y, z)``, µm if ``pixel_size_um`` was given, else pixels (``unit``).
    unit : str
        ``"um"`` or ``"px"``.
    residual_px : float
        RMS of the centred x-coordinates minus their rank-2 reconstruction, px.
    singular_values : (V,) array
        Singular values of the centred x-coordinate matrix ``U``.
    """

    tilt_deg: np.ndarray
    tilt_sigma_deg: np.ndarray
    xyz: np.ndarray
    unit: str
    residual_px: float
    singular_values: np.ndarray


def _noise_corrected_scatter(uc, noise_weights):
    """Scatter ``U Uᵀ`` (V, V) of centred x-coordinates minus the matching-noise part.

    With noise of variance ``λ w_i`` in view i (``w`` known up to the factor, e.g. 0 for the
    matching reference view whose positions are exact and 1 for the others), the scatter is
    ``S = A B Bᵀ Aᵀ + N λ D``, ``D = diag(w)``: noise confined to some views is not
    isotropic, so the rank-2 SVD of ``U`` is biased toward the noisy views (0.5–1° of tilt
    at 0.03 px on −5/0/+5°). ``Nλ`` is the smallest root of ``det(S − Nλ D) = 0`` (for
    V > 3 the mean of the V − 2 smallest: the model has rank 2), i.e. the generalized
    eigenvalue problem ``S v = Nλ D v``; ``S − Nλ D`` is the errors-in-variables corrected
    scatter (Fuller 1987, "Measurement Error Models", §1.3; Kanatani 1996 §9 on the bias
    of SVD fits under anisotropic noise).
    """
    S = uc @ uc.T
    w = np.asarray(noise_weights, float)
    # a relative jitter: exact (noise-free) rank-2 data make S singular, which an absolute
    # 1e-300 does not regularise on every LAPACK build (numpy 2.4.6: not positive definite)
    L = np.linalg.cholesky(S + 1e-12 * np.trace(S) / len(S) * np.eye(len(S)))
    Li = np.linalg.inv(L)
    mu = np.linalg.eigvalsh(Li @ np.diag(w) @ Li.T)       # ascending, = 1 / (Nλ)
    big = mu[::-1][: max(len(S) - 2, 1)]
    big = big[big > 0]
    if not len(big):
        return S
    lam = float(np.mean(1.0 / big))
    return S - lam * np.diag(w)


def _metric_tilts(uc, noise_weights=None):
    """Tilts (rad, up to common rotation & sign) and (x, z) px from centred x-coordinates.

    ``uc`` is (V, N). Rank-2 SVD ``U ≈ A0 B0``; the true ``A`` has rows ``(cos θ_i, sin θ_i)``
    so ``A = A0 G`` with ``a_iᵀ Q a_i = 1``, ``Q = G Gᵀ`` (3 unknowns, linear least squares,
    the orthographic metric constraints of Tomasi & Kanade 1992 / H&Z §18.3 reduced to
    rotations about y). ``G`` = Cholesky factor of ``Q``. With ``noise_weights`` (V,)
    (relative noise variance per view) the rank-2 column space comes from the
    noise-corrected scatter (:func:`_noise_corrected_scatter`) and ``B0`` by least squares.
    Returns (phi (V,), B (2, N), sv).
    """
    u, sv, vt = np.linalg.svd(uc, full_matrices=False)
    if sv[0] == 0 or sv[1] <= 1e-12 * sv[0]:
        raise GeometryError(
            "the x-coordinates have rank 1: the points are coplanar (flat surface) or the "
            "views have the same tilt, so the tilts are not observable; give tilt_deg")
    if noise_weights is None:
        a0 = u[:, :2] * sv[:2]
        scale = np.max(np.linalg.norm(a0, axis=1))
        a0 = a0 / scale
        b0 = vt[:2] * scale
    else:
        ev, evec = np.linalg.eigh(_noise_corrected_scatter(uc, noise_weights))
        ev, evec = ev[::-1][:2], evec[:, ::-1][:, :2]
        if ev[1] <= 1e-12 * ev[0]:
            raise GeometryError(
                "after removing the matching noise the x-coordinates have rank 1: the surface "
                "relief is below the noise, so the tilts are not observable; give tilt_deg")
        a0 = evec * np.sqrt(ev)
        a0 = a0 / np.max(np.linalg.norm(a0, axis=1))
        b0 = np.linalg.lstsq(a0, uc, rcond=None)[0]
    m = np.column_stack([a0[:, 0] ** 2, 2 * a0[:, 0] * a0[:, 1], a0[:, 1] ** 2])
    q, *_ = np.linalg.lstsq(m, np.ones(a0.shape[0]), rcond=None)
    qm = np.array([[q[0], q[1]], [q[1], q[2]]])
    if np.linalg.eigvalsh(qm)[0] <= 0:
        raise GeometryError(
            "the tilt (metric) constraints are inconsistent (Q not positive definite): the "
            "tilt range is too small for the matching noise or the surface is too flat; give "
            "tilt_deg in experiment.toml")
    g = np.linalg.cholesky(qm)
    a = a0 @ g
    b = np.linalg.solve(g, b0)
    phi = np.arctan2(a[:, 1], a[:, 0])
    return phi, b, sv


def _fix_gauge(phi, b, y, ref_view=None, ref_tilt=0.0, increasing=True):
    """Fix sign (θ_last > θ_0, or < with ``increasing=False``) and common rotation (level
    plane or a known view's tilt)."""
    d = np.angle(np.exp(1j * (phi - phi[0])))  # unwrap relative to view 0
    b = _rot2(-phi[0]) @ b
    if (d[-1] < 0) == bool(increasing):  # Necker reversal: θ → -θ, z → -z
        d = -d
        b = b * np.array([[1.0], [-1.0]])
    if ref_view is not None:
        alpha = ref_tilt - d[ref_view]
        return d + alpha, _rot2(alpha) @ b
    alpha = 0.0
    for _ in range(10):  # rotating changes the robust weights only slightly: 2-3 rounds
        bb = _rot2(alpha) @ b
        plane = fit_reference_plane(np.column_stack([bb[0], y, bb[1]]))
        step = -np.arctan(plane[0])
        alpha += step
        if abs(step) < 1e-11:
            break
    return d + alpha, _rot2(alpha) @ b


def estimate_tilts(pts, pixel_size_um=None, reference_view=None, reference_tilt_deg=0.0,
                   tilt_axis_deg=90.0, n_boot=200, seed=0, progress=True,
                   noise_free_view=None, increasing=True):
    """Stage tilts and 3D points from 3+ affine views about a common axis (no tilt given).

    Metric upgrade for rotations about the common image y axis: the per-view centred
    x-coordinates ``U`` (V, N) factor as ``U = A B`` with ``A`` rows ``(cos θ_i, sin θ_i)``
    and ``B`` = ``(x, z)/s`` — known only up to a 2×2 ``G`` from the rank-2 SVD. The
    unit-row-norm constraints ``a_iᵀ Q a_i = 1`` (``Q = G Gᵀ``, 3 unknowns, hence >= 3
    views) are solved by linear least squares, ``G`` by Cholesky (Tomasi & Kanade 1992;
    H&Z 2nd ed. §18.3). The scale is the pixel: ``v`` = ``y/s`` is the same in every view
    up to an offset, so ``x``, ``y``, ``z`` all come out in pixels of the same ``s``
    (µm with ``pixel_size_um``); equal magnification in all views is assumed.

    Two ambiguities remain and are fixed by convention:

    - **absolute tilt** (common rotation about y): the robust reference plane
      (:func:`semlab.plane.fit_reference_plane`) of the recovered surface is made
      level in x (zero dz/dx); or, with ``reference_view``, that view's tilt is set to
      ``reference_tilt_deg``;
    - **sign** (Necker reversal ``θ → -θ, z → -z``): not observable from the images; fixed
      so that tilt increases with view order (``θ_last > θ_0``; ``increasing=False``: it
      decreases). If your stage tilted the other way, pass ``increasing=False`` (in an
      experiment: ``[stereo] tilt_order = "decreasing"``), which negates the tilts and z.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels, V >= 3 views, N >= 4 points.
    pixel_size_um : float, optional
        Pixel size µm/px; scales ``xyz`` to µm.
    reference_view : int, optional
        View whose tilt is known (e.g. the untilted one).
    reference_tilt_deg : float
        Its tilt, degrees.
    tilt_axis_deg : float
        Tilt axis direction in the image (see :func:`heights_from_tilts`).
    n_boot : int
        Bootstrap resamples of the points for ``tilt_sigma_deg`` (0: no uncertainty, NaN).
    seed : int
        Seed of the bootstrap.
    progress : bool
        Show a tqdm bar over the bootstrap.
    noise_free_view : int, optional
        The view without matching error (the reference view of subset matching): the
        noise, confined to the other views, is removed from the scatter before the rank-2
        fit. With the first of −5/0/+5° views as reference, ignoring it biased the tilt
        differences by ~0.8° at 0.03 px (0.14° corrected); with the middle view as
        reference the bias cancels and the correction only adds variance (0.06° without,
        0.10° with), so match against the middle view and leave this ``None`` (as
        :func:`semlab.pipeline.choose_tilts` does; right for equal noise in all views).
    increasing : bool
        The sign convention: True (default), the tilts increase with view order; False,
        they decrease (the same fit with ``θ → -θ, z → -z``).

    Returns
    -------
    TiltEstimate

    Raises
    ------
    GeometryError
        Two views (bas-relief ambiguity, message :data:`TWO_VIEW_MESSAGE`), too few points,
        NaNs, coplanar points or inconsistent metric constraints.

    Examples
    --------
    Points of a rough surface seen at -4°, 1° and 6° (tilts unknown to the estimator):

    >>> import numpy as np, semlab
    >>> from semlab.camera import project_affine
    >>> rng = np.random.default_rng(0)
    >>> xyz = np.column_stack([rng.uniform(0, 10, (300, 2)), rng.normal(0, 0.3, 300)])
    >>> pts = np.stack([project_affine(xyz, t, 0.03) for t in (-4.0, 1.0, 6.0)], axis=1)
    >>> est = semlab.estimate_tilts(pts, 0.03, reference_view=1, reference_tilt_deg=1.0,
    ...                             n_boot=0, progress=False)
    >>> np.round(est.tilt_deg, 3).tolist()
    [-4.0, 1.0, 6.0]
    """
    p = np.asarray(pts, dtype=float)
    if p.ndim == 3 and p.shape[2] == 2 and p.shape[1] == 2:
        raise GeometryError(TWO_VIEW_MESSAGE)
    p = _as_pts(p, min_views=3, min_points=4)
    n, v = p.shape[:2]
    if reference_view is not None and not (-v <= int(reference_view) < v):
        raise GeometryError(f"reference_view={reference_view} but pts has {v} views")
    ref = None if reference_view is None else int(reference_view) % v
    ref_t = np.deg2rad(float(reference_tilt_deg))
    weights = None
    if noise_free_view is not None:
        if not (-v <= int(noise_free_view) < v):
            raise GeometryError(f"noise_free_view={noise_free_view} but pts has {v} views")
        weights = np.where(np.arange(v) == int(noise_free_view) % v, 0.0, 1.0)
    _check_not_collinear(p[:, 0, :], "matched points")
    p = np.stack([_rotate_to_vertical_axis(p[:, i], tilt_axis_deg, np.zeros(2))
                  for i in range(v)], 1)
    u = p[:, :, 0].T
    vv = p[:, :, 1].T
    yc = (vv - vv.mean(axis=1, keepdims=True)).mean(axis=0) + vv.mean()

    def solve(idx):
        uc = u[:, idx] - u[:, idx].mean(axis=1, keepdims=True)
        phi, b, sv = _metric_tilts(uc, weights)
        th, b = _fix_gauge(phi, b, yc[idx], ref, ref_t, increasing)
        return th, b, sv, uc

    th, b, sv, uc = solve(np.arange(n))
    a = np.column_stack([np.cos(th), np.sin(th)])
    resid = float(np.sqrt(np.mean((uc - a @ b) ** 2)))

    sig = np.full(v, np.nan)
    if n_boot and n_boot > 1:
        rng = np.random.default_rng(seed)
        boots = []
        for _ in tqdm(range(int(n_boot)), disable=not progress, desc="tilt bootstrap"):
            idx = rng.integers(0, n, n)
            try:
                boots.append(solve(idx)[0])
            except GeometryError:
                continue
        if len(boots) >= 2:
            sig = np.rad2deg(np.std(np.angle(np.exp(1j * (np.array(boots) - th))), 0, ddof=1))
        if ref is not None:
            sig[ref] = 0.0
    scale = 1.0 if pixel_size_um is None else _check_pixel_size(pixel_size_um)
    xyz = np.column_stack([b[0], yc, b[1]]) * scale
    return TiltEstimate(tilt_deg=np.rad2deg(th), tilt_sigma_deg=sig, xyz=xyz,
                        unit="px" if pixel_size_um is None else "um",
                        residual_px=resid, singular_values=sv)
