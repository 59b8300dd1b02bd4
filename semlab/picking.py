"""The state of picking corresponding points between views: plain numpy, no drawing.

:class:`CorrespondencePicker` holds the points seen in ``V`` views, the proposals for the
views not clicked yet, an undo stack, the automatic points under review, and what changed
since the last save. The figures and panels that turn mouse and keys into calls on it are
in :mod:`semlab.widgets`; everything here is tested without a canvas.

The proposal of a click is computed in two stages:

1. a geometric guess (:meth:`CorrespondencePicker.guess`): the clicked position shifted by
   the median offset between views of the points already picked, moved onto the epipolar
   line when ``F`` is known, clipped into the image;
2. an optional refinement passed in as ``refine(images, guess, ref_view) -> (1, V, 2)``, for
   instance :class:`WindowedRefine` around :func:`semlab.matching.refine_correspondences`
   (see :func:`matching_refine`). Its answer is kept where it is inside the image and within
   ``max_refine_shift_px`` of the guess; a :class:`~semlab.errors.SemlabError` it raises is
   kept in ``last_refine_error`` and the guess is used.

Coordinates are those of :mod:`semlab.proposals`: ``(x, y)`` pixels, origin at the centre
of the top-left pixel.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from .annotations import Correspondences, read_correspondences, write_correspondences
from .errors import ExperimentError, GeometryError, ImageError, SemlabError
from .io import atomic_write_text
from .proposals import clip_line_to_image, fundamental_dict

__all__ = [
    "CorrespondencePicker",
    "autosave_path",
    "write_autosave",
    "read_autosave",
]

_UNDO_LEVELS = 500
_AUTOSAVE_SCHEMA = "semlab-picker-autosave/1"
#: review state of an automatic point
AUTO_PENDING, AUTO_ACCEPTED, AUTO_REJECTED = 0, 1, -1


def _inside(xy, shape):
    h, w = shape[:2]
    return bool(np.all(np.isfinite(xy)) and -0.5 <= xy[0] <= w - 0.5 and -0.5 <= xy[1] <= h - 0.5)


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
    *current* point) in another view. The views not yet clicked get a *proposal*
    (:meth:`propose`); :meth:`accept` confirms the proposals. Clicking the point in every
    view completes it without :meth:`accept`.

    Parameters
    ----------
    images : list of V (H, W) arrays
        The views, indexed ``[row, col]``.
    pts : (N, V, 2) array, Correspondences, or None
        Points already picked, ``(x, y)`` pixels per view (NaN for views not picked).
    refine : callable, optional
        ``refine(images, guess, ref_view) -> (1, V, 2)``: ``guess`` ``(1, V, 2)`` holds the
        clicked (confirmed) positions and the geometric guess (:meth:`guess`) in the other
        views, ``ref_view`` is the view just clicked. Default: the guess itself
        (:func:`same_position_refine`); :func:`matching_refine` gives sub-pixel matching.
    F : (3, 3) array or dict, optional
        Fundamental matrix with ``x1ᵀ F x0 = 0`` (homogeneous pixels of views 0 and 1), or a
        dict ``{(i, j): F_ij}`` with ``x_jᵀ F_ij x_i = 0``; enables :meth:`epipolar_line`.
    titles : list of str, optional
        Names of the views (figure titles, status messages).
    point_id, crack_id : (N,) int arrays, optional
        Ids of the points given in ``pts``; crack of each point (``-1`` for none).
    max_refine_shift_px : float
        Largest move the refinement may make from the guess (pixels).

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
    auto_pts : (M, V, 2) float array
        Automatic points under review (:meth:`set_auto`).
    auto_sigma_px : (M,) float array
    auto_state : (M,) int array
        ``AUTO_PENDING`` (0), ``AUTO_ACCEPTED`` (1, then also a picked point) or
        ``AUTO_REJECTED`` (-1).
    last_refine_error : SemlabError or None
        Why the last refinement failed (the guess was used).
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
        self.F = fundamental_dict(F, v)
        if refine is not None and not callable(refine):
            raise TypeError(f"refine must be a callable refine(images, guess, ref_view), "
                            f"got {refine!r}")
        self.refine = refine
        self.max_refine_shift_px = float(max_refine_shift_px)
        self.last_refine_error = None
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
        self.auto_pts = np.zeros((0, v, 2))
        self.auto_sigma_px = np.zeros(0)
        self.auto_state = np.zeros(0, int)
        self._auto_point_id = np.zeros(0, int)   # id given to an accepted automatic point
        self._undo = []
        self.mark_saved()

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
                self.confirmed.copy(), self.current, self.selected, self._has_crack_column,
                self.auto_state.copy(), self._auto_point_id.copy())

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
         self.selected, self._has_crack_column, self.auto_state,
         self._auto_point_id) = self._undo.pop()
        return True

    @property
    def can_undo(self):
        """True when :meth:`undo` has something to undo."""
        return bool(self._undo)

    # ---- saved state and unsaved changes
    def _saved_view(self):
        ok = self.complete()
        return {int(pid): (np.round(p, 4).tobytes(), int(c))
                for pid, p, c in zip(self.point_id[ok], self.pts[ok], self.crack_id[ok])}

    def mark_saved(self):
        """Take the present complete points as the saved ones (after a save or a load)."""
        self._saved = self._saved_view()

    def unsaved_changes(self):
        """Number of points added, deleted or changed since the last save (or load).

        Counted against what was saved, so that an undo back to the saved state gives 0.
        The point being picked is not counted (it is not saved before it is complete).
        """
        now = self._saved_view()
        added = len(now.keys() - self._saved.keys())
        removed = len(self._saved.keys() - now.keys())
        changed = sum(now[k] != self._saved[k] for k in now.keys() & self._saved.keys())
        return added + removed + changed

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
                                f"{self.titles[view]}")
        return xy

    def _check_index(self, i):
        if not (isinstance(i, (int, np.integer)) and 0 <= i < self.n_points):
            raise GeometryError(f"point index must be in 0..{self.n_points - 1}, got {i!r}")
        return int(i)

    def _new_id(self):
        ids = np.concatenate([self.point_id, self._auto_point_id])
        return int(ids.max()) + 1 if ids.size else 0

    def _append(self, xy_views, confirmed, pid=None):
        pid = self._new_id() if pid is None else int(pid)
        self.pts = np.concatenate([self.pts, np.asarray(xy_views, float)[None]])
        self.point_id = np.append(self.point_id, pid)
        self.crack_id = np.append(self.crack_id, -1)
        self.confirmed = np.concatenate([self.confirmed, np.asarray(confirmed, bool)[None]])
        return self.n_points - 1

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
            self.current = self._append(np.full((self.n_views, 2), np.nan),
                                        np.zeros(self.n_views, bool))
        i = self.current
        self.pts[i, view] = xy
        self.confirmed[i, view] = True
        self.selected = i
        if self.confirmed[i].all():
            self.current = None
        else:
            self._propose(i, view)
        return i

    def guess(self, point_index, ref_view):
        """The geometric guess of a point in its views not confirmed, from ``ref_view``.

        The position in ``ref_view`` shifted by the median offset ``view k - ref_view`` of
        the complete points (none: the same position), projected onto the epipolar line of
        view ``k`` when ``F`` relates the two views, clipped into the image.

        Returns
        -------
        (V, 2) array
            Confirmed views keep their position.
        """
        i = self._check_index(point_index)
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

    def _refined(self, i, guess, ref_view):
        """The refinement's answer where it is usable, else the guess (stage 2)."""
        self.last_refine_error = None
        if self.refine is None:
            return guess
        try:
            out = np.asarray(self.refine(self.images, guess[None], ref_view), dtype=float)
        except SemlabError as err:
            self.last_refine_error = err
            return guess
        if out.shape != (1, self.n_views, 2):
            raise GeometryError(f"refine returned shape {out.shape}, expected (1, "
                                f"{self.n_views}, 2)")
        res = guess.copy()
        for k in range(self.n_views):
            q = out[0, k]
            if (not self.confirmed[i, k] and _inside(q, self.shapes[k])
                    and np.hypot(*(q - guess[k])) <= self.max_refine_shift_px):
                res[k] = q
        return res

    def _propose(self, i, ref_view):
        res = self._refined(i, self.guess(i, ref_view), ref_view)
        todo = ~self.confirmed[i]
        self.pts[i, todo] = res[todo]
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
        self.auto_state = np.where((self._auto_point_id == pid)
                                   & (self.auto_state == AUTO_ACCEPTED),
                                   AUTO_REJECTED, self.auto_state)

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

    def nearest(self, view, xy, max_dist_px, only=None):
        """Index of the point nearest to ``xy`` in ``view`` within ``max_dist_px``, or None.

        Parameters
        ----------
        view : int
        xy : (2,) sequence of pixels
        max_dist_px : float
        only : (N,) bool array, optional
            Candidates (default all points placed in ``view``).
        """
        view = self._check_view(view)
        if not self.n_points:
            return None
        d = np.hypot(*(self.pts[:, view] - np.asarray(xy, dtype=float)).T)
        d = np.where(np.isfinite(d), d, np.inf)
        if only is not None:
            d = np.where(only, d, np.inf)
        return int(np.argmin(d)) if d.min() <= max_dist_px else None

    def select_nearest(self, view, xy, max_dist_px):
        """Select the point nearest to ``xy`` in ``view`` if within ``max_dist_px``.

        Returns
        -------
        int or None
            The index selected, or None (the selection is then cleared).
        """
        self.selected = self.nearest(view, xy, max_dist_px)
        return self.selected

    # ---- automatic points under review
    def set_auto(self, pts, sigma_px=None):
        """Automatic points to review (shown apart; accepted ones become picked points).

        Parameters
        ----------
        pts : (M, V, 2) array of (x, y) pixels
        sigma_px : (M,) array, optional
            Their 1σ matching error (pixels), for :meth:`review_sigma`.
        """
        pts = np.asarray(pts, dtype=float)
        if pts.ndim != 3 or pts.shape[1:] != (self.n_views, 2):
            raise GeometryError(f"automatic points must have shape (M, {self.n_views}, 2), "
                                f"got {pts.shape}")
        ok = np.isfinite(pts).all(axis=(1, 2))
        sig = (np.full(len(pts), np.nan) if sigma_px is None
               else np.asarray(sigma_px, dtype=float).reshape(-1))
        if sig.shape != (len(pts),):
            raise GeometryError(f"sigma_px must have shape ({len(pts)},), got {sig.shape}")
        self.auto_pts, self.auto_sigma_px = pts[ok], sig[ok]
        self.auto_state = np.zeros(int(ok.sum()), int)
        self._auto_point_id = np.full(int(ok.sum()), -1)

    def _review(self, mask, accept):
        """Accept (append as picked points) or reject the pending automatic points in mask."""
        idx = np.flatnonzero(mask & (self.auto_state == AUTO_PENDING))
        if idx.size == 0:
            return 0
        self.push_undo()
        for j in idx:
            if accept:
                i = self._append(self.auto_pts[j], np.ones(self.n_views, bool))
                self._auto_point_id[j] = self.point_id[i]
            self.auto_state[j] = AUTO_ACCEPTED if accept else AUTO_REJECTED
        return int(idx.size)

    def review_region(self, view, x_range, y_range, accept):
        """Accept or reject the pending automatic points inside a box of one view.

        Parameters
        ----------
        view : int
        x_range, y_range : (2,) sequences of pixels
            The box (e.g. the zoomed part of the view).
        accept : bool

        Returns
        -------
        int
            Number of points accepted or rejected.
        """
        view = self._check_view(view)
        (x0, x1), (y0, y1) = sorted(x_range), sorted(y_range)
        p = self.auto_pts[:, view]
        inside = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1)
        return self._review(inside, bool(accept))

    def review_sigma(self, max_sigma_px, accept_rest=False):
        """Reject the pending automatic points with ``sigma_px > max_sigma_px`` (or no σ);
        with ``accept_rest`` accept the others.

        Returns
        -------
        (int, int)
            Numbers rejected and accepted.
        """
        bad = ~(self.auto_sigma_px <= float(max_sigma_px))
        n_rej = self._review(bad, False)
        n_acc = self._review(~bad, True) if accept_rest else 0
        return n_rej, n_acc

    def auto_counts(self):
        """``{"pending": n, "accepted": n, "rejected": n}`` of the automatic points."""
        s = self.auto_state
        return {"pending": int((s == AUTO_PENDING).sum()),
                "accepted": int((s == AUTO_ACCEPTED).sum()),
                "rejected": int((s == AUTO_REJECTED).sum())}

    # ---- what to do next
    def status(self):
        """One sentence saying what the next step is, for the status line.

        Examples: ``"point 56: check the × in view_1 — click it or press a, drag to adjust"``,
        ``"point 12 selected (complete): drag a marker to move it, d deletes it"``,
        ``"click a feature in any view to start point 57"``.
        """
        if self.current is not None:
            i = self.current
            pid = int(self.point_id[i])
            todo = [self.titles[k] for k in range(self.n_views) if not self.confirmed[i, k]]
            return (f"point {pid}: check the × in {', '.join(todo)} — click it or press a "
                    f"to accept, drag it to adjust, or click the right place; esc drops it")
        if self.selected is not None:
            pid = int(self.point_id[self.selected])
            return (f"point {pid} selected: drag a marker to move it, d deletes it; click a "
                    f"feature elsewhere to start point {self._new_id()}")
        return f"click a feature in any view to start point {self._new_id()}"

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
        bak = write_correspondences(path, self.to_correspondences(), backup=backup)
        self.mark_saved()
        return bak

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
        self.mark_saved()
        return corr

    # ---- autosave
    def to_state(self):
        """Everything needed to restore the picking session, as a JSON-able dict."""
        def arr(a):
            return [[None if not np.isfinite(v) else float(v) for v in row]
                    for row in np.asarray(a, float).reshape(len(a), -1)]

        return {"schema": _AUTOSAVE_SCHEMA, "n_views": self.n_views,
                "shapes": [list(map(int, s)) for s in self.shapes],
                "point_id": self.point_id.tolist(), "crack_id": self.crack_id.tolist(),
                "pts": arr(self.pts), "confirmed": self.confirmed.astype(int).tolist(),
                "has_crack_column": bool(self._has_crack_column),
                "current": self.current, "auto_state": self.auto_state.tolist(),
                "auto_point_id": self._auto_point_id.tolist(),
                "saved_ids": sorted(self._saved), "time": time.strftime("%Y-%m-%d %H:%M:%S")}

    def restore_state(self, state, source="autosave"):
        """Take the points of :meth:`to_state` (undoable); the saved baseline is kept.

        Raises
        ------
        ExperimentError
            When the state is for other views (number or image shapes).
        """
        if (state.get("schema") != _AUTOSAVE_SCHEMA or state.get("n_views") != self.n_views
                or [tuple(s) for s in state.get("shapes", [])] != [tuple(s) for s in self.shapes]):
            raise ExperimentError(f"{source}: not a picker autosave of these {self.n_views} "
                                  f"views (schema, number of views or image sizes differ); "
                                  f"delete it to start from the saved file")
        n = len(state["point_id"])
        pts = np.array([[np.nan if v is None else v for v in row] for row in state["pts"]],
                       float).reshape(n, self.n_views, 2)
        self.push_undo()
        self.pts = pts
        self.point_id = np.asarray(state["point_id"], int).reshape(n)
        self.crack_id = np.asarray(state["crack_id"], int).reshape(n)
        self.confirmed = np.asarray(state["confirmed"], bool).reshape(n, self.n_views)
        self._has_crack_column = bool(state.get("has_crack_column", False))
        cur = state.get("current")
        self.current = int(cur) if cur is not None and 0 <= int(cur) < n else None
        self.selected = self.current
        auto = np.asarray(state.get("auto_state", []), int)
        if auto.shape == self.auto_state.shape:
            self.auto_state = auto
            self._auto_point_id = np.asarray(state.get("auto_point_id"), int).reshape(auto.shape)


def autosave_path(save_path):
    """The side file the picker autosaves to: ``<stem>.autosave.json`` beside ``save_path``."""
    save_path = Path(save_path)
    return save_path.with_name(f"{save_path.stem}.autosave.json")


def write_autosave(picker, save_path):
    """Write the picking session beside ``save_path`` (no backup; replaced atomically).

    Returns
    -------
    Path
        The autosave file.
    """
    path = autosave_path(save_path)
    atomic_write_text(path, json.dumps(picker.to_state()) + "\n")
    return path


def read_autosave(save_path):
    """The autosaved state beside ``save_path``, or None when there is none.

    Raises
    ------
    ExperimentError
        When the file is not valid JSON (it names the file and says to delete it).
    """
    path = autosave_path(save_path)
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ExperimentError(f"{path}: the picker's autosave is unreadable ({err}); delete "
                              f"it to start from the saved file") from None


