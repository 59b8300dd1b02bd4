"""How a click becomes a proposal in the other views: epipolar geometry and refinement.

The correspondence picker (:class:`semlab.picking.CorrespondencePicker`) guesses the
position of a clicked point in the other views, then hands the guess to a *refinement*
passed in by its caller: a callable ``refine(images, guess, ref_view) -> (1, V, 2)``.
This module holds the refinements (:func:`same_position_refine`, :class:`WindowedRefine`,
:func:`matching_refine`) and the line geometry the picker draws (:func:`clip_line_to_image`,
:func:`fundamental_from_points`).

Coordinates are ``(x, y)`` pixels, x to the right, y down, origin at the centre of the
top-left pixel (OpenCV), so that an image of shape ``(H, W)`` covers
``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.
"""

from __future__ import annotations

import numpy as np

from .errors import GeometryError

__all__ = [
    "clip_line_to_image",
    "same_position_refine",
    "fundamental_from_points",
    "fundamental_dict",
    "WindowedRefine",
    "matching_refine",
]


# --------------------------------------------------------------------------- geometry helpers

def clip_line_to_image(line, shape):
    """End points of the part of a 2D line inside an image.

    Parameters
    ----------
    line : (3,) array
        Homogeneous line ``(a, b, c)``: points with ``a x + b y + c = 0``.
    shape : (H, W) tuple
        Image shape; the image covers ``[-0.5, W - 0.5] x [-0.5, H - 0.5]`` in pixels.

    Returns
    -------
    (2, 2) array or None
        ``[[x_a, y_a], [x_b, y_b]]`` in pixels, or None if the line misses the image (or is
        not a line, ``a = b = 0``).
    """
    a, b, c = (float(v) for v in np.asarray(line, dtype=float).ravel()[:3])
    h, w = shape[:2]
    x0, x1, y0, y1 = -0.5, w - 0.5, -0.5, h - 0.5
    norm = np.hypot(a, b)
    if not np.isfinite(norm) or norm == 0:
        return None
    a, b, c = a / norm, b / norm, c / norm
    tol = 1e-9 * max(w, h)
    cand = []
    if abs(b) > 1e-12:
        for x in (x0, x1):
            y = -(a * x + c) / b
            if y0 - tol <= y <= y1 + tol:
                cand.append((x, min(max(y, y0), y1)))
    if abs(a) > 1e-12:
        for y in (y0, y1):
            x = -(b * y + c) / a
            if x0 - tol <= x <= x1 + tol:
                cand.append((min(max(x, x0), x1), y))
    if len(cand) < 2:
        return None
    cand = np.asarray(cand)
    d = np.linalg.norm(cand[:, None] - cand[None], axis=2)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    if d[i, j] <= tol:
        return None
    return cand[[i, j]]


def fundamental_dict(F, n_views):
    """Normalise ``F`` (3x3 for views 0->1, or {(i, j): F_ij}) to a dict of 3x3 arrays."""
    if F is None:
        return {}
    if isinstance(F, dict):
        items = F.items()
    else:
        items = [((0, 1), F)]
    out = {}
    for (i, j), Fij in items:
        Fij = np.asarray(Fij, dtype=float)
        if Fij.shape != (3, 3) or not np.all(np.isfinite(Fij)):
            raise GeometryError(f"fundamental matrix for views ({i}, {j}) must be a finite "
                                f"3x3 array, got shape {Fij.shape}")
        if not (0 <= i < n_views and 0 <= j < n_views and i != j):
            raise GeometryError(f"fundamental matrix key ({i}, {j}) is not a pair of distinct "
                                f"views among {n_views}")
        out[(int(i), int(j))] = Fij
    return out


def same_position_refine(images, guess, ref_view):
    """The refinement that changes nothing: the proposal is the geometric guess.

    Parameters
    ----------
    images : list of V (H, W) arrays
    guess : (1, V, 2) array
        ``(x, y)`` pixels per view: the clicked position in ``ref_view`` (and any view
        already confirmed), the picker's guess elsewhere.
    ref_view : int
        The view that was clicked.

    Returns
    -------
    (1, V, 2) array
        A copy of ``guess``, clipped into each image.
    """
    out = np.array(guess, dtype=float, copy=True)
    for k, img in enumerate(images):
        h, w = np.shape(img)[:2]
        out[0, k] = np.clip(out[0, k], -0.5, [w - 0.5, h - 0.5])
    return out


def fundamental_from_points(pts, min_points=4):
    """Affine fundamental matrices from view 0 to every other view, from picked points.

    Parameters
    ----------
    pts : (N, V, 2) array
        ``(x, y)`` pixels; rows with NaN are ignored.
    min_points : int
        Fewer complete rows than this give None.

    Returns
    -------
    dict or None
        ``{(0, k): F_0k}`` (:func:`semlab.epipolar.fundamental_affine`, ``x_kᵀ F x_0 = 0``)
        for the views where it is determined; None when it is determined for none.
    str
        Why some or all are missing ("" when none is).
    """
    from .epipolar import fundamental_affine

    pts = np.asarray(pts, dtype=float)
    ok = np.isfinite(pts).all(axis=(1, 2)) if pts.size else np.zeros(0, bool)
    if ok.sum() < min_points:
        return None, (f"{int(ok.sum())} complete point(s): the epipolar line needs "
                      f"{min_points} picked points")
    out, why = {}, []
    for k in range(1, pts.shape[1]):
        try:
            out[(0, k)] = fundamental_affine(pts[ok, 0], pts[ok, k])
        except GeometryError as err:
            why.append(f"view {k}: {err}")
    return (out or None), "; ".join(why)


# --------------------------------------------------------------------------- refinement

class WindowedRefine:
    """A refinement for :class:`CorrespondencePicker` that matches in windows around the
    guesses instead of the whole views.

    A click on two 2048×1536 views took 0.9 s with the whole views, almost all of it
    spline-filtering the full images; in ``(2 window_px + 1)²`` windows it takes ~0.07 s.

    Parameters
    ----------
    match : callable
        ``match(crops, guess, ref_view) -> (1, V, 2) array or an object with .pts``: the
        matcher on equal-size image windows, with ``guess`` ``(1, V, 2)`` pixels in the
        windows' frame (e.g. :func:`semlab.matching.refine_correspondences`).
    window_px : int
        Half size of the windows, pixels.
    """

    def __init__(self, match, window_px=48):
        self.match = match
        self.window_px = int(window_px)

    def crops(self, images, guess):
        """Equal-size windows of the views around each view's guess, and their ``(V, 2)``
        ``(x, y)`` origins; the whole views when they are smaller than a window.

        Parameters
        ----------
        images : list of V (H, W) arrays
        guess : (V, 2) array of (x, y) pixels
        """
        r = self.window_px
        crops, origin = [], np.zeros((len(images), 2))
        for k, img in enumerate(images):
            h, w = img.shape[:2]
            sw, sh = min(2 * r + 1, w), min(2 * r + 1, h)
            x0 = int(np.clip(np.rint(guess[k, 0]) - r, 0, w - sw))
            y0 = int(np.clip(np.rint(guess[k, 1]) - r, 0, h - sh))
            crops.append(img[y0:y0 + sh, x0:x0 + sw])
            origin[k] = x0, y0
        return crops, origin

    def __call__(self, images, guess, ref_view):
        guess = np.asarray(guess, dtype=float)
        crops, origin = self.crops(images, guess[0])
        out = self.match(crops, guess - origin[None], ref_view)
        out = np.asarray(getattr(out, "pts", out), dtype=float)
        return out.reshape(guess.shape) + origin[None]


def matching_refine(window_px=48, **kwargs):
    """The picker's sub-pixel refinement: :func:`semlab.matching.refine_correspondences` in
    windows around the guesses (:class:`WindowedRefine`).

    Parameters
    ----------
    window_px : int
        Half size of the matching windows, pixels.
    **kwargs
        Passed to ``refine_correspondences``; default ``band_aware=False`` (the band-aware
        pass costs ~1 s per click).

    Returns
    -------
    WindowedRefine
    """
    from .matching import refine_correspondences

    kwargs.setdefault("band_aware", False)

    def match(crops, guess, ref_view):
        return refine_correspondences(crops, guess, ref_view=ref_view, **kwargs)

    return WindowedRefine(match, window_px=window_px)
