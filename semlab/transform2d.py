"""Global 2D transforms of pixel coordinates: a small transform type and its fitting.

:class:`Transform2D` (apply, inverse, compose, similarity parameters, rigid part) is what
the frame registration (:mod:`semlab.registration`) returns; :func:`fit_transform` is the
least-squares fit and :func:`estimate_transform` the robust one (RANSAC) of a translation,
similarity or affine map to point correspondences.

Conventions: points are ``(N, 2)`` arrays of ``(x, y)`` in pixels, x to the right, y down.
Rotation angles are in degrees, positive from +x toward +y (clockwise on the screen, where
y points down).

References
----------
- M. A. Fischler, R. C. Bolles, "Random sample consensus", Comm. ACM 24 (1981).
- S. Umeyama, "Least-squares estimation of transformation parameters between two point
  patterns", IEEE TPAMI 13 (1991) (the similarity least-squares fit).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .errors import GeometryError

__all__ = ["Transform2D", "MODELS", "fit_transform", "estimate_transform"]

#: Transform models: degrees of freedom 2 (shift), 4 (shift, rotation, scale), 6 (affine).
MODELS = ("translation", "similarity", "affine")


# ----------------------------------------------------------------------------- transform

@dataclass(frozen=True)
class Transform2D:
    """A 2D affine map of pixel coordinates, ``[x', y', 1]ᵀ = matrix @ [x, y, 1]ᵀ``.

    Like :class:`skimage.transform.AffineTransform`: call it on ``(N, 2)`` points, invert it,
    compose it (``a @ b`` is "``b`` then ``a``"). The similarity parameters are read about a
    centre: ``T(p) = c + (dx, dy) + scale · R(rotation) · (p − c)`` for a similarity.

    Parameters
    ----------
    matrix : (3, 3) array, last row ``[0, 0, 1]``; or (2, 3).
    """

    matrix: np.ndarray

    def __post_init__(self):
        m = np.asarray(self.matrix, float)
        if m.shape == (2, 3):
            m = np.vstack([m, [0.0, 0.0, 1.0]])
        if m.shape != (3, 3) or not np.isfinite(m).all() or not np.allclose(m[2], [0, 0, 1]):
            raise GeometryError(f"a 2D transform needs a finite (2, 3) or (3, 3) affine matrix, got "
                                f"{np.shape(self.matrix)}")
        if abs(np.linalg.det(m[:2, :2])) < 1e-12:
            raise GeometryError("the 2D transform is singular (determinant ~0)")
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)

    @classmethod
    def identity(cls):
        return cls(np.eye(3))

    @classmethod
    def from_params(cls, dx_px=0.0, dy_px=0.0, rotation_deg=0.0, scale=1.0, center=(0.0, 0.0)):
        """Similarity: shift ``(dx_px, dy_px)`` of ``center``, rotation and scale about it."""
        t = np.deg2rad(rotation_deg)
        A = scale * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
        c = np.asarray(center, float)
        m = np.eye(3)
        m[:2, :2] = A
        m[:2, 2] = c + np.array([dx_px, dy_px]) - A @ c
        return cls(m)

    @property
    def affine(self):
        """(2, 3) matrix (the form OpenCV's warps take)."""
        return self.matrix[:2].copy()

    def __call__(self, pts):
        """Map ``(N, 2)`` points (x, y); NaN rows stay NaN."""
        p = np.asarray(pts, float)
        return p @ self.matrix[:2, :2].T + self.matrix[:2, 2]

    def inverse(self):
        return Transform2D(np.linalg.inv(self.matrix))

    def __matmul__(self, other):
        """``(self @ other)(p) = self(other(p))``."""
        return Transform2D(self.matrix @ other.matrix)

    def params(self, center=(0.0, 0.0)):
        """Shift of ``center``, rotation (degrees) and scale (``sqrt|det|``) of the map.

        The rotation is that of the polar decomposition ``A = R P`` of the linear part (for an
        affine map with shear, the rotation nearest to it).
        """
        c = np.asarray(center, float)
        d = self(c[None])[0] - c
        R = _nearest_rotation(self.matrix[:2, :2])
        return {"dx_px": float(d[0]), "dy_px": float(d[1]),
                "rotation_deg": float(np.rad2deg(np.arctan2(R[1, 0], R[0, 0]))),
                "scale": float(np.sqrt(abs(np.linalg.det(self.matrix[:2, :2]))))}

    def rigid(self, center=(0.0, 0.0)):
        """The rigid-body part: the same shift of ``center`` and rotation, scale 1, no shear."""
        p = self.params(center)
        return Transform2D.from_params(p["dx_px"], p["dy_px"], p["rotation_deg"], 1.0, center)

    def distance(self, other, shape):
        """Largest distance (pixels) between the two maps over an ``(H, W)`` image.

        The difference of two affine maps is affine, so its largest norm over the image
        rectangle is reached at a corner.
        """
        h, w = shape
        corners = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float)
        return float(np.linalg.norm(self(corners) - other(corners), axis=1).max())

    def is_identity(self, tol=1e-9):
        return bool(np.abs(self.matrix - np.eye(3)).max() <= tol)


def _nearest_rotation(A):
    u, _, vt = np.linalg.svd(A)
    R = u @ vt
    if np.linalg.det(R) < 0:                  # a reflection: flip the weakest direction
        u[:, -1] *= -1
        R = u @ vt
    return R


def _check_model(model):
    if model not in MODELS:
        raise GeometryError(f"model must be one of {MODELS}, got {model!r}")


def fit_transform(p0, p1, model="affine"):
    """Least-squares transform ``p1 ≈ T(p0)`` (closed form; Umeyama 1991 for the similarity).

    Parameters
    ----------
    p0, p1 : (N, 2) arrays of (x, y) pixels; N >= 1 (translation), 2 (similarity), 3 (affine).
    model : {"translation", "similarity", "affine"}

    Returns
    -------
    Transform2D

    Raises
    ------
    GeometryError
        Too few or degenerate (coincident, collinear) points.
    """
    _check_model(model)
    p0 = np.asarray(p0, float)
    p1 = np.asarray(p1, float)
    if p0.shape != p1.shape or p0.ndim != 2 or p0.shape[1] != 2:
        raise GeometryError(f"p0 and p1 must be (N, 2) arrays of the same shape, got {p0.shape} "
                            f"and {p1.shape}")
    need = {"translation": 1, "similarity": 2, "affine": 3}[model]
    if len(p0) < need:
        raise GeometryError(f"a {model} transform needs {need} or more points, got {len(p0)}")
    c0, c1 = p0.mean(0), p1.mean(0)
    a, b = p0 - c0, p1 - c1
    m = np.eye(3)
    if model == "translation":
        m[:2, 2] = c1 - c0
        return Transform2D(m)
    spread = np.abs(a).max() if len(a) else 0.0
    rank = np.linalg.matrix_rank(a, tol=1e-9 * max(1.0, spread)) if spread > 0 else 0
    if rank < (1 if model == "similarity" else 2):
        raise GeometryError(f"the points are {'coincident' if rank == 0 else 'collinear'}: a "
                            f"{model} transform is undetermined")
    if model == "similarity":
        # x' = s R x + t with R a rotation: maximise tr(Rᵀ Σ b aᵀ) (Umeyama 1991)
        num = (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]).sum()
        den = (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
        A = np.array([[num, -den], [den, num]]) / (a * a).sum()
    else:
        A = np.linalg.lstsq(a, b, rcond=None)[0].T
    m[:2, :2] = A
    m[:2, 2] = c1 - A @ c0
    return Transform2D(m)


def estimate_transform(p0, p1, model="affine", ransac_threshold_px=2.0, min_inliers=6, seed=0):
    """Robust transform ``p1 ≈ T(p0)``: RANSAC (OpenCV), then least squares on the inliers.

    Parameters
    ----------
    p0, p1 : (N, 2) arrays of (x, y) pixels (e.g. from :func:`match_features`)
    model : {"translation", "similarity", "affine"}
    ransac_threshold_px : float
        RANSAC inlier threshold, pixels.
    min_inliers : int
        Fewest inliers accepted.
    seed : int
        OpenCV's RNG seed, for repeatable results.

    Returns
    -------
    transform : Transform2D
    inliers : (N,) bool

    Raises
    ------
    GeometryError
        Fewer than ``min_inliers`` consistent matches.
    """
    _check_model(model)
    p0 = np.asarray(p0, float).reshape(-1, 2)
    p1 = np.asarray(p1, float).reshape(-1, 2)
    n = len(p0)
    if n < max(int(min_inliers), 3):
        raise GeometryError(f"only {n} feature matches (need {max(int(min_inliers), 3)}): are the "
                            "images of the same area?")
    cv2.setRNGSeed(int(seed))
    if model == "translation":
        d = p1 - p0
        med = np.median(d, axis=0)
        inl = np.linalg.norm(d - med, axis=1) <= ransac_threshold_px
    else:
        est = cv2.estimateAffine2D if model == "affine" else cv2.estimateAffinePartial2D
        M, inl = est(p0.astype(np.float32), p1.astype(np.float32), method=cv2.RANSAC,
                     ransacReprojThreshold=float(ransac_threshold_px), maxIters=5000,
                     confidence=0.999)
        inl = np.zeros(n, bool) if M is None or inl is None else inl.ravel().astype(bool)
    if inl.sum() < min_inliers:
        raise GeometryError(f"RANSAC found {int(inl.sum())} consistent matches among {n} (need "
                            f"{min_inliers}): no global {model} transform between the images")
    T = fit_transform(p0[inl], p1[inl], model)
    # one re-selection with the least-squares fit (RANSAC's minimal-sample model is noisy)
    inl2 = np.linalg.norm(T(p0) - p1, axis=1) <= ransac_threshold_px
    if inl2.sum() >= min_inliers:
        inl = inl2
        T = fit_transform(p0[inl], p1[inl], model)
    return T, inl
