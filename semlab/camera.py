"""The SEM camera models shared by synth, reconstruction and matching.

Affine (parallel) model of an SEM view at eucentric stage tilt θ about the image y axis::

    u = cx + (x cos θ + z sin θ) / s
    v = cy + y / s

with ``(x, y, z)`` in µm in the material frame (x, y in the surface plane, z out of the
surface toward the detector, z > 0 an extrusion), ``s`` the pixel size in µm/px and
``(cx, cy)`` the pixel position of the tilt axis (by default the image centre,
``((W - 1) / 2, (H - 1) / 2)``). Pixel coordinates follow OpenCV: origin at the centre of
the top-left pixel, x to the right, y down.

Perspective model (the reference paper's option): ``λ [u, v, 1]ᵀ = K (R X + t)``.
"""

from __future__ import annotations

import numpy as np

from .errors import GeometryError


def image_center(shape):
    """Pixel position ``(cx, cy)`` of the centre of an image of ``shape`` ``(H, W[, ...])``."""
    h, w = shape[:2]
    return (w - 1) / 2.0, (h - 1) / 2.0


def affine_camera_matrix(tilt_deg, pixel_size_um, center_px=(0.0, 0.0)):
    """2×4 affine camera ``P`` with ``[u, v]ᵀ = P @ [x_um, y_um, z_um, 1]ᵀ``.

    Parameters
    ----------
    tilt_deg : float
        Stage tilt about the image y axis, degrees.
    pixel_size_um : float
        Pixel size in µm/px (> 0).
    center_px : (2,) sequence of float
        Pixel position ``(cx, cy)`` of the tilt axis.
    """
    if not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise GeometryError(f"pixel_size_um must be a positive number, got {pixel_size_um!r}")
    t = np.deg2rad(tilt_deg)
    s = float(pixel_size_um)
    cx, cy = center_px
    return np.array([[np.cos(t) / s, 0.0, np.sin(t) / s, cx],
                     [0.0, 1.0 / s, 0.0, cy]])


def project_affine(xyz_um, tilt_deg, pixel_size_um, center_px=(0.0, 0.0)):
    """Project material points into an affine SEM view.

    Parameters
    ----------
    xyz_um : (N, 3) array
        Material points ``(x, y, z)`` in µm.
    tilt_deg, pixel_size_um, center_px
        See :func:`affine_camera_matrix`.

    Returns
    -------
    (N, 2) array of (x, y) in pixels.
    """
    xyz = np.asarray(xyz_um, dtype=float).reshape(-1, 3)
    P = affine_camera_matrix(tilt_deg, pixel_size_um, center_px)
    return xyz @ P[:, :3].T + P[:, 3]


def project_perspective(xyz, K, R, t):
    """Project 3D points with a pinhole camera ``λ [u, v, 1]ᵀ = K (R X + t)``.

    Parameters
    ----------
    xyz : (N, 3) array
        World points (any consistent length unit).
    K : (3, 3) array
        Intrinsics.
    R : (3, 3) array
        World-to-camera rotation.
    t : (3,) array
        World-to-camera translation.

    Returns
    -------
    (N, 2) array of (x, y) in pixels.
    """
    X = np.asarray(xyz, dtype=float).reshape(-1, 3)
    c = X @ np.asarray(R, float).T + np.asarray(t, float).reshape(1, 3)
    if np.any(c[:, 2] <= 0):
        raise GeometryError("some points are behind the perspective camera (z_cam <= 0)")
    h = c @ np.asarray(K, float).T
    return h[:, :2] / h[:, 2:3]


def rotation_about_axis(axis, angle_rad):
    """Rotation matrix for a right-handed rotation of ``angle_rad`` about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * (k @ k)


def _check_pixel_size(pixel_size_um):
    if pixel_size_um is None or not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise GeometryError(
            f"pixel_size_um must be a positive number (µm/px), got {pixel_size_um!r}; read it "
            "from the SEM file or give it in experiment.toml")
    return float(pixel_size_um)
