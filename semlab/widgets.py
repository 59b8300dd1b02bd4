"""Interactive pickers for JupyterLab: point correspondences between views, and line segments.

Two layers, so that the logic is testable without a browser:

- state classes, plain Python on numpy arrays: :class:`CorrespondencePicker` (points seen in
  ``V`` views, proposals, undo) and :class:`LinePicker` (segments in line families for
  vanishing-point calibration);
- matplotlib views that turn canvas events into calls on the state: :class:`PickerFigure`,
  :class:`LinePickerFigure`; and the ipywidgets panels :func:`picker_widget`,
  :func:`line_picker_widget` (interactive with the ipympl backend, ``%matplotlib widget``).

Coordinates are ``(x, y)`` pixels, x to the right, y down, origin at the centre of the
top-left pixel (OpenCV), so that an image of shape ``(H, W)`` covers
``[-0.5, W - 0.5] x [-0.5, H - 0.5]``. Files are written with a backup of what they replace
(:mod:`semlab.annotations`).

Mouse and keys in a picker figure (zoom and pan with the toolbar; clicks are ignored while
the toolbar is in zoom or pan mode):

=====================  =====================================================================
left click             new point in that view / the current point's position in that view
left click on marker   select it; drag to move it; a click on a proposal confirms it
right click            select the nearest point (or segment)
``a`` / enter          accept the current point with its proposals
``d`` / delete         delete the selected point (segment)
``u`` / ctrl+z         undo (many levels)
escape                 drop the point (segment) being picked
=====================  =====================================================================
"""

from __future__ import annotations

import inspect
import io
import json
import warnings
from pathlib import Path

import numpy as np

from .annotations import (Correspondences, atomic_write_text,
                          read_correspondences, write_correspondences)
from .errors import ExperimentError, GeometryError, ImageError, SemlabError

__all__ = [
    "CorrespondencePicker",
    "PickerFigure",
    "picker_widget",
    "LinePicker",
    "LinePickerFigure",
    "line_picker_widget",
    "clip_line_to_image",
    "same_position_refine",
]

_UNDO_LEVELS = 500
_LINES_SCHEMA = "semlab-lines/1"


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


def _fundamental_dict(F, n_views):
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


def same_position_refine(images, pts, ref_view):
    """The simplest proposal: the clicked pixel position, copied into the unknown views.

    Parameters
    ----------
    images : list of V (H, W) arrays
    pts : (1, V, 2) array
        ``(x, y)`` pixels per view, NaN where unknown.
    ref_view : int
        The view that was clicked.

    Returns
    -------
    (1, V, 2) array
        Unknown views get ``pts[0, ref_view]`` clipped to their image.
    """
    out = np.array(pts, dtype=float, copy=True)
    ref = out[0, ref_view]
    for k, img in enumerate(images):
        if not np.all(np.isfinite(out[0, k])):
            h, w = np.shape(img)[:2]
            out[0, k] = np.clip(ref, -0.5, [w - 0.5, h - 0.5])
    return out


def _inside(xy, shape):
    h, w = shape[:2]
    return bool(np.all(np.isfinite(xy)) and -0.5 <= xy[0] <= w - 0.5 and -0.5 <= xy[1] <= h - 0.5)


def _robust_limits(img):
    img = np.asarray(img)
    if img.ndim != 2:
        return None, None
    finite = img[np.isfinite(img)]
    if finite.size == 0:
        return None, None
    lo, hi = np.percentile(finite, [0.5, 99.5])
    if hi <= lo:
        return None, None
    return float(lo), float(hi)


def _check_images(images):
    if isinstance(images, np.ndarray) and images.ndim == 2:
        images = [images]
    images = [np.asarray(im) for im in images]
    for k, im in enumerate(images):
        if im.ndim not in (2, 3) or min(im.shape[:2]) < 1:
            raise ImageError(f"image of view {k} must be a 2D (H, W) array (or (H, W, 3) RGB), "
                             f"got shape {im.shape}")
    return images


# --------------------------------------------------------------------------- correspondences

class CorrespondencePicker:
    """The state of picking corresponding points in ``V >= 2`` views (no drawing).

    A click in one view starts a new point, or places the point being picked (the
    *current* point) in another view. The views not yet clicked get a *proposal* from
    ``refine``; :meth:`accept` confirms the proposals. Clicking the point in every view
    completes it without :meth:`accept`.

    Parameters
    ----------
    images : list of V (H, W) arrays
        The views, indexed ``[row, col]``.
    pts : (N, V, 2) array, Correspondences, or None
        Points already picked, ``(x, y)`` pixels per view (NaN for views not picked).
    refine : callable, optional
        ``refine(images, pts, ref_view) -> (1, V, 2)`` where ``pts`` is ``(1, V, 2)`` with NaN
        for the views to propose and ``ref_view`` the view just clicked. Default: the clicked
        position shifted by the median offset between views of the points already picked,
        moved onto the epipolar line when ``F`` is known, then refined by
        ``semlab.matching.refine_correspondences`` when that function exists and returns a
        finite point inside the image within ``max_refine_shift_px`` of the guess.
    F : (3, 3) array or dict, optional
        Fundamental matrix with ``x1ᵀ F x0 = 0`` (homogeneous pixels of views 0 and 1), or a
        dict ``{(i, j): F_ij}`` with ``x_jᵀ F_ij x_i = 0``; enables :meth:`epipolar_line`.
    titles : list of str, optional
        Names of the views (figure titles).
    point_id, crack_id : (N,) int arrays, optional
        Ids of the points given in ``pts``; crack of each point (``-1`` for none).
    max_refine_shift_px : float
        Largest move the default refinement may make from the guess (pixels).

    Attributes
    ----------
    pts : (N, V, 2) float array
    point_id : (N,) int array
    crack_id : (N,) int array
    confirmed : (N, V) bool array
        False where the position is a proposal not yet clicked or accepted.
    current : int or None
        Index of the point being picked.
    selected : int or None
        Index of the selected point (for :meth:`delete`, drawing).
    """

    def __init__(self, images, pts=None, refine=None, F=None, titles=None, point_id=None,
                 crack_id=None, max_refine_shift_px=20.0):
        self.images = _check_images(images)
        if len(self.images) < 2:
            raise ImageError(f"correspondences need at least 2 views, got {len(self.images)} "
                             f"image(s)")
        v = len(self.images)
        self.shapes = [im.shape[:2] for im in self.images]
        self.titles = list(titles) if titles is not None else [f"view {k}" for k in range(v)]
        if len(self.titles) != v:
            raise ImageError(f"{len(self.titles)} titles given for {v} views")
        self.F = _fundamental_dict(F, v)
        self.refine = refine
        self.max_refine_shift_px = float(max_refine_shift_px)
        self.last_refine_error = None
        self._proposing = None
        self._has_crack_column = crack_id is not None
        if isinstance(pts, Correspondences):
            point_id, crack_id, pts = pts.point_id, pts.crack_id, pts.pts
            self._has_crack_column = crack_id is not None
        pts = np.zeros((0, v, 2)) if pts is None else np.array(pts, dtype=float)
        if pts.ndim != 3 or pts.shape[1:] != (v, 2):
            raise GeometryError(f"pts must have shape (N, {v}, 2) for {v} views, got {pts.shape}")
        n = pts.shape[0]
        self.pts = pts
        self.point_id = (np.arange(n) if point_id is None else np.asarray(point_id)).astype(int)
        self.crack_id = (np.full(n, -1) if crack_id is None else np.asarray(crack_id)).astype(int)
        if self.point_id.shape != (n,) or self.crack_id.shape != (n,):
            raise GeometryError(f"point_id and crack_id must have shape ({n},)")
        if len(np.unique(self.point_id)) != n:
            raise GeometryError("point_id values must be unique")
        self.confirmed = np.isfinite(pts).all(axis=2)
        self.current = None
        self.selected = None
        self._undo = []

    # ---- basic properties
    @property
    def n_views(self):
        """Number of views ``V``."""
        return len(self.images)

    @property
    def n_points(self):
        """Number of points ``N`` (including the one being picked)."""
        return int(self.pts.shape[0])

    def __len__(self):
        return self.n_points

    def complete(self):
        """(N,) bool: points placed in every view and not still being picked."""
        ok = np.isfinite(self.pts).all(axis=(1, 2))
        if self.current is not None:
            ok[self.current] = False
        return ok

    # ---- undo
    def _snapshot(self):
        return (self.pts.copy(), self.point_id.copy(), self.crack_id.copy(),
                self.confirmed.copy(), self.current, self.selected, self._has_crack_column)

    def push_undo(self):
        """Save the present state on the undo stack (done by every editing method)."""
        self._undo.append(self._snapshot())
        if len(self._undo) > _UNDO_LEVELS:
            del self._undo[0]

    def undo(self):
        """Go back to the state before the last edit; returns False if nothing to undo."""
        if not self._undo:
            return False
        (self.pts, self.point_id, self.crack_id, self.confirmed, self.current,
         self.selected, self._has_crack_column) = self._undo.pop()
        return True

    @property
    def can_undo(self):
        """True when :meth:`undo` has something to undo."""
        return bool(self._undo)

    # ---- checks
    def _check_view(self, view):
        if not (isinstance(view, (int, np.integer)) and 0 <= view < self.n_views):
            raise GeometryError(f"view must be an integer in 0..{self.n_views - 1}, got {view!r}")
        return int(view)

    def _check_xy(self, view, xy):
        xy = np.asarray(xy, dtype=float).reshape(-1)
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise GeometryError(f"xy must be a finite (x, y) pixel pair, got {xy!r}")
        if not _inside(xy, self.shapes[view]):
            h, w = self.shapes[view]
            raise GeometryError(f"(x={xy[0]:g}, y={xy[1]:g}) px is outside the {w}x{h} image of "
                                f"view {view}")
        return xy

    def _check_index(self, i):
        if not (isinstance(i, (int, np.integer)) and 0 <= i < self.n_points):
            raise GeometryError(f"point index must be in 0..{self.n_points - 1}, got {i!r}")
        return int(i)

    # ---- editing
    def add(self, view, xy):
        """Click at ``xy`` in ``view``.

        Starts a new point when none is being picked, else places the current point in
        ``view`` (a second click in the same view corrects it). The views not clicked yet
        get proposals (:meth:`propose`). When every view has been clicked the point is
        complete.

        Parameters
        ----------
        view : int
        xy : (2,) sequence
            ``(x, y)`` in pixels of that view.

        Returns
        -------
        int
            Index of the point clicked.
        """
        view = self._check_view(view)
        xy = self._check_xy(view, xy)
        self.push_undo()
        if self.current is None:
            nid = int(self.point_id.max()) + 1 if self.n_points else 0
            self.pts = np.concatenate([self.pts, np.full((1, self.n_views, 2), np.nan)])
            self.point_id = np.append(self.point_id, nid)
            self.crack_id = np.append(self.crack_id, -1)
            self.confirmed = np.concatenate([self.confirmed, np.zeros((1, self.n_views), bool)])
            self.current = self.n_points - 1
        i = self.current
        self.pts[i, view] = xy
        self.confirmed[i, view] = True
        self.selected = i
        if self.confirmed[i].all():
            self.current = None
        else:
            self._propose(i, view)
        return i

    def _guess(self, i, ref_view):
        """Initial guess of point ``i`` in the unknown views from its position in ``ref_view``."""
        p = self.pts[i].copy()
        ref = p[ref_view]
        done = self.complete()
        done[i] = False
        for k in range(self.n_views):
            if self.confirmed[i, k]:
                continue
            g = ref.copy()
            if done.any():
                g = ref + np.median(self.pts[done, k] - self.pts[done, ref_view], axis=0)
            line = self._line(ref_view, ref, k)
            if line is not None:
                a, b, c = line
                g = g - (a * g[0] + b * g[1] + c) / (a * a + b * b) * np.array([a, b])
            h, w = self.shapes[k]
            p[k] = np.clip(g, -0.5, [w - 0.5, h - 0.5])
        return p

    #: Half size (pixels) of the windows the default refinement matches in.
    refine_window_px = 48

    def _crops(self, images, guess):
        """Equal-size windows of the views around each view's guess, and their (x, y)
        origins (V, 2); the whole views when they are smaller than a window."""
        r = int(self.refine_window_px)
        crops, origin = [], np.zeros((len(images), 2))
        for k, img in enumerate(images):
            h, w = img.shape[:2]
            sw, sh = min(2 * r + 1, w), min(2 * r + 1, h)
            x0 = int(np.clip(np.rint(guess[k, 0]) - r, 0, w - sw))
            y0 = int(np.clip(np.rint(guess[k, 1]) - r, 0, h - sh))
            crops.append(img[y0:y0 + sh, x0:x0 + sw])
            origin[k] = x0, y0
        return crops, origin

    def _default_refine(self, images, pts, ref_view):
        i = self._proposing
        guess = self._guess(i, ref_view)
        try:
            from . import matching
            fn = getattr(matching, "refine_correspondences")
        except (ImportError, AttributeError):
            return guess[None]
        try:
            params = inspect.signature(fn).parameters
            kw = {"ref_view": ref_view} if "ref_view" in params else {}
            if "band_aware" in params:  # the band-aware pass costs ~1 s: too slow per click
                kw["band_aware"] = False
            # match in windows around the guesses, not in the whole views: a click on two
            # 2048×1536 views took 0.9 s, almost all of it spline-filtering the full images
            crops, origin = self._crops(images, guess)
            out = fn(crops, (guess - origin)[None], **kw)
            out = np.asarray(getattr(out, "pts", out), dtype=float)
            out = out.reshape(1, self.n_views, 2) + origin[None]
        except (SemlabError, TypeError, ValueError) as err:
            self.last_refine_error = err
            return guess[None]
        res = guess.copy()
        for k in range(self.n_views):
            if self.confirmed[i, k]:
                continue
            q = out[0, k]
            if _inside(q, self.shapes[k]) and np.hypot(*(q - guess[k])) <= self.max_refine_shift_px:
                res[k] = q
        return res[None]

    def _propose(self, i, ref_view):
        query = self.pts[i].copy()
        query[~self.confirmed[i]] = np.nan
        self._proposing = i
        fn = self.refine if self.refine is not None else self._default_refine
        out = np.asarray(fn(self.images, query[None], ref_view), dtype=float)
        if out.shape != (1, self.n_views, 2):
            raise GeometryError(f"refine returned shape {out.shape}, expected (1, "
                                f"{self.n_views}, 2)")
        for k in range(self.n_views):
            if not self.confirmed[i, k]:
                q = out[0, k]
                if not _inside(q, self.shapes[k]):
                    q = same_position_refine(self.images, query[None], ref_view)[0, k]
                self.pts[i, k] = q
        return self.pts[i].copy()

    def propose(self, point_index=None, ref_view=None):
        """(Re)compute the proposals of a point in its views not yet confirmed.

        Parameters
        ----------
        point_index : int, optional
            Default: the current point.
        ref_view : int, optional
            The view to propose from. Default: the first confirmed view.

        Returns
        -------
        (V, 2) array
            The point in every view, proposals included.
        """
        i = self.current if point_index is None else self._check_index(point_index)
        if i is None:
            raise GeometryError("no point is being picked; click a point first")
        if ref_view is None:
            conf = np.flatnonzero(self.confirmed[i])
            if conf.size == 0:
                raise GeometryError(f"point {self.point_id[i]} is confirmed in no view")
            ref_view = int(conf[0])
        return self._propose(i, self._check_view(ref_view))

    def accept(self):
        """Accept the current point with its proposals.

        Returns
        -------
        int or None
            Index of the accepted point, None if no point was being picked.
        """
        i = self.current
        if i is None:
            return None
        missing = [k for k in range(self.n_views) if not np.all(np.isfinite(self.pts[i, k]))]
        if missing:
            raise GeometryError(f"point {self.point_id[i]} has no position in view(s) {missing}; "
                                f"click it there before accepting")
        self.push_undo()
        self.confirmed[i] = True
        self.current = None
        self.selected = i
        return i

    def cancel(self):
        """Drop the point being picked (undoable); returns its index or None."""
        if self.current is None:
            return None
        return self.delete(self.current)

    def move(self, point_index, view, xy, record=True):
        """Move point ``point_index`` in ``view`` to ``xy`` (a drag); confirms that position.

        Parameters
        ----------
        point_index : int
        view : int
        xy : (2,) sequence of pixels
        record : bool
            Push an undo level (a drag records only its first move).
        """
        i = self._check_index(point_index)
        view = self._check_view(view)
        xy = self._check_xy(view, xy)
        if record:
            self.push_undo()
        self.pts[i, view] = xy
        self.confirmed[i, view] = True
        if i == self.current and self.confirmed[i].all():
            self.current = None
        self.selected = i

    def delete(self, point_index=None):
        """Delete a point (default: the selected one, else the current one).

        Returns
        -------
        int or None
            ``point_id`` of the deleted point, None if nothing was selected.
        """
        if point_index is None:
            point_index = self.selected if self.selected is not None else self.current
        if point_index is None:
            return None
        i = self._check_index(point_index)
        self.push_undo()
        pid = int(self.point_id[i])
        keep = np.arange(self.n_points) != i
        self.pts, self.point_id = self.pts[keep], self.point_id[keep]
        self.crack_id, self.confirmed = self.crack_id[keep], self.confirmed[keep]

        def shift(j):
            return None if j is None or j == i else (j - 1 if j > i else j)

        self.current, self.selected = shift(self.current), None
        return pid

    def set_crack(self, point_index, crack_id):
        """Assign point ``point_index`` to crack ``crack_id`` (``-1`` for none)."""
        i = self._check_index(point_index)
        self.push_undo()
        self.crack_id[i] = int(crack_id)
        self._has_crack_column = True

    def select_nearest(self, view, xy, max_dist_px):
        """Select the point nearest to ``xy`` in ``view`` if within ``max_dist_px``.

        Returns
        -------
        int or None
            The index selected, or None (the selection is then cleared).
        """
        view = self._check_view(view)
        xy = np.asarray(xy, dtype=float)
        d = np.hypot(*(self.pts[:, view] - xy).T) if self.n_points else np.zeros(0)
        d = np.where(np.isfinite(d), d, np.inf)
        if d.size == 0 or d.min() > max_dist_px:
            self.selected = None
            return None
        self.selected = int(np.argmin(d))
        return self.selected

    # ---- epipolar geometry
    def _line(self, view_from, xy, view_to):
        if (view_from, view_to) in self.F:
            Fm = self.F[(view_from, view_to)]
        elif (view_to, view_from) in self.F:
            Fm = self.F[(view_to, view_from)].T
        else:
            return None
        line = Fm @ np.array([xy[0], xy[1], 1.0])
        return line if np.hypot(line[0], line[1]) > 0 else None

    def epipolar_line(self, view_from, xy, view_to=None):
        """Epipolar line in ``view_to`` of the pixel ``xy`` of ``view_from``, clipped to the image.

        For ``x_to ᵀ F x_from = 0`` the line is ``l = F x_from`` (Hartley & Zisserman 2nd ed.,
        sec. 9.2.2, result 9.5); for the other direction ``l = Fᵀ x``.

        Parameters
        ----------
        view_from : int
        xy : (2,) sequence of pixels in ``view_from``
        view_to : int, optional
            Needed when there are more than 2 views.

        Returns
        -------
        (2, 2) array or None
            End points ``[[x_a, y_a], [x_b, y_b]]`` in pixels of ``view_to``, None if the
            line misses the image.
        """
        view_from = self._check_view(view_from)
        if view_to is None:
            if self.n_views != 2:
                raise GeometryError("view_to is needed with more than 2 views")
            view_to = 1 - view_from
        view_to = self._check_view(view_to)
        if not self.F:
            raise GeometryError("no fundamental matrix: pass F=... to the picker")
        line = self._line(view_from, np.asarray(xy, dtype=float), view_to)
        if line is None:
            if (view_from, view_to) not in self.F and (view_to, view_from) not in self.F:
                raise GeometryError(f"no fundamental matrix between views {view_from} and "
                                    f"{view_to}; give F as a dict {{({view_from}, {view_to}): F}}")
            return None
        return clip_line_to_image(line, self.shapes[view_to])

    # ---- tables and files
    def table(self):
        """The points as a list of dict rows.

        Keys: ``point_id``, ``x{k}_px``, ``y{k}_px`` for each view (None where unknown),
        ``crack_id`` (None for none) and ``status``: ``"picked"``, ``"picking"`` (the current
        point) or ``"incomplete"``.
        """
        rows = []
        for i in range(self.n_points):
            row = {"point_id": int(self.point_id[i])}
            for k in range(self.n_views):
                x, y = self.pts[i, k]
                row[f"x{k}_px"] = float(x) if np.isfinite(x) else None
                row[f"y{k}_px"] = float(y) if np.isfinite(y) else None
            row["crack_id"] = int(self.crack_id[i]) if self.crack_id[i] >= 0 else None
            if i == self.current:
                row["status"] = "picking"
            elif np.isfinite(self.pts[i]).all():
                row["status"] = "picked"
            else:
                row["status"] = "incomplete"
            rows.append(row)
        return rows

    def to_correspondences(self):
        """The complete points (not the one being picked) as :class:`Correspondences`."""
        ok = self.complete()
        crack = None
        if self._has_crack_column or np.any(self.crack_id[ok] >= 0):
            crack = self.crack_id[ok].copy()
        return Correspondences(self.point_id[ok].copy(), self.pts[ok].copy(), crack)

    def save(self, path, backup=True):
        """Write the complete points to a correspondences CSV.

        The point being picked is not written. An existing file is first copied to
        ``<stem>.bak.csv`` (``.bak1.csv``, ...), see
        :func:`semlab.annotations.write_correspondences`.

        Returns
        -------
        Path or None
            The backup written.
        """
        return write_correspondences(path, self.to_correspondences(), backup=backup)

    def load(self, path):
        """Replace the points by those of a correspondences CSV (undoable).

        The file is validated against the number of views and the image shapes.
        """
        corr = read_correspondences(path, n_views=self.n_views, image_shapes=self.shapes)
        self.push_undo()
        self.pts = corr.pts.copy()
        self.point_id = corr.point_id.copy()
        self._has_crack_column = corr.crack_id is not None
        self.crack_id = (corr.crack_id.copy() if corr.crack_id is not None
                         else np.full(corr.n_points, -1))
        self.confirmed = np.ones((corr.n_points, self.n_views), bool)
        self.current = self.selected = None
        return corr


# --------------------------------------------------------------------------- figure helpers

def _new_figure(figsize):
    import matplotlib.pyplot as plt
    from matplotlib._pylab_helpers import Gcf

    with plt.ioff():
        fig = plt.figure(figsize=figsize)
    # keep the picker out of pyplot's figure list: a later plt.close("all") or a backend
    # switch in another cell must not close the live picker
    Gcf.figs.pop(fig.canvas.manager.num, None)
    return fig


def _toolbar_busy(fig):
    """True when the navigation toolbar is in zoom or pan mode."""
    toolbar = getattr(fig.canvas, "toolbar", None)
    return bool(str(getattr(toolbar, "mode", "") or ""))


def _display_scale(ax):
    """Display pixels per data pixel along x of ``ax``."""
    t = ax.transData.transform([[0.0, 0.0], [1.0, 0.0]])
    return max(abs(t[1, 0] - t[0, 0]), 1e-12)


class _ScreenImage:
    """Show an image at the resolution of the screen: only the visible part, block-averaged
    by ``k`` so that it has about as many pixels as the axes has on the screen.

    A full SEM view (2048×1536) costs matplotlib ~0.12 s to resample at every draw, which
    makes clicking sluggish in ipympl (which cannot blit); the visible part at screen
    resolution draws in a fraction of that. Zoomed in (one image pixel over several screen
    pixels) the crop is shown at full resolution, so what the user clicks on is the image
    itself. The extent keeps pixel centres at integer coordinates (pixel ``(i, j)`` is
    the square ``[j - 0.5, j + 0.5] × [i - 0.5, i + 0.5]``).
    """

    def __init__(self, ax, img, **imshow_kw):
        self.ax = ax
        self.img = np.asarray(img)
        h, w = self.img.shape[:2]
        self.artist = ax.imshow(self.img[:1, :1], extent=(-0.5, 0.5, 0.5, -0.5), **imshow_kw)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        self.key = None
        self.update()
        # matplotlib keeps only weak references to these bound methods: the owner keeps
        # this object alive (see _show_image)
        ax.callbacks.connect("xlim_changed", self.update)
        ax.callbacks.connect("ylim_changed", self.update)

    def update(self, *_):
        """Re-crop and re-decimate for the current view limits."""
        h, w = self.img.shape[:2]
        x0, x1 = sorted(self.ax.get_xlim())
        y0, y1 = sorted(self.ax.get_ylim())
        c0 = int(np.clip(np.floor(x0 + 0.5), 0, w - 1))
        c1 = int(np.clip(np.ceil(x1 + 0.5), c0 + 1, w))
        r0 = int(np.clip(np.floor(y0 + 0.5), 0, h - 1))
        r1 = int(np.clip(np.ceil(y1 + 0.5), r0 + 1, h))
        try:
            screen_px = max(self.ax.get_window_extent().width, 1.0)
        except Exception:  # no renderer yet
            screen_px = 400.0
        k = max(1, int((c1 - c0) // screen_px))
        key = (c0, c1, r0, r1, k)
        if key == self.key:
            return
        self.key = key
        nr, nc = -(-(r1 - r0) // k), -(-(c1 - c0) // k)   # blocks, the last one partial
        crop = self.img[r0:r1, c0:c1].astype(np.float32)
        if k > 1:
            pad = np.full((nr * k, nc * k), np.nan, np.float32)
            pad[:r1 - r0, :c1 - c0] = crop
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                crop = np.nanmean(pad.reshape(nr, k, nc, k), axis=(1, 3))
        self.artist.set_data(crop)
        self.artist.set_extent((c0 - 0.5, c0 + nc * k - 0.5, r0 + nr * k - 0.5, r0 - 0.5))


def _show_image(ax, img, title):
    lo, hi = _robust_limits(img)
    ax._semlab_screen_image = _ScreenImage(ax, img, cmap="gray", vmin=lo, vmax=hi,
                                           interpolation="nearest")
    ax.set_autoscale_on(False)
    ax.set_title(title)
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")


class PickerFigure:
    """Matplotlib view and mouse/key controller of a :class:`CorrespondencePicker`.

    The views are shown side by side; picked points are cyan circles with their
    ``point_id``, proposals orange crosses, the active point (being picked or selected) a
    red ring, and with ``F`` its epipolar lines in yellow. See the module docstring for the
    mouse and keys.

    Parameters
    ----------
    picker : CorrespondencePicker
    fig : matplotlib Figure, optional
        An empty figure to draw in; default a new pyplot figure.
    pick_radius : float
        How close (display pixels) a click must be to a marker to select it.

    Attributes
    ----------
    axes : list of Axes, one per view
    message : str
        The last status message (also drawn at the bottom of the figure).
    on_change : list of callables
        Called with no argument after every redraw (the widget refreshes its table).
    """

    def __init__(self, picker, fig=None, pick_radius=8.0, figsize=None):
        self.picker = picker
        v = picker.n_views
        if fig is None:
            fig = _new_figure(figsize or (4.5 * v, 4.8))
        self.fig = fig
        self.pick_radius = float(pick_radius)
        self.axes = list(fig.subplots(1, v, squeeze=False)[0])
        self._done, self._prop, self._active, self._epi, self._labels = [], [], [], [], []
        for k, ax in enumerate(self.axes):
            _show_image(ax, picker.images[k], picker.titles[k])
            self._epi.append(ax.plot([], [], "-", color="yellow", lw=1.0, alpha=0.8)[0])
            self._done.append(ax.plot([], [], "o", mfc="none", mec="#00e5ff", ms=7,
                                      ls="none")[0])
            self._prop.append(ax.plot([], [], "x", color="orange", ms=8, mew=1.5, ls="none")[0])
            self._active.append(ax.plot([], [], "o", mfc="none", mec="red", ms=13, mew=2,
                                        ls="none")[0])
            self._labels.append({})
        self._status = fig.text(0.01, 0.005, "", fontsize=8, va="bottom")
        self.message = ""
        self.on_change = []
        self._drag = None
        self._bg = None
        self._cids = [fig.canvas.mpl_connect(name, cb) for name, cb in (
            ("button_press_event", self._on_press),
            ("motion_notify_event", self._on_motion),
            ("button_release_event", self._on_release),
            ("key_press_event", self._on_key))]
        self.redraw()

    def disconnect(self):
        """Stop listening to the canvas."""
        for cid in self._cids:
            self.fig.canvas.mpl_disconnect(cid)
        self._cids = []

    # ---- drawing
    def redraw(self):
        """Update every artist from the picker state and ask the canvas to redraw."""
        self._update_artists()
        self.fig.canvas.draw_idle()
        for cb in list(self.on_change):
            cb()

    def _dynamic_artists(self):
        """Everything that changes while picking (markers, lines, labels, status)."""
        arts = []
        for k in range(len(self.axes)):   # the order of a full draw: lines, then texts
            arts += [self._epi[k], self._done[k], self._prop[k], self._active[k]]
            arts += list(self._labels[k].values())
        return arts + [self._status]

    def _start_blit(self):
        """Dragging: draw the images once without the markers and keep that background, so
        that each mouse move only redraws the markers (a full draw of two 2048×1536 views
        takes ~0.25 s; see :meth:`_blit`)."""
        canvas = self.fig.canvas
        if not getattr(canvas, "supports_blit", False):
            return
        for a in self._dynamic_artists():
            a.set_animated(True)
        canvas.draw()
        self._bg = canvas.copy_from_bbox(self.fig.bbox)
        self._blit()

    def _blit(self):
        self._update_artists()
        canvas = self.fig.canvas
        canvas.restore_region(self._bg)
        for a in self._dynamic_artists():
            a.set_animated(True)
            self.fig.draw_artist(a)
        canvas.blit(self.fig.bbox)

    def _stop_blit(self):
        if self._bg is None:
            return
        self._bg = None
        for a in self._dynamic_artists():
            a.set_animated(False)

    def _update_artists(self):
        p = self.picker
        active = p.current if p.current is not None else p.selected
        for k, ax in enumerate(self.axes):
            xy = p.pts[:, k] if p.n_points else np.zeros((0, 2))
            fin = np.isfinite(xy).all(axis=1)
            conf = p.confirmed[:, k] if p.n_points else np.zeros(0, bool)
            done = fin & conf
            prop = fin & ~conf
            self._done[k].set_data(xy[done, 0], xy[done, 1])
            self._prop[k].set_data(xy[prop, 0], xy[prop, 1])
            if active is not None and fin[active]:
                self._active[k].set_data([xy[active, 0]], [xy[active, 1]])
            else:
                self._active[k].set_data([], [])
            seg = self._epipolar_for(active, k) if active is not None else None
            if seg is None:
                self._epi[k].set_data([], [])
            else:
                self._epi[k].set_data(seg[:, 0], seg[:, 1])
            self._update_labels(k, ax, xy, fin, prop)
        help_text = ("click: add | drag marker: move | a/enter: accept | d/delete: delete | "
                     "u/ctrl+z: undo | esc: drop")
        n_done = int(p.complete().sum())
        self._status.set_text(f"{n_done} point(s) picked. " + (self.message or help_text))

    def _update_labels(self, k, ax, xy, fin, prop):
        """Point-id labels of view ``k``, updated in place (cheap while dragging)."""
        labels = self._labels[k]
        shown = set()
        for i in np.flatnonzero(fin):
            pid = int(self.picker.point_id[i])
            shown.add(pid)
            pos = (xy[i, 0] + 4, xy[i, 1] - 4)
            color = "orange" if prop[i] else "#00e5ff"
            t = labels.get(pid)
            if t is None:
                labels[pid] = ax.text(*pos, str(pid), fontsize=7, color=color, clip_on=True)
            else:
                t.set_position(pos)
                t.set_color(color)
        for pid in set(labels) - shown:
            labels.pop(pid).remove()

    def _epipolar_for(self, i, view_to):
        p = self.picker
        if not p.F:
            return None
        for j in range(p.n_views):
            if j != view_to and p.confirmed[i, j] and np.isfinite(p.pts[i, j]).all():
                line = p._line(j, p.pts[i, j], view_to)
                if line is not None:
                    return clip_line_to_image(line, p.shapes[view_to])
        return None

    # ---- events
    def _view_of(self, event):
        if event.inaxes is None or event.xdata is None or event.ydata is None:
            return None
        for k, ax in enumerate(self.axes):
            if event.inaxes is ax:
                return k
        return None

    def _run(self, fn, *args):
        try:
            out = fn(*args)
            self.message = ""
            return out
        except SemlabError as err:
            self.message = str(err)
            return None

    def _on_press(self, event):
        k = self._view_of(event)
        if k is None or _toolbar_busy(self.fig):
            return
        xy = (event.xdata, event.ydata)
        r = self.pick_radius / _display_scale(self.axes[k])
        if event.button == 1:
            i = self.picker.select_nearest(k, xy, r)
            if i is not None:
                self._drag = [i, k, False]
                self.message = ""
            else:
                self._run(self.picker.add, k, xy)
        elif event.button == 3:
            self.picker.select_nearest(k, xy, r)
        else:
            return
        self.redraw()

    def _on_motion(self, event):
        if self._drag is None:
            return
        i, k, moved = self._drag
        if self._view_of(event) != k:
            return
        self._run(self.picker.move, i, k, (event.xdata, event.ydata), not moved)
        self._drag[2] = True
        if self._bg is None and not moved:
            self._start_blit()
        if self._bg is not None:
            self._blit()
        else:
            self.redraw()

    def _on_release(self, event):
        if self._drag is None:
            return
        i, k, moved = self._drag
        self._drag = None
        self._stop_blit()
        p = self.picker
        if not moved and i == p.current and not p.confirmed[i, k]:
            self._run(p.add, k, tuple(p.pts[i, k]))  # a click on a proposal confirms it
        self.redraw()

    def _on_key(self, event):
        key = (event.key or "").lower()
        p = self.picker
        if key in ("d", "delete"):
            self._run(p.delete)
        elif key in ("u", "ctrl+z"):
            if not p.undo():
                self.message = "nothing to undo"
        elif key in ("a", "enter"):
            self._run(p.accept)
        elif key == "escape":
            self._run(p.cancel)
        else:
            return
        self.redraw()


def _canvas_widget(fig, refresh_callbacks):
    """The figure as a widget: the ipympl canvas itself, else a static PNG preview."""
    import ipywidgets as W

    if isinstance(fig.canvas, W.DOMWidget):
        fig.canvas.header_visible = False
        return fig.canvas
    image = W.Image(format="png")

    def refresh():
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=72)
        image.value = buf.getvalue()

    refresh_callbacks.append(refresh)
    note = W.HTML("<b>Static preview</b>: run <code>%matplotlib widget</code> (ipympl) "
                  "before creating the picker to click in the images.")
    return W.VBox([note, image])


def _table_html(picker, max_rows=500):
    rows = picker.table()
    v = picker.n_views
    head = ["point_id"] + [f"{a}{k}_px" for k in range(v) for a in "xy"] + ["crack_id", "status"]
    out = ["<div style='max-height:260px;overflow:auto'><table style='font-size:11px'>",
           "<tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for i, r in enumerate(rows[:max_rows]):
        bg = " style='background:#ffe0b0'" if i in (picker.current, picker.selected) else ""
        cells = []
        for h in head:
            val = r.get(h)
            cells.append("" if val is None else (f"{val:.2f}" if isinstance(val, float) else
                                                 str(val)))
        out.append(f"<tr{bg}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    if len(rows) > max_rows:
        out.append(f"<tr><td colspan={len(head)}>... {len(rows) - max_rows} more</td></tr>")
    out.append("</table></div>")
    return "".join(out)


def picker_widget(images, save_path, pts=None, refine=None, F=None, titles=None,
                  load_existing=True, figsize=None):
    """A JupyterLab panel to pick corresponding points in 2+ views and save them as CSV.

    Run ``%matplotlib widget`` (ipympl) first so that the figure is interactive.

    Parameters
    ----------
    images : list of V (H, W) arrays
    save_path : str or Path
        The correspondences CSV (e.g. ``annotations/correspondences.csv``). Save keeps a
        backup of the file it replaces.
    pts, refine, F, titles
        See :class:`CorrespondencePicker`.
    load_existing : bool
        Start from the points in ``save_path`` when it exists and ``pts`` is None.
    figsize : (float, float), optional

    Returns
    -------
    ipywidgets.VBox
        Buttons Accept / Undo / Delete / Save, a status line, the figure and a table of the
        points. ``box.picker`` is the :class:`CorrespondencePicker`, ``box.figure`` the
        :class:`PickerFigure`, ``box.buttons`` a dict of the buttons.
    """
    import ipywidgets as W

    save_path = Path(save_path)
    picker = CorrespondencePicker(images, pts=pts, refine=refine, F=F, titles=titles)
    status = W.HTML()
    if load_existing and pts is None and save_path.exists():
        corr = picker.load(save_path)
        picker._undo.clear()
        status.value = f"loaded {corr.n_points} point(s) from <code>{save_path}</code>"
    fig = _new_figure(figsize or (4.5 * picker.n_views, 4.8))
    table = W.HTML()
    callbacks = []
    canvas = _canvas_widget(fig, callbacks)
    view = PickerFigure(picker, fig)

    def refresh():
        table.value = _table_html(picker)
        for cb in callbacks:
            cb()
        if view.message:
            status.value = f"<span style='color:#b00'>{view.message}</span>"

    view.on_change.append(refresh)

    def action(fn):
        def handler(_button):
            view._run(fn)
            view.redraw()
        return handler

    def undo(_button):
        if not picker.undo():
            view.message = "nothing to undo"
        view.redraw()

    def save(_button):
        try:
            bak = picker.save(save_path)
        except (SemlabError, OSError) as err:
            status.value = f"<span style='color:#b00'>not saved: {err}</span>"
            return
        n = int(picker.complete().sum())
        msg = f"saved {n} point(s) to <code>{save_path}</code>"
        if bak is not None:
            msg += f"; previous version kept as <code>{bak}</code>"
        if picker.current is not None:
            msg += " (the point being picked was not saved: accept it first)"
        status.value = msg

    buttons = {name: W.Button(description=name, layout=W.Layout(width="90px"))
               for name in ("Accept", "Undo", "Delete", "Save")}
    buttons["Accept"].on_click(action(picker.accept))
    buttons["Undo"].on_click(undo)
    buttons["Delete"].on_click(action(picker.delete))
    buttons["Save"].on_click(save)
    box = W.VBox([W.HBox(list(buttons.values())), status, canvas, table])
    box.picker, box.figure, box.buttons = picker, view, buttons
    refresh()
    return box


# --------------------------------------------------------------------------- line segments

def _point_segment_distance(xy, seg):
    p, a, b = np.asarray(xy, float), seg[:2], seg[2:]
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
    return float(np.hypot(*(p - (a + t * ab))))


class LinePicker:
    """The state of picking line segments in families of parallel 3D lines (one image).

    Two clicks make a segment, put in the selected family. See ``lines.json``
    (schema ``"semlab-lines/1"``) for the file written by :meth:`save`.

    Parameters
    ----------
    image : (H, W) array
    families : sequence of str
        Names of the line families (default ``("x", "y", "z")``, the three orthogonal
        directions of a calibration block).
    segments : dict, optional
        ``{family: [[x1, y1, x2, y2], ...]}`` already picked, pixels.

    Attributes
    ----------
    family : str
        The family new segments go to.
    pending : (2,) array or None
        The first end of the segment being picked.
    selected : int or None
        Index (in :meth:`segment_list` order) of the selected segment.
    """

    def __init__(self, image, families=("x", "y", "z"), segments=None):
        self.image = _check_images([image])[0]
        self.shape = self.image.shape[:2]
        self.families = tuple(str(f) for f in families)
        if not self.families or len(set(self.families)) != len(self.families):
            raise GeometryError(f"families must be distinct names, got {families!r}")
        self.family = self.families[0]
        self._segs = []  # list of (family, (4,) array)
        self.pending = None
        self.selected = None
        self.save_warning = None
        self._undo = []
        if segments:
            self._set_from_families(segments)

    def _set_from_families(self, fams):
        segs = []
        for f, lst in fams.items():
            if f not in self.families:
                raise GeometryError(f"family {f!r} is not one of {self.families}")
            for s in lst:
                s = np.asarray(s, dtype=float).reshape(-1)
                if s.shape != (4,) or not np.all(np.isfinite(s)):
                    raise GeometryError(f"segment {s!r} of family {f!r} must be 4 finite "
                                        f"numbers x1, y1, x2, y2")
                segs.append((f, s))
        self._segs = segs

    # ---- undo
    def _push(self):
        self._undo.append(([(f, s.copy()) for f, s in self._segs],
                           None if self.pending is None else self.pending.copy(),
                           self.selected, self.family))
        if len(self._undo) > _UNDO_LEVELS:
            del self._undo[0]

    def undo(self):
        """Undo the last edit; returns False when there is nothing to undo."""
        if not self._undo:
            return False
        self._segs, self.pending, self.selected, self.family = self._undo.pop()
        return True

    # ---- editing
    def set_family(self, family):
        """Choose the family of the next segments."""
        if family not in self.families:
            raise GeometryError(f"family {family!r} is not one of {self.families}")
        self.family = family

    def add(self, xy):
        """Click at ``xy`` (pixels): the first or second end of a segment.

        Returns
        -------
        int or None
            Index of the new segment when this click completes one, else None.
        """
        xy = np.asarray(xy, dtype=float).reshape(-1)
        if xy.shape != (2,) or not _inside(xy, self.shape):
            h, w = self.shape
            raise GeometryError(f"{xy!r} is not a pixel position inside the {w}x{h} image")
        if self.pending is None:
            self._push()
            self.pending = xy
            return None
        if np.hypot(*(xy - self.pending)) < 1.0:
            raise GeometryError("the segment is shorter than 1 px: click its other end farther "
                                "away")
        self._push()
        self._segs.append((self.family, np.concatenate([self.pending, xy])))
        self.pending = None
        self.selected = len(self._segs) - 1
        return self.selected

    def cancel(self):
        """Forget the first end of the segment being picked."""
        if self.pending is not None:
            self._push()
            self.pending = None

    def select_nearest(self, xy, max_dist_px):
        """Select the segment nearest to ``xy`` if within ``max_dist_px``; returns its index."""
        d = [_point_segment_distance(xy, s) for _, s in self._segs]
        if not d or min(d) > max_dist_px:
            self.selected = None
            return None
        self.selected = int(np.argmin(d))
        return self.selected

    def delete(self, index=None):
        """Delete a segment (default: the selected one, else the last one).

        Returns
        -------
        (str, (4,) array) or None
            The family and end points of the deleted segment.
        """
        if index is None:
            index = self.selected if self.selected is not None else len(self._segs) - 1
        if not (0 <= index < len(self._segs)):
            return None
        self._push()
        out = self._segs.pop(index)
        self.selected = None
        return out

    # ---- access
    def segment_list(self):
        """List of ``(family, (4,) array [x1, y1, x2, y2])`` in picking order."""
        return list(self._segs)

    def segments(self, family):
        """``(M, 4)`` array of the segments ``[x1, y1, x2, y2]`` (pixels) of ``family``."""
        arr = [s for f, s in self._segs if f == family]
        return np.asarray(arr, dtype=float).reshape(-1, 4)

    def to_lines_dict(self, view=0, image=None):
        """The segments in the ``"semlab-lines/1"`` schema (one view; empty families left out).

        Parameters
        ----------
        view : int
            View number written in the file.
        image : str, optional
            Image path relative to the experiment folder (e.g. ``"calibration/block_0.png"``).
        """
        entry = {"view": int(view)}
        if image is not None:
            entry["image"] = str(image)
        entry["families"] = {f: [[float(v) for v in s] for s in self.segments(f)]
                             for f in self.families if len(self.segments(f))}
        return {"schema": _LINES_SCHEMA, "views": [entry]}

    def load(self, path, view=0):
        """Replace the segments by those of ``view`` in a lines.json file (undoable)."""
        data = _read_lines_json(path)
        for entry in data.get("views", []):
            if int(entry.get("view", -1)) == int(view):
                self._push()
                fams = entry.get("families", {})
                for f in fams:
                    if f not in self.families:
                        self.families = self.families + (str(f),)
                self._set_from_families(fams)
                self.pending = self.selected = None
                return True
        return False

    def save(self, path, view=0, image=None, backup=True):
        """Write the segments as ``view`` of a lines.json file, keeping its other views.

        An existing file is kept as a backup first. Uses ``semlab.vanishing.write_lines``
        when available (its backup is ``lines.json.bak``, ``.bak1``, ...); work in progress
        it refuses (a family with fewer than 2 segments) is still written, with the same
        schema and a ``<stem>.bak.json`` backup, and :attr:`save_warning` says why it is not
        usable for calibration yet.

        Returns
        -------
        Path or None
            The backup written.
        """
        path = Path(path)
        mine = self.to_lines_dict(view, image)
        views = []
        if path.exists():
            views = [e for e in _read_lines_json(path).get("views", [])
                     if int(e.get("view", -1)) != int(view)]
        views.append(mine["views"][0])
        views.sort(key=lambda e: int(e.get("view", 0)))
        bak, self.save_warning = _write_lines_json(
            path, {"schema": _LINES_SCHEMA, "views": views}, backup)
        return bak


def _read_lines_json(path):
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ExperimentError(f"{path}: lines file not found") from None
    except json.JSONDecodeError as err:
        raise ExperimentError(f"{path}: not valid JSON ({err}); fix it or move it away "
                              f"before saving lines") from None
    if not isinstance(data, dict) or data.get("schema") != _LINES_SCHEMA:
        raise ExperimentError(f"{path}: expected a JSON object with \"schema\": "
                              f"\"{_LINES_SCHEMA}\"; fix it or move it away")
    return data


def _write_lines_json(path, data, backup=True):
    """Write a lines dict with a backup of the file it replaces.

    ``semlab.vanishing.write_lines`` (the canonical writer, which validates the file for
    calibration) is used when it exists and can represent ``data`` (views numbered
    ``0..n-1``, image names for all views or none). Work in progress that it refuses (a
    family with a single segment, a view with none) is written by the same schema here.

    Returns
    -------
    backup : Path or None
    warning : str or None
        Why the canonical writer refused the file (it is saved but not yet usable for
        calibration), None when it wrote it.
    """
    path = Path(path)
    views = data["views"]
    try:
        from .vanishing import read_lines, write_lines
    except ImportError:
        read_lines = write_lines = None
    n_img = sum("image" in v for v in views)
    if (write_lines is not None and backup and n_img in (0, len(views))
            and [int(v["view"]) for v in views] == list(range(len(views)))):
        images = [v["image"] for v in views] if n_img else None
        try:
            bak = write_lines(path, [v["families"] for v in views], images=images)
            return (Path(bak) if isinstance(bak, (str, Path)) else None), None
        except SemlabError:
            pass  # work in progress: written below, with the reason in the warning
    text = json.dumps(data, indent=1) + "\n"
    bak = atomic_write_text(path, text, backup=backup)
    warning = None
    if read_lines is not None:
        try:
            read_lines(path)
        except SemlabError as err:
            warning = f"saved, but not usable for calibration yet: {err}"
    return bak, warning


_FAMILY_COLORS = {"x": "#ff4040", "y": "#40ff40", "z": "#4090ff"}
_OTHER_COLORS = ["#ffd000", "#ff40ff", "#40ffff", "#ff9000"]


class LinePickerFigure:
    """Matplotlib view and controller of a :class:`LinePicker`.

    Left click twice: a segment in the selected family (a dashed line follows the mouse
    after the first click); right click: select the nearest segment; keys: a family name
    (e.g. ``x``) selects that family, ``d``/delete deletes the selected (else last) segment,
    ``u``/ctrl+z undoes, escape drops the first end.

    Parameters
    ----------
    picker : LinePicker
    fig : matplotlib Figure, optional
    title : str, optional
    pick_radius : float
        Display pixels within which a right click selects a segment.
    """

    def __init__(self, picker, fig=None, title=None, pick_radius=8.0, figsize=None):
        self.picker = picker
        if fig is None:
            fig = _new_figure(figsize or (6.5, 5.5))
        self.fig = fig
        self.pick_radius = float(pick_radius)
        self.ax = fig.subplots()
        _show_image(self.ax, picker.image, title or "lines")
        self._lines = {}
        self._colors = {}
        for j, f in enumerate(picker.families):
            self._add_family_artist(f, j)
        self._sel = self.ax.plot([], [], "-", color="white", lw=3, alpha=0.6)[0]
        self._pending = self.ax.plot([], [], "+", color="white", ms=12, mew=2)[0]
        self._rubber = self.ax.plot([], [], "--", color="white", lw=1)[0]
        self._status = fig.text(0.01, 0.005, "", fontsize=8, va="bottom")
        self.message = ""
        self.on_change = []
        self._cids = [fig.canvas.mpl_connect(name, cb) for name, cb in (
            ("button_press_event", self._on_press),
            ("motion_notify_event", self._on_motion),
            ("key_press_event", self._on_key))]
        self.redraw()

    def _add_family_artist(self, f, j):
        color = _FAMILY_COLORS.get(f, _OTHER_COLORS[j % len(_OTHER_COLORS)])
        self._colors[f] = color
        self._lines[f] = self.ax.plot([], [], "-o", color=color, lw=1.5, ms=3, label=f)[0]

    def disconnect(self):
        """Stop listening to the canvas."""
        for cid in self._cids:
            self.fig.canvas.mpl_disconnect(cid)
        self._cids = []

    def redraw(self):
        """Update the artists from the picker state and ask the canvas to redraw."""
        p = self.picker
        for j, f in enumerate(p.families):
            if f not in self._lines:
                self._add_family_artist(f, j)
            segs = p.segments(f)
            xs = np.column_stack([segs[:, 0], segs[:, 2], np.full(len(segs), np.nan)]).ravel()
            ys = np.column_stack([segs[:, 1], segs[:, 3], np.full(len(segs), np.nan)]).ravel()
            self._lines[f].set_data(xs, ys)
        segs = p.segment_list()
        if p.selected is not None and p.selected < len(segs):
            s = segs[p.selected][1]
            self._sel.set_data([s[0], s[2]], [s[1], s[3]])
        else:
            self._sel.set_data([], [])
        if p.pending is None:
            self._pending.set_data([], [])
            self._rubber.set_data([], [])
        else:
            self._pending.set_data([p.pending[0]], [p.pending[1]])
        counts = ", ".join(f"{f}: {len(p.segments(f))}" for f in p.families)
        self._status.set_text(f"family {p.family!r} | {counts}. " + (
            self.message or "click twice: segment | right click: select | d: delete | "
                            "u: undo | family key: choose family"))
        self._pending.set_color(self._colors.get(p.family, "white"))
        self.fig.canvas.draw_idle()
        for cb in list(self.on_change):
            cb()

    def _run(self, fn, *args):
        try:
            out = fn(*args)
            self.message = ""
            return out
        except SemlabError as err:
            self.message = str(err)
            return None

    def _on_press(self, event):
        if (event.inaxes is not self.ax or event.xdata is None or _toolbar_busy(self.fig)):
            return
        xy = (event.xdata, event.ydata)
        if event.button == 1:
            self._run(self.picker.add, xy)
        elif event.button == 3:
            self.picker.select_nearest(xy, self.pick_radius / _display_scale(self.ax))
        else:
            return
        self.redraw()

    def _on_motion(self, event):
        p = self.picker
        if p.pending is None or event.inaxes is not self.ax or event.xdata is None:
            return
        self._rubber.set_data([p.pending[0], event.xdata], [p.pending[1], event.ydata])
        self.fig.canvas.draw_idle()

    def _on_key(self, event):
        key = event.key or ""
        p = self.picker
        if key in p.families:
            p.set_family(key)
        elif key.lower() in ("d", "delete"):
            if p.delete() is None:
                self.message = "no segment to delete"
        elif key.lower() in ("u", "ctrl+z"):
            if not p.undo():
                self.message = "nothing to undo"
        elif key == "escape":
            p.cancel()
        else:
            return
        self.redraw()


def line_picker_widget(image, save_path, view=0, image_name=None, families=("x", "y", "z"),
                       load_existing=True, figsize=None):
    """A JupyterLab panel to pick line segments of a calibration image into lines.json.

    Parameters
    ----------
    image : (H, W) array
    save_path : str or Path
        The lines.json file; Save replaces only entry ``view`` and keeps a backup.
    view : int
        View number of this image in lines.json.
    image_name : str, optional
        Image path relative to the experiment folder, stored with the view.
    families : sequence of str
    load_existing : bool
        Start from the segments of ``view`` in ``save_path`` when it exists.

    Returns
    -------
    ipywidgets.VBox
        A family ToggleButtons, buttons Undo / Delete / Save, a status line and the
        figure. ``box.picker`` is the :class:`LinePicker`, ``box.figure`` the
        :class:`LinePickerFigure`, ``box.family`` the ToggleButtons, ``box.buttons`` a dict.
    """
    import ipywidgets as W

    save_path = Path(save_path)
    picker = LinePicker(image, families=families)
    status = W.HTML()
    if load_existing and save_path.exists():
        if picker.load(save_path, view=view):
            picker._undo.clear()
            status.value = f"loaded view {view} from <code>{save_path}</code>"
    fig = _new_figure(figsize or (6.5, 5.5))
    callbacks = []
    canvas = _canvas_widget(fig, callbacks)
    view_fig = LinePickerFigure(picker, fig, title=image_name or f"view {view}")
    family = W.ToggleButtons(options=list(picker.families), value=picker.family,
                             description="family")

    def on_family(change):
        picker.set_family(change["new"])
        view_fig.redraw()

    family.observe(on_family, names="value")

    def refresh():
        if family.value != picker.family and picker.family in family.options:
            family.value = picker.family
        for cb in callbacks:
            cb()

    view_fig.on_change.append(refresh)

    def undo(_b):
        if not picker.undo():
            view_fig.message = "nothing to undo"
        view_fig.redraw()

    def delete(_b):
        if picker.delete() is None:
            view_fig.message = "no segment to delete"
        view_fig.redraw()

    def save(_b):
        try:
            bak = picker.save(save_path, view=view, image=image_name)
        except (SemlabError, OSError) as err:
            status.value = f"<span style='color:#b00'>not saved: {err}</span>"
            return
        msg = f"saved view {view} to <code>{save_path}</code>"
        if bak is not None:
            msg += f"; previous version kept as <code>{bak}</code>"
        if picker.save_warning:
            msg += f"<br><span style='color:#b60'>{picker.save_warning}</span>"
        status.value = msg

    buttons = {name: W.Button(description=name, layout=W.Layout(width="90px"))
               for name in ("Undo", "Delete", "Save")}
    buttons["Undo"].on_click(undo)
    buttons["Delete"].on_click(delete)
    buttons["Save"].on_click(save)
    box = W.VBox([family, W.HBox(list(buttons.values())), status, canvas])
    box.picker, box.figure, box.family, box.buttons = picker, view_fig, family, buttons
    refresh()
    return box
