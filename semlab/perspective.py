"""Perspective (low-magnification) SEM geometry: pose from F and K, triangulation, heights.

Split from :mod:`semlab.reconstruct` (which re-exports these names). Matches are ``(N, 2)``
arrays of ``(x, y)`` pixels in views 0 and 1; ``K`` the 3×3 intrinsics (e.g. from vanishing
points, :func:`semlab.vanishing.calibrate_views`).

References
----------
- R. Hartley, A. Zisserman, *Multiple View Geometry*, 2nd ed. (H&Z): §9.6 (essential matrix),
  §12.2 (linear triangulation), Alg. 14.1 (affine F).
"""

from __future__ import annotations

import numpy as np

from .camera import _check_pixel_size
from .errors import GeometryError

__all__ = [
    "tilt_from_rotation",
    "triangulate_perspective",
    "heights_perspective",
    "perspective_height_sigma",
    "check_perspective_visible",
    "PERSPECTIVE_GAIN_MIN",
]


def tilt_from_rotation(R_rel):
    """Stage tilt difference from a relative camera rotation (e.g. from vanishing points).

    With world-to-camera rotations ``R_i = R_y(θ_i)`` (the first two rows of ``R_y(θ)`` are
    the affine SEM camera of :mod:`semlab.camera`), ``R_rel = R_1 R_0ᵀ = R_y(θ_1 - θ_0)``.
    The angle about the camera y axis is ``atan2(R[0,2] - R[2,0], R[0,0] + R[2,2])``, the
    closest y-rotation to ``R_rel`` (any small rotation about other axes, e.g. scan
    rotation, is ignored).

    Parameters
    ----------
    R_rel : (3, 3) array
        Rotation matrix from view 0 camera frame to view 1 camera frame.

    Returns
    -------
    float
        ``θ_1 - θ_0`` in degrees.
    """
    r = np.asarray(R_rel, dtype=float)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise GeometryError(f"R_rel must be a finite 3x3 rotation matrix, got shape {r.shape}")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        raise GeometryError(
            "R_rel is not a rotation matrix (RᵀR != I or det < 0); orthonormalize it first")
    return float(np.rad2deg(np.arctan2(r[0, 2] - r[2, 0], r[0, 0] + r[2, 2])))


# ----------------------------------------------------------------------------- perspective

def _normalized(K_inv, x):
    """(N, 2) pixels -> (N, 2) normalized image coordinates ``K⁻¹ [x, 1]``."""
    h = np.column_stack([x, np.ones(len(x))]) @ K_inv.T
    return h[:, :2] / h[:, 2:]


def _triangulate_linear(p0, p1, x0, x1):
    """DLT triangulation (H&Z §12.2) of normalized points; returns (N, 3), (N,) w."""
    rows = np.stack([
        x0[:, 0:1] * p0[2] - p0[0], x0[:, 1:2] * p0[2] - p0[1],
        x1[:, 0:1] * p1[2] - p1[0], x1[:, 1:2] * p1[2] - p1[1],
    ], axis=1)  # (N, 4, 4)
    rows /= np.linalg.norm(rows, axis=2, keepdims=True)
    _, _, vt = np.linalg.svd(rows)
    h = vt[:, -1, :]
    w = h[:, 3]
    return h[:, :3] / np.where(np.abs(w) < 1e-300, 1e-300, w)[:, None], w


def triangulate_perspective(K, F_or_E, x0, x1, essential=False):
    """Relative pose and 3D points from two calibrated perspective views.

    ``E = Kᵀ F K`` (same ``K`` in both views), its four decompositions
    ``(R, t) ∈ {(U W Vᵀ, ±u3), (U Wᵀ Vᵀ, ±u3)}`` (H&Z 2nd ed. §9.6.2, Result 9.19), the one
    placing most points in front of both cameras (cheirality), and linear triangulation
    (H&Z §12.2) with ``P0 = K[I | 0]``, ``P1 = K[R | t]``.

    The scale is arbitrary: ``‖t‖ = 1``, so ``X`` is the scene in the camera-0 frame up to
    one unknown factor (the baseline length); fix it with a known length.

    Parameters
    ----------
    K : (3, 3) array
        Intrinsics.
    F_or_E : (3, 3) array
        Fundamental matrix with ``x1ᵀ F x0 = 0`` (homogeneous pixels), or the essential
        matrix if ``essential=True``.
    x0, x1 : (N, 2) arrays
        Matched ``(x, y)`` pixels in views 0 and 1, N >= 1 (more for a reliable
        cheirality vote).
    essential : bool
        ``F_or_E`` is already the essential matrix (in normalized coordinates).

    Returns
    -------
    X : (N, 3) array
        Points in the camera-0 frame (units of ``‖t‖ = 1``).
    R : (3, 3) array
        Rotation camera 0 → camera 1.
    t : (3,) array
        Unit translation, ``X_1 = R X_0 + t``.

    Raises
    ------
    GeometryError
        Bad shapes/NaNs, singular K, E of rank < 2 (e.g. no translation or degenerate F),
        or no decomposition with the majority of points in front of both cameras.
    """
    k = np.asarray(K, float)
    f = np.asarray(F_or_E, float)
    a = np.asarray(x0, float)
    b = np.asarray(x1, float)
    if k.shape != (3, 3) or f.shape != (3, 3):
        raise GeometryError(f"K and F_or_E must be 3x3, got {k.shape} and {f.shape}")
    if a.ndim != 2 or a.shape[1] != 2 or a.shape != b.shape or a.shape[0] < 1:
        raise GeometryError(
            f"x0 and x1 must be matching (N, 2) arrays of pixels, got {a.shape} and {b.shape}")
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(f)) and np.all(np.isfinite(a))
            and np.all(np.isfinite(b))):
        raise GeometryError("K, F_or_E, x0 and x1 must be finite (no NaN/inf)")
    if abs(np.linalg.det(k)) < 1e-12 * max(1.0, np.abs(k).max()) ** 3:
        raise GeometryError("K is singular: check the calibration (focal lengths must be > 0)")
    e = f if essential else k.T @ f @ k
    u, sv, vt = np.linalg.svd(e)
    if sv[0] == 0 or sv[1] < 1e-6 * sv[0]:
        raise GeometryError(
            "the essential matrix has rank < 2 (degenerate F, or no camera translation): "
            "the pose cannot be recovered from it")
    if np.linalg.det(u) < 0:
        u = -u
    if np.linalg.det(vt) < 0:
        vt = -vt
    w = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    kinv = np.linalg.inv(k)
    na, nb = _normalized(kinv, a), _normalized(kinv, b)
    p0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    best = None
    for r in (u @ w @ vt, u @ w.T @ vt):
        for t in (u[:, 2], -u[:, 2]):
            p1 = np.hstack([r, t[:, None]])
            x, _ = _triangulate_linear(p0, p1, na, nb)
            z0 = x[:, 2]
            z1 = x @ r[2] + t[2]
            good = int(np.sum((z0 > 0) & (z1 > 0)))
            if best is None or good > best[0]:
                best = (good, x, r, t)
    good, x, r, t = best
    if good <= len(a) / 2:
        raise GeometryError(
            f"no (R, t) puts the majority of points in front of both cameras (best {good} of "
            f"{len(a)}): F/E or the matches are wrong, or x0/x1 are swapped")
    return x, r, t


def heights_perspective(x0, x1, K, pixel_size_um, F=None):
    """Metric 3D points of a surface from two calibrated perspective views.

    For ``camera = "perspective"`` (low magnification, where the SEM is not a parallel
    projection): the fundamental matrix (normalised eight-point, H&Z Alg. 11.1, unless
    ``F`` is given), ``E = Kᵀ F K``, the pose and linear triangulation
    (:func:`triangulate_perspective`). The reconstruction is known up to one scale (the
    baseline); it is fixed by the pixel size: a pixel of ``pixel_size_um`` at the working
    distance ``D`` means ``D = pixel_size_um · f`` (``f`` the focal length in pixels), so
    the median depth of the points in camera 0 is set to ``D``.

    Parameters
    ----------
    x0, x1 : (N, 2) arrays
        Matched ``(x, y)`` pixels in views 0 and 1, N >= 8.
    K : (3, 3) array
        Intrinsics (e.g. from vanishing points, :func:`semlab.vanishing.calibrate_views`).
    pixel_size_um : float
        Pixel size on the sample at the working distance, µm.
    F : (3, 3) array, optional
        Fundamental matrix ``x1ᵀ F x0 = 0``.

    Returns
    -------
    xyz_um : (N, 3) array
        Points in the camera-0 frame in µm: x right, y down (as the image) and z towards
        the camera (out of the surface), so that extrusions have larger z.
    R : (3, 3) array, t : (3,) array
        Pose of camera 1 relative to camera 0 (``t`` in µm).
    tilt_deg : float
        Rotation about the camera y axis between the views (:func:`tilt_from_rotation`).

    Raises
    ------
    GeometryError
        Fewer than 8 points, a degenerate eight-point problem (e.g. affine-looking views of
        a nearly flat surface: use ``camera = "affine"``), matches that an affine camera
        explains as well (:func:`check_perspective_visible`), or no consistent pose.
    """
    from .epipolar import fundamental_8point

    a = np.asarray(x0, float)
    b = np.asarray(x1, float)
    s = _check_pixel_size(pixel_size_um)
    if F is None:
        try:
            F = fundamental_8point(a, b)
        except GeometryError as exc:
            raise GeometryError(
                f"camera = 'perspective': {exc}. The views look like parallel projections "
                "(usual for SEM above ~1000x): use camera = 'affine'") from exc
    check_perspective_visible(a, b, F)
    X, R, t = triangulate_perspective(K, F, a, b)
    f = float(np.sqrt(abs(np.linalg.det(np.asarray(K, float)[:2, :2]))))
    depth = float(np.median(X[:, 2]))
    k = s * f / depth
    xyz = X * k
    xyz[:, 2] = -xyz[:, 2]
    return xyz, R, t * k, tilt_from_rotation(R)


def perspective_height_sigma(K, R, t_um, x0, x1, sigma_px):
    """1σ height error of perspective-triangulated points from their matching error.

    The match in view 1 is moved by ``sigma_px`` along x (the parallax direction) and the
    point re-triangulated with the pose kept (:func:`heights_perspective` gives ``R`` and
    ``t_um``); the change of depth is the height error. The uncertainty of the pose itself
    is not included.

    Parameters
    ----------
    K : (3, 3) array
    R : (3, 3) array, t_um : (3,) array
        Pose of camera 1 relative to camera 0, ``t_um`` in µm.
    x0, x1 : (N, 2) arrays of (x, y) pixels
    sigma_px : float or (N,) array
        1σ matching error of each point in view 1, pixels.

    Returns
    -------
    (N,) array of z errors in µm.
    """
    k = np.asarray(K, float)
    t = np.asarray(t_um, float)
    scale = float(np.linalg.norm(t))
    if not scale > 0:
        raise GeometryError("t_um must be a non-zero translation")
    kinv = np.linalg.inv(k)
    a = np.asarray(x0, float)
    b = np.asarray(x1, float)
    p0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    p1 = np.hstack([np.asarray(R, float), (t / scale)[:, None]])
    na = _normalized(kinv, a)
    X, _ = _triangulate_linear(p0, p1, na, _normalized(kinv, b))
    sig = np.broadcast_to(np.asarray(sigma_px, float), (len(a),))
    Xp, _ = _triangulate_linear(p0, p1, na,
                                _normalized(kinv, b + np.column_stack([sig, 0 * sig])))
    return np.abs(Xp[:, 2] - X[:, 2]) * scale


#: A perspective F must fit the matches this many times better (RMS) than an affine one.
PERSPECTIVE_GAIN_MIN = 2.0


def check_perspective_visible(x0, x1, F):
    """Refuse a perspective reconstruction of views that look like parallel projections.

    On SEM views at high magnification the eight-point F is fitted to the matching noise:
    it is "determined" but meaningless, and the triangulated depths are noise of any size
    (metres). The perspective model is used only when it explains the matches clearly
    better than the affine camera: the RMS geometric residual of the affine epipolar
    geometry (Gold Standard hyperplane, H&Z Alg. 14.1) must exceed
    :data:`PERSPECTIVE_GAIN_MIN` times the RMS Sampson residual of ``F``, both per degree of
    freedom left (n − 4 and n − 7 for n matches), and the gain must also pass an F-test at the
    0.1 % level (with few matches a better fit of the 7-parameter F is no evidence).

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) pixels
    F : (3, 3) array
        The perspective fundamental matrix, ``x1ᵀ F x0 = 0``.

    Returns
    -------
    (rms_affine_px, rms_perspective_px)

    Raises
    ------
    GeometryError
        When the perspective F fits less than :data:`PERSPECTIVE_GAIN_MIN` times better.
    """
    from .epipolar import sampson_distance

    a = np.asarray(x0, float)
    b = np.asarray(x1, float)
    n = len(a)
    X = np.hstack([b, a])
    sv = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    # residuals per degree of freedom left (affine F: 4 parameters, perspective F: 7), so that
    # a few points, which any F with more parameters fits better, do not pass as perspective
    dof_aff, dof_per = max(n - 4, 0), max(n - 7, 0)
    rms_aff = float(sv[-1] / np.sqrt(max(dof_aff, 1)))
    ss_per = float(np.sum(np.asarray(sampson_distance(F, a, b), float) ** 2))
    rms_per = float(np.sqrt(ss_per / dof_per)) if dof_per > 0 else np.inf
    # and a gain that few points could give by chance is not enough (F-test, 0.1 % level)
    from scipy.stats import f as f_dist

    gain_min = PERSPECTIVE_GAIN_MIN
    if dof_per > 0:
        gain_min = max(gain_min, float(np.sqrt(f_dist.ppf(0.999, dof_aff, dof_per))))
    if not rms_aff > gain_min * rms_per:
        raise GeometryError(
            f"camera = 'perspective': the {len(a)} matches fit an affine (parallel-projection) "
            f"camera as well as a perspective one (RMS residual {rms_aff:.3g} px affine, "
            f"{rms_per:.3g} px perspective), so the perspective pose and depths are "
            "undetermined and the heights would be noise. The views look like SEM views at "
            "high magnification: use camera = 'affine'")
    return rms_aff, rms_per
