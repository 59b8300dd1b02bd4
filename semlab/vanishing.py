"""Camera calibration from vanishing points (the reference paper §4.1).

Line families (images of parallel 3D edges of a calibration block) are clicked in one or
more views and stored in ``lines.json`` (schema ``"semlab-lines/1"``). Each family gives a
vanishing point; three families of mutually orthogonal directions give the intrinsics ``K``
(zero skew, square pixels) through the image of the absolute conic ``ω`` and the rotation of
the block in each view (Hartley & Zisserman, *Multiple View Geometry*, 2nd ed., §8.6–8.8,
example 8.27, table 8.1).

Points and segments are in pixels, x right, y down, origin at the centre of the top-left
pixel. A segment is ``(x1, y1, x2, y2)``. Homogeneous vectors are unit 3-vectors; a
vanishing point at infinity has a last coordinate ≈ 0.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .epipolar import hartley_normalization
from .io import read_text, write_with_backup
from .errors import GeometryError, SemlabError

__all__ = [
    "SCHEMA",
    "read_lines",
    "write_lines",
    "vanishing_point",
    "calibrate_k",
    "rotation_from_vps",
    "relative_rotation",
    "axis_angle",
    "euler_zyx_deg",
    "VanishingCalibration",
    "calibrate_views",
    "refine_calibration",
]

SCHEMA = "semlab-lines/1"
_FAMILY_ORDER = ("x", "y", "z")
# Conditioning thresholds (dimensionless, in Hartley-normalised coordinates).
_RANK_RTOL = 1e-6          # second-smallest / largest singular value of the ω system
_PARALLEL_DEG = 2.0        # two conditioned vps closer than this angle: parallel families
_INFINITY_RTOL = 1e-9      # |w| / ||v|| below this: the vp is at infinity


# ----------------------------------------------------------------------------- lines.json

def _lines_error(path, msg, view=None, family=None):
    where = f"{path}"
    if view is not None:
        where += f", view {view}"
    if family is not None:
        where += f", family {family!r}"
    return SemlabError(f"{where}: {msg}")


def _check_family(segs, path, view, family):
    try:
        a = np.asarray(segs, dtype=float)
    except (TypeError, ValueError):
        raise _lines_error(path, "segments must be lists of 4 numbers [x1, y1, x2, y2] in pixels",
                           view, family) from None
    if a.ndim != 2 or a.shape[1] != 4:
        raise _lines_error(path, f"segments must be an (M, 4) list of [x1, y1, x2, y2], got shape {a.shape}",
                           view, family)
    if len(a) < 2:
        raise _lines_error(path, f"a family needs at least 2 segments (images of parallel edges), got {len(a)}; "
                           "click at least two edges of this direction", view, family)
    if not np.isfinite(a).all():
        raise _lines_error(path, "segments contain NaN/inf; re-click those edges", view, family)
    zero = np.flatnonzero(np.hypot(a[:, 2] - a[:, 0], a[:, 3] - a[:, 1]) == 0)
    if zero.size:
        raise _lines_error(path, f"segments {zero.tolist()} have zero length (both end points equal); "
                           "click two distinct end points along the edge", view, family)
    return a


def read_lines(path):
    """Read and validate a ``lines.json`` file (schema ``"semlab-lines/1"``).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    list of dict
        One dict per view (in the order of the file), ``{family_name: (M, 4) array}`` of
        segments ``(x1, y1, x2, y2)`` in pixels, M >= 2.

    Raises
    ------
    SemlabError
        Unreadable or invalid JSON, wrong schema, missing keys, a family with fewer than two
        segments, a zero-length segment or NaN; the message names the file, view and family.
    """
    path = Path(path)
    if not path.is_file():
        raise _lines_error(path, "cannot read the file (not found); check `lines = ...` in the [stereo] section "
                           "of experiment.toml")
    try:
        doc = json.loads(read_text(path, "lines file"))
    except json.JSONDecodeError as exc:
        raise _lines_error(path, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}; "
                           "fix the file or re-save it with the line-clicking widget") from None
    if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
        got = doc.get("schema") if isinstance(doc, dict) else type(doc).__name__
        raise _lines_error(path, f"expected a JSON object with \"schema\": \"{SCHEMA}\", got {got!r}")
    views = doc.get("views")
    if not isinstance(views, list) or not views:
        raise _lines_error(path, "missing key \"views\" (a non-empty list of {\"view\", \"image\", \"families\"})")
    out = []
    for i, v in enumerate(views):
        if not isinstance(v, dict) or not isinstance(v.get("families"), dict):
            raise _lines_error(path, "missing key \"families\" (an object {name: [[x1, y1, x2, y2], ...]})", i)
        if not v["families"]:
            raise _lines_error(path, "\"families\" is empty; click at least three line families", i)
        out.append({str(name): _check_family(segs, path, i, name) for name, segs in v["families"].items()})
    return out


def _entries(views, images, path):
    """Normalise the accepted inputs of :func:`write_lines` to schema entries."""
    if isinstance(views, dict):
        if views.get("schema", SCHEMA) != SCHEMA or not isinstance(views.get("views"), list):
            raise SemlabError(f"{path}: a document to write must have \"schema\": \"{SCHEMA}\" and a list \"views\"")
        views = views["views"]
    if images is not None and len(images) != len(views):
        raise SemlabError(f"{path}: got {len(images)} image names for {len(views)} views")
    out = []
    for i, v in enumerate(views):
        if not isinstance(v, dict):
            raise SemlabError(f"{path}, view {i}: expected a dict of families, got {type(v).__name__}")
        fams = v["families"] if isinstance(v.get("families"), dict) else v
        entry = {"view": int(v.get("view", i)) if "families" in v else i}
        image = images[i] if images is not None else v.get("image") if "families" in v else None
        if image is not None:
            entry["image"] = str(image)
        entry["families"] = {str(k): _check_family(s, path, i, k).tolist() for k, s in fams.items()}
        out.append(entry)
    return out


def write_lines(path, views, images=None, backup=True):
    """Write line families to ``lines.json`` (schema ``"semlab-lines/1"``).

    An existing file is never overwritten silently: it is first copied to ``<stem>.bak.json``
    (or ``.bak1.json``, ... if that exists; :func:`semlab.io.write_with_backup`). The data are validated as by
    :func:`read_lines` before anything is touched.

    Parameters
    ----------
    path : str or Path
    views : list of dict, or dict
        One ``{family_name: (M, 4) array-like}`` per view (segments ``(x1, y1, x2, y2)`` in
        pixels), or schema entries ``{"view", "image", "families"}``, or a whole document
        ``{"schema": "semlab-lines/1", "views": [...]}``.
    images : list of str, optional
        Image path of each view (relative to the experiment folder), stored as ``"image"``.
    backup : bool
        Keep the existing file as a backup (default). ``False`` replaces it explicitly.

    Returns
    -------
    Path or None
        The backup file written, if any.
    """
    path = Path(path)
    text = json.dumps({"schema": SCHEMA, "views": _entries(views, images, path)}, indent=1)
    return write_with_backup(path, text + "\n", backup=backup)


# ----------------------------------------------------------------------------- vanishing points

def _segment_lines(segs):
    """Homogeneous lines through the end points of each segment, (M, 3), unit (a, b)."""
    p = np.hstack([segs[:, :2], np.ones((len(segs), 1))])
    q = np.hstack([segs[:, 2:], np.ones((len(segs), 1))])
    L = np.cross(p, q)
    return L / np.hypot(L[:, 0], L[:, 1])[:, None]


def _unit_sign(v):
    v = np.asarray(v, float) / np.linalg.norm(v)
    k = 2 if abs(v[2]) > _INFINITY_RTOL else int(np.argmax(np.abs(v) > _INFINITY_RTOL))
    return -v if v[k] < 0 else v


def _midpoint_residuals(vp, segs):
    """Signed distance of each segment's first end point to the line (midpoint, vp), px."""
    mid = np.hstack([(segs[:, :2] + segs[:, 2:]) / 2.0, np.ones((len(segs), 1))])
    lines = np.cross(mid, vp)
    lines = lines / np.hypot(lines[:, 0], lines[:, 1])[:, None]
    return np.sum(lines[:, :2] * segs[:, :2], axis=1) + lines[:, 2]


def _refine_vp(vp, segs, n_iter=20):
    """Gauss-Newton minimisation of the end-point residuals over the unit sphere (H&Z §8.6.1).

    Works in Hartley-normalised coordinates with a local 2-parameter update orthogonal to the
    current estimate, so points at infinity need no special case.
    """
    T, _ = hartley_normalization(segs.reshape(-1, 2))
    p = np.c_[segs.reshape(-1, 2), np.ones(2 * len(segs))] @ T.T
    segn = np.hstack([p[0::2, :2], p[1::2, :2]])
    v = T @ vp
    v /= np.linalg.norm(v)
    cost = np.sum(_midpoint_residuals(v, segn) ** 2)
    for _ in range(n_iter):
        B = np.linalg.svd(v[None])[2][1:].T                       # (3, 2) tangent basis
        r = _midpoint_residuals(v, segn)
        eps = 1e-7
        J = np.stack([(_midpoint_residuals(v + eps * B[:, k], segn) - r) / eps for k in range(2)], axis=1)
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        v_new = v + B @ step
        v_new /= np.linalg.norm(v_new)
        new_cost = np.sum(_midpoint_residuals(v_new, segn) ** 2)
        if not new_cost < cost:
            break
        converged = cost - new_cost <= 1e-14 * max(cost, 1e-300)
        v, cost = v_new, new_cost
        if converged:
            break
    return _unit_sign(np.linalg.solve(T, v))


def vanishing_point(segments, refine=True):
    """Vanishing point of a family of image segments (H&Z §8.6.1).

    Each segment gives the line through its end points; in Hartley-normalised coordinates
    the linear estimate is the right singular vector of the smallest singular value of the
    stacked lines. With ``refine`` it is then refined to the maximum-likelihood estimate
    under isotropic end-point noise: the vp minimising the summed squared distances of the
    end points to the lines joining each segment's midpoint with the vp (Gauss-Newton on the
    unit sphere). A point at infinity (parallel image lines) is a legal result.

    Parameters
    ----------
    segments : (M, 4) array of (x1, y1, x2, y2) in pixels, M >= 2.
    refine : bool
        Refine the linear estimate by minimising the residuals.

    Returns
    -------
    vp : (3,) homogeneous unit vector (last coordinate >= 0) in pixel coordinates.
    residuals : (M,) array, pixels
        Distance of each segment's end points (both are equally far) from the line joining
        its midpoint to ``vp``.

    Raises
    ------
    GeometryError
        Fewer than two segments, NaN, zero-length segments, or all segments on one line.
    """
    try:
        segs = _check_family(segments, "segments", None, None)
    except SemlabError as exc:
        raise GeometryError(str(exc)) from None
    T, _ = hartley_normalization(segs.reshape(-1, 2))
    Ln = _segment_lines(segs) @ np.linalg.inv(T)          # l' = T⁻ᵀ l, stored as rows
    Ln /= np.linalg.norm(Ln, axis=1)[:, None]
    _, sv, Vt = np.linalg.svd(Ln)
    if len(sv) >= 2 and sv[1] <= 1e-9 * sv[0]:
        raise GeometryError("all segments of the family lie on one image line, so the vanishing "
                            "point is undetermined; click edges that are distinct parallel lines")
    vp = _unit_sign(np.linalg.solve(T, Vt[-1]))
    if refine and len(segs) > 2:
        vp = _refine_vp(vp, segs)
    return vp, np.abs(_midpoint_residuals(vp, segs))


# ----------------------------------------------------------------------------- K from ω

def _omega_rows(vps):
    """Rows of the linear system vᵢᵀ ω vⱼ = 0 for ω = [[w1,0,w2],[0,w1,w3],[w2,w3,w4]]."""
    rows = []
    for v in vps:
        for i, j in ((0, 1), (0, 2), (1, 2)):
            a, b = v[i], v[j]
            rows.append([a[0] * b[0] + a[1] * b[1], a[0] * b[2] + a[2] * b[0],
                         a[1] * b[2] + a[2] * b[1], a[2] * b[2]])
    A = np.array(rows)
    return A / np.linalg.norm(A, axis=1)[:, None]


def _conditioning_transform(vps):
    """Similarity moving the finite vps to zero mean and unit RMS radius."""
    flat = vps.reshape(-1, 3)
    finite = np.abs(flat[:, 2]) > _INFINITY_RTOL
    if finite.sum() < 2:
        return np.eye(3)
    pts = flat[finite, :2] / flat[finite, 2:3]
    c = pts.mean(axis=0)
    r = np.sqrt(((pts - c) ** 2).sum(axis=1).mean())
    s = 1.0 / r if r > 0 else 1.0
    return np.array([[s, 0.0, -s * c[0]], [0.0, s, -s * c[1]], [0.0, 0.0, 1.0]])


def _check_vp_triplets(vps, vps_cond):
    """Reject vp triplets that cannot determine K (raw and conditioned unit vectors)."""
    for k, (trip, cond) in enumerate(zip(vps, vps_cond)):
        at_inf = np.abs(trip[:, 2]) <= _INFINITY_RTOL
        if at_inf.sum() >= 2:
            raise GeometryError(
                f"view {k}: {int(at_inf.sum())} vanishing points are at infinity (those edge families "
                "are parallel in the image), so the focal length is undetermined; photograph the block "
                "from a corner so that all three edge directions converge visibly")
        for i, j in ((0, 1), (0, 2), (1, 2)):
            ang = np.degrees(np.arccos(min(1.0, abs(cond[i] @ cond[j]))))
            if ang < _PARALLEL_DEG:
                raise GeometryError(
                    f"view {k}: families {i} and {j} (in the order x, y, z) have nearly the same "
                    "vanishing point, i.e. their edges are nearly parallel in 3D; click edges of "
                    "three different, mutually orthogonal directions of the block")


def _focal_known_pp(v, pp):
    """f from orthogonal vp pairs when the principal point is known: a + f² b = 0 per pair."""
    pp = np.asarray(pp, float).reshape(2)
    d = v[..., :2] - pp * v[..., 2:3]                      # vp relative to pp (homogeneous)
    w = v[..., 2]
    pairs = ((0, 1), (0, 2), (1, 2))
    a = np.concatenate([np.sum(d[:, i] * d[:, j], axis=1) for i, j in pairs])
    b = np.concatenate([w[:, i] * w[:, j] for i, j in pairs])
    scale = np.sqrt(np.mean(np.abs(a))) if np.any(a) else 1.0
    rows = np.column_stack([a / scale ** 2, b])
    rows /= np.linalg.norm(rows, axis=1)[:, None]
    _, sv, Vt = np.linalg.svd(rows)
    if np.abs(rows[:, 1]).max() < 1e-9:
        raise GeometryError("every vanishing point is at infinity, so the focal length is undetermined; "
                            "photograph the block so that its edge directions converge in the image")
    n = Vt[-1]
    f2 = n[1] / n[0] * scale ** 2 if n[0] != 0 else -1.0
    if not f2 > 0:
        raise GeometryError(
            "with the given principal point the vanishing points give f² <= 0: the three families "
            "are not images of mutually orthogonal directions, or the principal point is wrong; "
            "check the x, y, z families and the principal point")
    f = np.sqrt(f2)
    return np.array([[f, 0.0, pp[0]], [0.0, f, pp[1]], [0.0, 0.0, 1.0]])


def calibrate_k(vps, principal_point=None):
    """Intrinsics from mutually orthogonal vanishing points (H&Z example 8.27, table 8.1).

    With zero skew and square pixels, ``ω = K⁻ᵀ K⁻¹ = [[w1, 0, w2], [0, w1, w3], [w2, w3, w4]]``
    and each pair of orthogonal directions gives ``vᵢᵀ ω vⱼ = 0``. Three vps per view give
    three equations; several views of the same camera are solved jointly. ``K`` follows from
    the Cholesky factorisation of ω (H&Z §8.8).

    Parameters
    ----------
    vps : (3, 3) or (V, 3, 3) array
        Per view, three homogeneous vanishing points (rows) of mutually orthogonal 3D
        directions, in pixel coordinates.
    principal_point : (2,) sequence of float, optional
        Known ``(cx, cy)`` in pixels (e.g. the image centre). Then only f is estimated
        (least squares over ``(vᵢ - p)·(vⱼ - p) + f² wᵢwⱼ = 0``), which is far more robust
        for weak perspective or few clicked edges.

    Returns
    -------
    K : (3, 3) array, ``[[f, 0, cx], [0, f, cy], [0, 0, 1]]``, pixels.

    Raises
    ------
    GeometryError
        Two families nearly parallel, vanishing points at infinity leaving f undetermined,
        an ill-conditioned system, or ω not positive definite.
    """
    v = np.asarray(vps, float)
    if v.ndim == 2:
        v = v[None]
    if v.ndim != 3 or v.shape[1:] != (3, 3) or not np.isfinite(v).all():
        raise GeometryError("vps must be a finite (3, 3) or (V, 3, 3) array of homogeneous points, "
                            f"got shape {v.shape}")
    v = v / np.linalg.norm(v, axis=2, keepdims=True)
    T = _conditioning_transform(v)
    vn = v @ T.T
    vn /= np.linalg.norm(vn, axis=2, keepdims=True)
    _check_vp_triplets(v, vn)
    if principal_point is not None:
        return _focal_known_pp(v, principal_point)
    _, sv, Vt = np.linalg.svd(_omega_rows(vn))
    if sv[2] <= _RANK_RTOL * sv[0]:
        raise GeometryError(
            "the vanishing points do not determine K (the ω system is rank deficient, "
            f"singular values {np.array2string(sv, precision=3)}): typically one vanishing point is "
            "at or near infinity, so the principal point and focal length slide along a line. "
            "Photograph the block so that all three edge directions converge in the image, or add a view")
    w1, w2, w3, w4 = Vt[-1]
    if w1 < 0:
        w1, w2, w3, w4 = -w1, -w2, -w3, -w4
    cx, cy = -w2 / w1, -w3 / w1
    f2 = w4 / w1 - cx ** 2 - cy ** 2
    if not w1 > 0 or not f2 > 0:
        raise GeometryError(
            "the image of the absolute conic is not positive definite (f² <= 0): the three line "
            "families are not images of mutually orthogonal directions, or a vanishing point is "
            "badly placed by noisy clicks. Check that the x, y, z families are the three orthogonal "
            "edge directions and click longer edges far apart")
    Kn = np.array([[np.sqrt(f2), 0.0, cx], [0.0, np.sqrt(f2), cy], [0.0, 0.0, 1.0]])
    K = np.linalg.solve(T, Kn)
    return K / K[2, 2]


# ----------------------------------------------------------------------------- rotations

def _nearest_rotation(M):
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_from_vps(K, vps, reference=None):
    """Rotation of the world axes in camera coordinates from three vanishing points (H&Z §8.6.2).

    Column i is the direction ``K⁻¹ vᵢ`` of world axis i in camera coordinates. A vanishing
    point fixes a direction only up to sign; the signs are chosen consistently:
    without ``reference`` columns 0 and 1 point away from the camera (positive camera z, or
    for a vp at infinity a positive first non-zero coordinate) and column 2 makes
    ``det R = +1``; with ``reference`` the proper sign pattern closest to it is taken (use
    view 0's R for the other views of one block). The result is orthonormalised by SVD.

    Parameters
    ----------
    K : (3, 3) array
    vps : (3, 3) array
        Homogeneous vanishing points (rows) of world axes x, y, z.
    reference : (3, 3) array, optional

    Returns
    -------
    R : (3, 3) proper rotation, world-to-camera (``x_cam = R x_world``).
    """
    v = np.asarray(vps, float).reshape(3, 3)
    D = np.linalg.solve(np.asarray(K, float), v.T)
    D /= np.linalg.norm(D, axis=0)
    if reference is None:
        for i in range(2):
            D[:, i] = _unit_sign(D[:, i])
        if np.linalg.det(D) < 0:
            D[:, 2] = -D[:, 2]
        return _nearest_rotation(D)
    ref = np.asarray(reference, float)
    best, best_score = None, -np.inf
    for s in ((1, 1, 1), (1, -1, -1), (-1, 1, -1), (-1, -1, 1), (1, 1, -1), (1, -1, 1), (-1, 1, 1), (-1, -1, -1)):
        Ds = D * np.array(s)
        if np.linalg.det(Ds) <= 0:
            continue
        score = np.trace(ref.T @ Ds)
        if score > best_score:
            best, best_score = Ds, score
    return _nearest_rotation(best)


def relative_rotation(R0, R1):
    """Rotation from camera 0 to camera 1 coordinates, ``R1 R0ᵀ`` (``x_cam1 = R x_cam0``)."""
    return np.asarray(R1, float) @ np.asarray(R0, float).T


def axis_angle(R):
    """Axis and angle of a rotation matrix.

    Parameters
    ----------
    R : (3, 3) rotation

    Returns
    -------
    axis : (3,) unit vector (``(1, 0, 0)`` for the identity)
    angle_deg : float in [0, 180]
    """
    R = np.asarray(R, float)
    c = (np.trace(R) - 1.0) / 2.0
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    angle = np.arctan2(np.linalg.norm(w) / 2.0, c)        # accurate near 0° and 180°
    if np.linalg.norm(w) > 1e-6:
        axis = w / np.linalg.norm(w)
    elif c > 0:
        axis = np.array([1.0, 0.0, 0.0])
    else:  # angle ~ 180°: axis is the eigenvector of the symmetric part with eigenvalue 1
        vals, vecs = np.linalg.eigh((R + R.T) / 2.0)
        axis = vecs[:, np.argmax(vals)]
    return axis, float(np.degrees(angle))


def euler_zyx_deg(R):
    """Euler angles of ``R = Rz(a) @ Ry(b) @ Rx(c)`` (rotations about the camera axes).

    Applied to a vector, ``R`` rotates first by ``c`` about x, then ``b`` about y, then ``a``
    about z (fixed axes); equivalently intrinsic z, y', x''.

    Returns
    -------
    (3,) array ``(a, b, c)`` in degrees: about z, about y (in [-90, 90]), about x.
    """
    R = np.asarray(R, float)
    b = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    if abs(R[2, 0]) < 1.0 - 1e-12:
        a = np.arctan2(R[1, 0], R[0, 0])
        c = np.arctan2(R[2, 1], R[2, 2])
    else:  # gimbal lock: put everything in a
        a = np.arctan2(-R[0, 1], R[1, 1])
        c = 0.0
    return np.degrees([a, b, c])


# ----------------------------------------------------------------------------- pipeline

@dataclass
class VanishingCalibration:
    """Result of :func:`calibrate_views`.

    Attributes
    ----------
    K : (3, 3) array
        Intrinsics shared by all views (pixels).
    families : tuple of str
        Names of the three families, in the order of the columns of ``R`` and rows of ``vps``.
    R : (V, 3, 3) array
        Per view, world-to-camera rotation; columns are the world axes in camera coordinates.
    vps : (V, 3, 3) array
        Per view, homogeneous unit vanishing points (rows).
    residuals_px : list of dict
        Per view, ``{family: (M,) residuals in pixels}`` (see :func:`vanishing_point`).
    relative_R : (V, 3, 3) array
        ``R_v R_0ᵀ``, rotation from camera 0 to camera v.
    axis : (V, 3) array, angle_deg : (V,) array
        Axis-angle of ``relative_R``.
    euler_zyx_deg : (V, 3) array
        :func:`euler_zyx_deg` of ``relative_R`` (about camera z, y, x).
    """

    K: np.ndarray
    families: tuple
    R: np.ndarray
    vps: np.ndarray
    residuals_px: list = field(default_factory=list)
    relative_R: np.ndarray = None
    axis: np.ndarray = None
    angle_deg: np.ndarray = None
    euler_zyx_deg: np.ndarray = None

    @property
    def focal_px(self):
        """Focal length in pixels."""
        return float(self.K[0, 0])

    @property
    def principal_point(self):
        """Principal point ``(cx, cy)`` in pixels."""
        return self.K[:2, 2].copy()


def refine_calibration(K, Rs, lines_per_view, families, principal_point=None):
    """Joint maximum-likelihood refinement of K and every view's rotation from the lines.

    The linear calibration (vanishing points one family at a time, then ω, then each R)
    does not use that the three vanishing points of a view are ``K r_k`` for the columns
    ``r_k`` of one rotation, nor that all views share ``K``. Here ``f, cx, cy`` and a
    rotation per view are adjusted together (Levenberg–Marquardt, ``scipy.optimize``) to
    minimise the distances of all segment end points to the lines joining each segment's
    midpoint with its family's vanishing point ``K R_v e_k``: the ML estimate under
    isotropic end-point noise (H&Z §8.6.1, extended to the constrained model as in
    bundle adjustment, H&Z §18.1).

    Parameters
    ----------
    K : (3, 3) array, Rs : (V, 3, 3) array
        Starting point (from the linear calibration).
    lines_per_view : list of dict
        As for :func:`calibrate_views`.
    families : sequence of 3 str
        Family names in the order of the columns of ``R``.
    principal_point : (2,) sequence, optional
        Keep this principal point fixed (only f and the rotations are refined).

    Returns
    -------
    K : (3, 3) array, Rs : (V, 3, 3) array
    """
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    K = np.asarray(K, float)
    Rs = np.asarray(Rs, float)
    V = len(Rs)
    segs = [[np.asarray(view[name], float) for name in families] for view in lines_per_view]
    fixed_pp = principal_point is not None
    pp0 = np.asarray(principal_point, float) if fixed_pp else K[:2, 2]

    def unpack(x):
        f = x[0]
        pp = pp0 if fixed_pp else x[1:3]
        off = 1 if fixed_pp else 3
        Kx = np.array([[f, 0.0, pp[0]], [0.0, f, pp[1]], [0.0, 0.0, 1.0]])
        R = [Rs[v] @ Rotation.from_rotvec(x[off + 3 * v: off + 3 * v + 3]).as_matrix()
             for v in range(V)]
        return Kx, R

    def residuals(x):
        Kx, R = unpack(x)
        out = []
        for v in range(V):
            for k in range(3):
                out.append(_midpoint_residuals(Kx @ R[v][:, k], segs[v][k]))
        return np.concatenate(out)

    x0 = np.concatenate([[K[0, 0]], [] if fixed_pp else K[:2, 2], np.zeros(3 * V)])
    sol = least_squares(residuals, x0, method="lm", x_scale="jac")
    if not sol.success or not np.all(np.isfinite(sol.x)) or sol.x[0] <= 0:
        return K, Rs
    Kr, Rr = unpack(sol.x)
    return Kr, np.array(Rr)


def _family_names(view, index):
    names = tuple(view)
    if set(_FAMILY_ORDER) <= set(names):
        return _FAMILY_ORDER
    if len(names) == 3:
        return names
    raise GeometryError(
        f"view {index}: calibration needs three families of orthogonal directions named "
        f"'x', 'y', 'z' (or exactly three families), got {list(names)}")


def calibrate_views(lines_per_view, principal_point=None, refine=True):
    """Calibrate K (jointly over all views) and each view's rotation from line families.

    Parameters
    ----------
    lines_per_view : list of dict
        As returned by :func:`read_lines`: per view ``{family: (M, 4) segments in px}`` with
        families ``"x"``, ``"y"``, ``"z"`` (or exactly three families, taken in file order)
        of mutually orthogonal 3D directions. All views must come from the same camera.
    principal_point : (2,) sequence of float, optional
        Known principal point ``(cx, cy)`` in pixels; see :func:`calibrate_k`.
    refine : bool
        Refine K and the rotations jointly by maximum likelihood
        (:func:`refine_calibration`) after the linear estimate.

    Returns
    -------
    VanishingCalibration
    """
    if not lines_per_view:
        raise GeometryError("no views given; lines.json must hold at least one view with three line families")
    names0 = _family_names(lines_per_view[0], 0)
    vps, res = [], []
    for k, view in enumerate(lines_per_view):
        names = _family_names(view, k)
        if names != names0:
            raise GeometryError(f"view {k} has families {list(names)} but view 0 has {list(names0)}; "
                                "use the same three family names in every view")
        trip, r = [], {}
        for name in names:
            try:
                vp, r[name] = vanishing_point(view[name])
            except GeometryError as exc:
                raise GeometryError(f"view {k}, family {name!r}: {exc}") from None
            trip.append(vp)
        vps.append(trip)
        res.append(r)
    vps = np.array(vps)
    K = calibrate_k(vps, principal_point)
    Rs = [rotation_from_vps(K, vps[0])]
    for trip in vps[1:]:
        Rs.append(rotation_from_vps(K, trip, reference=Rs[0]))
    Rs = np.array(Rs)
    if refine:
        K, Rs = refine_calibration(K, Rs, lines_per_view, names0, principal_point)
        # the vanishing points and residuals of the refined (consistent) model
        vps = np.array([[_unit_sign(K @ R[:, k]) for k in range(3)] for R in Rs])
        res = [{name: np.abs(_midpoint_residuals(vps[v][k], np.asarray(view[name], float)))
                for k, name in enumerate(names0)} for v, view in enumerate(lines_per_view)]
    rel = np.array([relative_rotation(Rs[0], R) for R in Rs])
    aa = [axis_angle(R) for R in rel]
    return VanishingCalibration(
        K=K, families=names0, R=Rs, vps=vps, residuals_px=res, relative_R=rel,
        axis=np.array([a for a, _ in aa]), angle_deg=np.array([g for _, g in aa]),
        euler_zyx_deg=np.array([euler_zyx_deg(R) for R in rel]))
