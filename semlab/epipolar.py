"""Epipolar geometry of two views: fundamental matrices, epipoles, epipolar distances.

The fundamental matrix ``F`` relates corresponding points of view 0 and view 1 by
``x1ᵀ F x0 = 0`` with ``x = (x, y, 1)`` in pixels (Hartley & Zisserman, *Multiple View
Geometry*, 2nd ed., ch. 9). Two estimators:

- :func:`fundamental_8point`, the normalised eight-point algorithm (H&Z Alg. 11.1) for
  perspective cameras (the reference paper's method);
- :func:`fundamental_affine`, the Gold Standard affine estimator (H&Z Alg. 14.1) for
  parallel-projection (SEM) views, ``F = [[0, 0, a], [0, 0, b], [c, d, e]]``.

Points are ``(N, 2)`` arrays of ``(x, y)`` in pixels, x right, y down, origin at the
centre of the top-left pixel (OpenCV). Every ``F`` returned has unit Frobenius norm.
"""

from __future__ import annotations

import numpy as np
from tqdm.auto import tqdm

from .errors import GeometryError

__all__ = [
    "hartley_normalization",
    "fundamental_8point",
    "fundamental_affine",
    "ransac_fundamental",
    "epipoles",
    "epipolar_lines",
    "sampson_distance",
    "symmetric_epipolar_distance",
    "affine_tilt_axis",
    "stability",
]

_MODELS = ("8point", "affine")
_MIN_POINTS = {"8point": 8, "affine": 4}
# A second-smallest singular value below this fraction of the largest (noise-free data) or
# below this multiple of the smallest one (noisy data) means a null space of dimension > 1.
_RANK_RTOL = 1e-9
_NULL_RATIO = 1.5
_COLLINEAR_RTOL = 1e-6


# ----------------------------------------------------------------------------- helpers

def hartley_normalization(pts):
    """Similarity that centres points and scales their mean distance to √2 (H&Z §4.4.4).

    Parameters
    ----------
    pts : (N, 2) array of (x, y) in pixels (N >= 1, finite).

    Returns
    -------
    T : (3, 3) array
        ``x_n = T @ [x, y, 1]``.
    pts_n : (N, 2) array
        Normalised points.
    """
    p = np.asarray(pts, float).reshape(-1, 2)
    c = p.mean(axis=0)
    d = np.sqrt(((p - c) ** 2).sum(axis=1)).mean()
    s = np.sqrt(2.0) / d if d > 0 else 1.0
    T = np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])
    return T, (p - c) * s


def _homog(pts):
    p = np.asarray(pts, float).reshape(-1, 2)
    return np.hstack([p, np.ones((len(p), 1))])


def _as_points(pts, name):
    try:
        p = np.asarray(pts, dtype=float)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name} must be an (N, 2) array of (x, y) pixels: {exc}") from None
    if p.ndim != 2 or p.shape[1] != 2:
        raise GeometryError(f"{name} must be an (N, 2) array of (x, y) pixels, got shape {p.shape}")
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise GeometryError(
            f"{name} has NaN/inf coordinates at rows {np.flatnonzero(bad)[:10].tolist()}; "
            "drop those correspondences before estimating F")
    return p


def _check_pairs(x0, x1, model):
    """Validate a correspondence set for ``model``; return float arrays."""
    if model not in _MODELS:
        raise GeometryError(f"model must be one of {_MODELS}, got {model!r}")
    x0 = _as_points(x0, "x0")
    x1 = _as_points(x1, "x1")
    if len(x0) != len(x1):
        raise GeometryError(f"x0 and x1 must hold the same number of points, got {len(x0)} and {len(x1)}")
    n_min = _MIN_POINTS[model]
    if len(x0) < n_min:
        hint = " (or use model='affine', which needs 4)" if model == "8point" else ""
        raise GeometryError(
            f"the {model} fundamental matrix needs at least {n_min} correspondences, got {len(x0)}; "
            f"click more points{hint}")
    for name, p in (("x0", x0), ("x1", x1)):
        _, first = np.unique(p, axis=0, return_index=True)
        if len(first) < len(p):
            dup = np.setdiff1d(np.arange(len(p)), first)[:10]
            raise GeometryError(
                f"{name} has duplicate points (rows {dup.tolist()}); each correspondence must be "
                "a distinct point: remove the repeated clicks")
        _, pn = hartley_normalization(p)
        sv = np.linalg.svd(pn, compute_uv=False)
        if sv[1] <= _COLLINEAR_RTOL * sv[0]:
            raise GeometryError(
                f"the points of {name} are (nearly) collinear, so F is undetermined; "
                "click points spread over the whole image, not along one line")
    return x0, x1


def _null_space_is_large(sv):
    """True if the two smallest singular values say the null space has dimension > 1."""
    return sv[-2] <= _RANK_RTOL * sv[0] or sv[-2] <= _NULL_RATIO * sv[-1]


def _design_8point(x0n, x1n):
    """Rows ``kron(x1, x0)`` so that ``A @ F.ravel() = x1ᵀ F x0`` (H&Z eq. 11.3)."""
    h0 = np.concatenate([x0n, np.ones(x0n.shape[:-1] + (1,))], axis=-1)
    h1 = np.concatenate([x1n, np.ones(x1n.shape[:-1] + (1,))], axis=-1)
    return (h1[..., :, None] * h0[..., None, :]).reshape(h0.shape[:-1] + (9,))


def _enforce_rank2(F):
    """Closest rank-2 matrices (Frobenius), batched over leading axes (H&Z §11.1.1)."""
    U, s, Vt = np.linalg.svd(F)
    s = s.copy()
    s[..., 2] = 0.0
    return (U * s[..., None, :]) @ Vt


def _unit(F):
    F = np.asarray(F, float)
    return F / np.linalg.norm(F.reshape(F.shape[:-2] + (9,)), axis=-1)[..., None, None]


def _svd_padded(A):
    """Singular values and right vectors of A (..., M, 9), singular values padded to 9."""
    # full U only when needed for a complete 9×9 Vt (M < 9): for tens of thousands of
    # automatic matches a full M×M U would take minutes and gigabytes
    _, s, Vt = np.linalg.svd(A, full_matrices=A.shape[-2] < 9)
    if s.shape[-1] < 9:
        pad = np.zeros(s.shape[:-1] + (9 - s.shape[-1],))
        s = np.concatenate([s, pad], axis=-1)
    return s, Vt


# ----------------------------------------------------------------------------- estimators

def fundamental_8point(x0, x1):
    """Fundamental matrix by the normalised eight-point algorithm (H&Z Alg. 11.1).

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) in pixels
        Corresponding points in view 0 and view 1, N >= 8.

    Returns
    -------
    F : (3, 3) array
        Rank 2, unit Frobenius norm, ``x1ᵀ F x0 = 0``.

    Raises
    ------
    GeometryError
        Too few points, NaN, duplicates, collinear points, or a design matrix of rank < 8
        (a planar scene, or affine cameras on a flat scene): the perspective F is then
        undetermined.
    """
    x0, x1 = _check_pairs(x0, x1, "8point")
    T0, x0n = hartley_normalization(x0)
    T1, x1n = hartley_normalization(x1)
    sv, Vt = _svd_padded(_design_8point(x0n, x1n))
    if _null_space_is_large(sv):
        raise GeometryError(
            "the eight-point design matrix has rank < 8 (null space of dimension > 1), so the "
            "perspective fundamental matrix is undetermined: the points are (nearly) coplanar, "
            "or the views are parallel (affine) projections of a flat scene. For SEM views use "
            "camera = \"affine\" / fundamental_affine (it needs some height relief), or click "
            "points at clearly different heights")
    Fn = _enforce_rank2(Vt[-1].reshape(3, 3))
    return _unit(T1.T @ Fn @ T0)


def fundamental_affine(x0, x1):
    """Affine fundamental matrix by the Gold Standard algorithm (H&Z Alg. 14.1).

    Minimises the geometric (orthogonal) distance of the 4-vectors ``(x1, y1, x0, y0)`` to
    the hyperplane ``a x1 + b y1 + c x0 + d y0 + e = 0``.

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) in pixels
        Corresponding points in view 0 and view 1, N >= 4.

    Returns
    -------
    F : (3, 3) array
        ``[[0, 0, a], [0, 0, b], [c, d, e]]`` with unit Frobenius norm, ``x1ᵀ F x0 = 0``.

    Raises
    ------
    GeometryError
        Too few points, NaN, duplicates, collinear points, or points related by an affine
        map (a flat scene without height relief): the epipolar geometry is undetermined.
    """
    x0, x1 = _check_pairs(x0, x1, "affine")
    X = np.hstack([x1, x0])
    mean = X.mean(axis=0)
    _, sv, Vt = np.linalg.svd(X - mean, full_matrices=False)
    if _null_space_is_large(sv):
        raise GeometryError(
            "the affine epipolar geometry is undetermined: view 1 is an affine map of view 0 "
            "within the points' own scatter (their height relief is not above their position "
            "error, or there is no tilt between the views). Click points at clearly different "
            "heights (ridges, pits, particles), refine the clicks, or use views with a larger "
            "tilt")
    a, b, c, d = Vt[-1]
    e = -Vt[-1] @ mean
    return _unit(np.array([[0.0, 0.0, a], [0.0, 0.0, b], [c, d, e]]))


def _fit(x0, x1, model):
    return fundamental_8point(x0, x1) if model == "8point" else fundamental_affine(x0, x1)


def _batch_fit(x0n, x1n, idx, model):
    """Fit F to every sample ``idx`` (B, m) in normalised coordinates; None rows degenerate."""
    a0, a1 = x0n[idx], x1n[idx]
    if model == "8point":
        sv, Vt = _svd_padded(_design_8point(a0, a1))
        F = _enforce_rank2(Vt[:, -1].reshape(-1, 3, 3))
    else:
        X = np.concatenate([a1, a0], axis=-1)
        mean = X.mean(axis=1, keepdims=True)
        _, sv, Vt = np.linalg.svd(X - mean, full_matrices=False)
        n = Vt[:, -1]
        e = -(n * mean[:, 0]).sum(axis=1)
        F = np.zeros((len(idx), 3, 3))
        F[:, 0, 2], F[:, 1, 2], F[:, 2, 0], F[:, 2, 1], F[:, 2, 2] = n[:, 0], n[:, 1], n[:, 2], n[:, 3], e
        sv = sv.copy()
        sv[:, -1] = 0.0  # minimal samples fit exactly; only the rank test matters
    ok = sv[:, -2] > _RANK_RTOL * sv[:, 0]
    return F, ok


def ransac_fundamental(x0, x1, model="8point", threshold_px=1.0, n_iter=2000, seed=0):
    """Robust fundamental matrix by RANSAC (H&Z Alg. 11.4) with a final refit on the inliers.

    Minimal samples (8 points, or 4 for ``model="affine"``) are fitted in Hartley-normalised
    coordinates; a correspondence is an inlier when its Sampson distance
    (:func:`sampson_distance`) is below ``threshold_px``. The best consensus set is refitted
    with :func:`fundamental_8point` / :func:`fundamental_affine`, its inliers recomputed and
    refitted once more.

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) in pixels
    model : {"8point", "affine"}
    threshold_px : float
        Inlier threshold on the Sampson distance, pixels.
    n_iter : int
        Number of random samples.
    seed : int
        Seed of the random generator (results are reproducible).

    Returns
    -------
    F : (3, 3) array, unit norm.
    inliers : (N,) bool array
    """
    x0, x1 = _check_pairs(x0, x1, model)
    if not threshold_px > 0:
        raise GeometryError(f"threshold_px must be > 0, got {threshold_px!r}")
    m = _MIN_POINTS[model]
    n = len(x0)
    T0, x0n = hartley_normalization(x0)
    T1, x1n = hartley_normalization(x1)
    rng = np.random.default_rng(seed)
    best, best_key = None, (-1, np.inf)
    for start in range(0, int(n_iter), 256):
        b = min(256, int(n_iter) - start)
        idx = np.argsort(rng.random((b, n)), axis=1)[:, :m]
        Fn, ok = _batch_fit(x0n, x1n, idx, model)
        F = T1.T @ Fn[ok] @ T0
        if len(F) == 0:
            continue
        d = _sampson_batch(F, x0, x1)
        inl = d < threshold_px
        count = inl.sum(axis=1)
        score = np.where(inl, d, threshold_px).sum(axis=1)
        k = np.lexsort((score, -count))[0]
        key = (count[k], score[k])
        if key[0] > best_key[0] or (key[0] == best_key[0] and key[1] < best_key[1]):
            best, best_key = inl[k], key
    if best is None or best.sum() < m:
        raise GeometryError(
            "RANSAC found no consensus: every sample was degenerate or had fewer than "
            f"{m} inliers within {threshold_px} px; check the correspondences or raise threshold_px")
    F = _fit(x0[best], x1[best], model)
    inliers = sampson_distance(F, x0, x1) < threshold_px
    if inliers.sum() >= m and not np.array_equal(inliers, best):
        F = _fit(x0[inliers], x1[inliers], model)
        inliers = sampson_distance(F, x0, x1) < threshold_px
    return F, inliers


# ----------------------------------------------------------------------------- geometry

def _sign_fix(v):
    """Make a homogeneous vector's last (else first non-zero) coordinate positive."""
    v = v / np.linalg.norm(v)
    scale = np.max(np.abs(v))
    k = 2 if abs(v[2]) > 1e-12 * scale else int(np.argmax(np.abs(v) > 1e-12 * scale))
    return -v if v[k] < 0 else v


def epipoles(F):
    """Epipoles of a fundamental matrix (H&Z Result 9.13).

    Parameters
    ----------
    F : (3, 3) array

    Returns
    -------
    e0, e1 : (3,) homogeneous unit vectors
        ``F e0 = 0`` (epipole in view 0), ``Fᵀ e1 = 0`` (epipole in view 1). For an affine
        ``F`` they are points at infinity ``(dx, dy, 0)``, the epipolar-line directions.
        Signs: last coordinate >= 0 (else the first non-zero one > 0).
    """
    F = np.asarray(F, float)
    U, _, Vt = np.linalg.svd(F)
    return _sign_fix(Vt[-1]), _sign_fix(U[:, -1])


def epipolar_lines(F, pts, from_view=0):
    """Epipolar lines of points, normalised so that ``a² + b² = 1``.

    Parameters
    ----------
    F : (3, 3) array
    pts : (N, 2) array of (x, y) in pixels, in view ``from_view``.
    from_view : {0, 1}
        ``0``: lines ``F x0`` in view 1; ``1``: lines ``Fᵀ x1`` in view 0.

    Returns
    -------
    (N, 3) array of lines ``(a, b, c)``; ``a x + b y + c`` is the signed distance in pixels.
    A point at the epipole has no epipolar line (row of NaN).
    """
    if from_view not in (0, 1):
        raise GeometryError(f"from_view must be 0 or 1, got {from_view!r}")
    F = np.asarray(F, float)
    h = _homog(_as_points(pts, "pts"))
    L = h @ (F.T if from_view == 0 else F)
    nrm = np.hypot(L[:, 0], L[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        return L / np.where(nrm > 0, nrm, np.nan)[:, None]


def _sampson_batch(F, x0, x1):
    """Sampson distance (B, N) for a stack of F (B, 3, 3)."""
    h0, h1 = _homog(x0), _homog(x1)
    Fx0 = np.einsum("bij,nj->bni", F, h0)
    Ftx1 = np.einsum("bji,nj->bni", F, h1)
    num = np.einsum("ni,bni->bn", h1, Fx0)
    den = Fx0[..., 0] ** 2 + Fx0[..., 1] ** 2 + Ftx1[..., 0] ** 2 + Ftx1[..., 1] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(num) / np.sqrt(den)


def sampson_distance(F, x0, x1):
    """First-order geometric (Sampson) distance of each correspondence, pixels.

    The square root of the Sampson error of H&Z eq. 11.9:
    ``|x1ᵀFx0| / sqrt((Fx0)₁² + (Fx0)₂² + (Fᵀx1)₁² + (Fᵀx1)₂²)``, the distance in the joint
    4D space ``(x0, y0, x1, y1)`` to the epipolar variety, to first order.

    Parameters
    ----------
    F : (3, 3) array
        Fundamental matrix, ``x1ᵀ F x0 = 0`` for a true correspondence.
    x0, x1 : (N, 2) arrays of (x, y) in pixels
        Corresponding points in view 0 and view 1.

    Returns
    -------
    (N,) array of Sampson distances, pixels.
    """
    x0, x1 = _as_points(x0, "x0"), _as_points(x1, "x1")
    return _sampson_batch(np.asarray(F, float)[None], x0, x1)[0]


def symmetric_epipolar_distance(F, x0, x1):
    """RMS of the two point-to-epipolar-line distances (H&Z eq. 11.10), pixels.

    ``sqrt((d(x1, F x0)² + d(x0, Fᵀ x1)²) / 2)``.

    Parameters
    ----------
    F : (3, 3) array
    x0, x1 : (N, 2) arrays of (x, y) in pixels

    Returns
    -------
    (N,) array, pixels.
    """
    x0, x1 = _as_points(x0, "x0"), _as_points(x1, "x1")
    d1 = np.sum(epipolar_lines(F, x0, 0) * _homog(x1), axis=1)
    d0 = np.sum(epipolar_lines(F, x1, 1) * _homog(x0), axis=1)
    return np.sqrt((d0 ** 2 + d1 ** 2) / 2.0)


def affine_tilt_axis(F):
    """Tilt-axis and epipolar-line directions of an affine fundamental matrix.

    For parallel projection the epipolar lines of a view are parallel, along the epipole
    at infinity ``e = (dx, dy, 0)`` (H&Z §14.2); the tilt axis is perpendicular to them in
    the image. A eucentric tilt about the image y axis gives horizontal epipolar lines
    (0°) and a tilt axis at 90°.

    Parameters
    ----------
    F : (3, 3) array
        Affine fundamental matrix ``[[0, 0, a], [0, 0, b], [c, d, e]]``.

    Returns
    -------
    axis_deg : (2,) array
        Tilt-axis direction in view 0 and view 1, degrees in [0, 180), measured from the
        image x axis towards the image y axis (clockwise on screen, since y points down).
    line_deg : (2,) array
        Epipolar-line direction in view 0 and view 1, same convention.

    Raises
    ------
    GeometryError
        If ``F`` is not of the affine form.
    """
    F = _unit(np.asarray(F, float))
    if np.abs(F[:2, :2]).max() > 1e-6:
        raise GeometryError(
            "affine_tilt_axis needs an affine fundamental matrix (upper-left 2x2 block zero); "
            "estimate it with fundamental_affine or model='affine'")
    # epipolar lines of view 0, Fᵀ x1 = (c, d, ·), all have the normal (c, d); those of
    # view 1, F x0 = (a, b, ·), the normal (a, b). The tilt axis is along the normal.
    normals = np.array([F[2, :2], F[:2, 2]])
    if np.any(np.linalg.norm(normals, axis=1) < 1e-12):
        raise GeometryError("the affine fundamental matrix is degenerate (an epipolar-line normal is zero)")
    normal_deg = np.degrees(np.arctan2(normals[:, 1], normals[:, 0])) % 180.0
    line_deg = (normal_deg + 90.0) % 180.0
    return normal_deg, line_deg


def _angle_between_deg(a, b):
    """Angle between unit vectors up to sign, degrees, batched over the first axis."""
    c = np.abs(np.sum(a * b, axis=-1)) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def stability(x0, x1, sizes, n_resamples=50, model="8point", seed=0, progress=True):
    """How F settles as the number of correspondences grows (the reference paper's test).

    For each subset size, ``n_resamples`` random subsets are fitted and compared with F of
    all points.

    Parameters
    ----------
    x0, x1 : (N, 2) arrays of (x, y) in pixels
    sizes : sequence of int
        Subset sizes, each between the model's minimum (8 or 4) and N.
    n_resamples : int
    model : {"8point", "affine"}
    seed : int
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    dict of (S,) arrays, S = len(sizes):
        ``sizes``; ``f_angle_deg_median`` / ``f_angle_deg_iqr``: angle between F(subset) and
        F(all) as unit 9-vectors, sign-aligned; ``epipole_angle_deg_median`` /
        ``epipole_angle_deg_iqr``: angle between the view-0 epipoles as homogeneous unit
        vectors (for affine F: the change of the epipolar-line direction in the image);
        ``sampson_px_median``: median over resamples of the median Sampson distance of all
        points; ``n_failed``: subsets that were degenerate.
    """
    x0, x1 = _check_pairs(x0, x1, model)
    sizes = np.asarray(sizes, dtype=int).ravel()
    m = _MIN_POINTS[model]
    if sizes.size == 0 or sizes.min() < m or sizes.max() > len(x0):
        raise GeometryError(f"sizes must lie between {m} and the number of points {len(x0)}, got {sizes.tolist()}")
    if int(n_resamples) < 1:
        raise GeometryError(f"n_resamples must be >= 1, got {n_resamples!r}")
    F_all = _fit(x0, x1, model)
    e_all = epipoles(F_all)[0]
    rng = np.random.default_rng(seed)
    keys = ("f_angle_deg_median", "f_angle_deg_iqr", "epipole_angle_deg_median",
            "epipole_angle_deg_iqr", "sampson_px_median", "n_failed")
    out = {k: np.full(len(sizes), np.nan) for k in keys}
    for i, size in enumerate(tqdm(sizes, desc="F stability", disable=not progress)):
        fa, ea, sd, failed = [], [], [], 0
        for _ in range(int(n_resamples)):
            sub = rng.choice(len(x0), size=int(size), replace=False)
            try:
                F = _fit(x0[sub], x1[sub], model)
            except GeometryError:
                failed += 1
                continue
            fa.append(_angle_between_deg(F.ravel(), F_all.ravel()))
            ea.append(_angle_between_deg(epipoles(F)[0], e_all))
            sd.append(np.median(sampson_distance(F, x0, x1)))
        out["n_failed"][i] = failed
        if fa:
            for name, v in (("f_angle_deg", fa), ("epipole_angle_deg", ea)):
                q25, q50, q75 = np.percentile(v, [25, 50, 75])
                out[name + "_median"][i], out[name + "_iqr"][i] = q50, q75 - q25
            out["sampson_px_median"][i] = np.median(sd)
    out["sizes"] = sizes
    out["n_failed"] = out["n_failed"].astype(int)
    return out
