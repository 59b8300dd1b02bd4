"""Input checks shared by the subset-matching modules (images, points, integers)."""

from __future__ import annotations

import numpy as np

from .errors import ImageError, SemlabError


def _as_image(img, name):
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        raise ImageError(f"{name} is a colour image of shape {a.shape}; convert it to grey "
                         "(e.g. img.mean(axis=2)) before matching")
    if a.ndim != 2:
        raise ImageError(f"{name} must be a 2D grey image, got shape {a.shape}")
    if min(a.shape) < 8:
        raise ImageError(f"{name} of shape {a.shape} is too small for subset matching")
    a = a.astype(np.float64, copy=False)
    if not np.all(np.isfinite(a)):
        raise ImageError(f"{name} contains NaN or infinite values; fill or crop them first")
    return a


def _as_points(pts, name, n=None):
    p = np.asarray(pts, dtype=np.float64)
    if p.ndim == 1 and p.shape == (2,):
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 2:
        raise SemlabError(f"{name} must be an (N, 2) array of (x, y) pixels, got shape "
                          f"{np.shape(pts)}")
    if n is not None and len(p) != n:
        raise SemlabError(f"{name} has {len(p)} points but pts_ref has {n}; give one guess "
                          "per reference point")
    return p


def _check_int(value, name, lo):
    if isinstance(value, bool) or not float(value).is_integer() or int(value) < lo:
        raise SemlabError(f"{name} must be an integer >= {lo}, got {value!r}")
    return int(value)
