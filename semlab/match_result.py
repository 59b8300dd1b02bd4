"""The result of stereo matching (:class:`MatchResult`), input checks, and merging."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from .errors import GeometryError, ImageError, SemlabError

__all__ = ["MatchResult", "merge_matches"]


@dataclass(frozen=True)
class MatchResult:
    """Correspondences of N material points in V views.

    Attributes
    ----------
    pts : (N, V, 2) float array
        Pixel positions ``(x, y)`` in each view; NaN in a non-reference view where that
        view could not be matched. The reference-view positions are kept exactly as given.
    zncc : (N, V) float array
        Zero-normalised cross-correlation of the match in each view (1 in the reference
        view, -1 where undefined).
    valid : (N,) bool array
        True where every view matched with ``zncc >= min_zncc`` and passed the outlier
        tests.
    sigma_px : (N,) float array
        Estimated 1σ random matching error (pixels) along the parallax direction (x),
        root-mean-square over the non-reference views; NaN where invalid.
    reason : (N,) str array
        Empty for valid points, otherwise why the point was rejected.
    ref_view : int
        Index of the reference view.
    kind : (N,) str array
        Origin of each point: ``"click"`` (refined hand click) or ``"auto"``.
    source_index : (N,) int array
        Row of each point in the input of its kind (click row, or grid index for auto).
    subset_px : (N,) int array
        Side ``2h+1`` (pixels) of the largest square subset used for the point over the
        views: its spatial resolution (times the pixel size in µm). With
        ``target_sigma_px`` it is chosen per point (:func:`semlab.adaptive.adaptive_icgn`);
        None in results made without it.
    view_valid : (N, V) bool array or None
        Per view: the match in that view passed every test of that view (the reference
        column is True for the points that were matched at all). ``valid`` is True where
        all views are; a point matched in the reference and at least one other view still
        has a height (:meth:`seen_in`, :func:`semlab.reconstruct.heights_from_tilts` with
        ``view_valid``). None in results made without it (every view as ``valid``).
    view_sigma_px : (N, V) float array or None
        1σ matching error (pixels, x) of each view's match: its noise σ with the a
        posteriori factor and its model error; 0 in the reference view, NaN where the view
        is not valid. ``sigma_px`` is the root mean square of its non-reference columns.
    params : AutoMatchParams or None
        The parameters of :func:`auto_match` that made the result (None for clicks).
    """

    pts: np.ndarray
    zncc: np.ndarray
    valid: np.ndarray
    sigma_px: np.ndarray
    reason: np.ndarray
    ref_view: int
    kind: np.ndarray
    source_index: np.ndarray
    subset_px: np.ndarray = None
    params: object = None
    view_valid: np.ndarray = None
    view_sigma_px: np.ndarray = None

    def __len__(self):
        return len(self.pts)

    @property
    def n_views(self):
        """Number of views V."""
        return self.pts.shape[1]

    def select(self, mask):
        """A new :class:`MatchResult` with the rows selected by ``mask`` (bool or index)."""
        m = np.asarray(mask)
        return replace(self, pts=self.pts[m], zncc=self.zncc[m], valid=self.valid[m],
                       sigma_px=self.sigma_px[m], reason=self.reason[m], kind=self.kind[m],
                       source_index=self.source_index[m],
                       subset_px=None if self.subset_px is None else self.subset_px[m],
                       view_valid=None if self.view_valid is None else self.view_valid[m],
                       view_sigma_px=None if self.view_sigma_px is None
                       else self.view_sigma_px[m])

    def only_valid(self):
        """The valid points only."""
        return self.select(self.valid)

    def views_valid(self):
        """(N, V) bool: which views of each point are valid (``view_valid``, or ``valid`` in
        every view where the result has no per-view record)."""
        if self.view_valid is not None:
            return np.asarray(self.view_valid, bool)
        return np.repeat(np.asarray(self.valid, bool)[:, None], self.n_views, axis=1)

    def seen_in(self, min_views=2):
        """The points valid in at least ``min_views`` views, the reference view included
        (``min_views = V``: :meth:`only_valid`). Their heights need
        :func:`semlab.reconstruct.heights_from_tilts` with ``view_valid``."""
        if not 2 <= int(min_views) <= self.n_views:
            raise SemlabError(f"min_views must be in 2..{self.n_views}, got {min_views!r}")
        vv = self.views_valid()
        return self.select(vv[:, self.ref_view] & (vv.sum(1) >= int(min_views)))


def _check_images(images, n_views=None):
    if isinstance(images, np.ndarray) and images.ndim == 2:
        raise ImageError("images must be a sequence of 2 or more views, got one 2D array")
    try:
        ims = [np.asarray(im) for im in images]
    except TypeError:
        raise ImageError("images must be a sequence of 2D arrays (one per view)") from None
    if len(ims) < 2:
        raise ImageError(f"need 2 or more views, got {len(ims)}")
    for i, im in enumerate(ims):
        if im.ndim != 2:
            raise ImageError(f"view {i} must be a 2D grey image, got shape {im.shape}")
        if not np.issubdtype(im.dtype, np.number) or np.iscomplexobj(im):
            raise ImageError(f"view {i} must hold real numbers, got dtype {im.dtype}")
        if not np.all(np.isfinite(im)):
            raise ImageError(f"view {i} contains NaN or infinite values")
    shapes = {im.shape for im in ims}
    if len(shapes) != 1:
        raise ImageError(f"all views must have the same shape, got {[im.shape for im in ims]}; "
                         "crop them to a common size (the data bar removed) first")
    if n_views is not None and len(ims) != n_views:
        raise GeometryError(f"pts has {n_views} views per point but {len(ims)} images were given")
    return [im.astype(np.float64, copy=False) for im in ims]


def _check_ref_view(ref_view, n_views):
    if isinstance(ref_view, bool) or not float(ref_view).is_integer() or \
            not 0 <= int(ref_view) < n_views:
        raise GeometryError(f"ref_view must be a view index in 0..{n_views - 1}, got {ref_view!r}")
    return int(ref_view)


def merge_matches(a, b, min_separation_px=3):
    """Merge two :class:`MatchResult` (e.g. refined clicks and automatic matches).

    Points whose reference-view positions are closer than ``min_separation_px`` are
    duplicates; of each group the best one is kept: valid before invalid, then the smaller
    ``sigma_px``, then the higher mean ZNCC (ties keep ``a``'s point).

    Parameters
    ----------
    a, b : MatchResult
        Same number of views and the same reference view.
    min_separation_px : float
        Duplicate distance in the reference view, pixels.

    Returns
    -------
    MatchResult
        ``a``'s kept points first, then ``b``'s, each in their original order.

    Raises
    ------
    GeometryError
        If the results have different numbers of views or reference views.
    """
    for r, name in ((a, "a"), (b, "b")):
        if not isinstance(r, MatchResult):
            raise SemlabError(f"{name} must be a MatchResult, got {type(r).__name__}")
    if a.n_views != b.n_views:
        raise GeometryError(f"cannot merge results with {a.n_views} and {b.n_views} views")
    if a.ref_view != b.ref_view:
        raise GeometryError(f"cannot merge results with reference views {a.ref_view} and "
                            f"{b.ref_view}")
    pts = np.concatenate([a.pts, b.pts])
    n = len(pts)
    if n == 0:
        return a
    valid = np.concatenate([a.valid, b.valid])
    sig = np.concatenate([a.sigma_px, b.sigma_px])
    zmean = np.concatenate([a.zncc, b.zncc]).mean(1)
    origin = np.r_[np.zeros(len(a)), np.ones(len(b))]
    order = np.lexsort((origin, -zmean, np.where(np.isfinite(sig), sig, np.inf), ~valid))
    xy = pts[:, a.ref_view]
    tree = cKDTree(xy)
    taken = np.zeros(n, bool)
    keep = np.zeros(n, bool)
    for i in order:            # greedy non-maximum suppression by quality
        if taken[i]:
            continue
        keep[i] = True
        taken[tree.query_ball_point(xy[i], r=min_separation_px)] = True
    ka, kb = keep[:len(a)], keep[len(a):]
    return MatchResult(pts=np.concatenate([a.pts[ka], b.pts[kb]]),
                       zncc=np.concatenate([a.zncc[ka], b.zncc[kb]]),
                       valid=np.concatenate([a.valid[ka], b.valid[kb]]),
                       sigma_px=np.concatenate([a.sigma_px[ka], b.sigma_px[kb]]),
                       reason=np.concatenate([a.reason[ka], b.reason[kb]]),
                       ref_view=a.ref_view,
                       kind=np.concatenate([a.kind[ka], b.kind[kb]]),
                       source_index=np.concatenate([a.source_index[ka], b.source_index[kb]]),
                       subset_px=_merge_subset_px(a, ka, b, kb),
                       view_valid=None if a.view_valid is None and b.view_valid is None else
                       np.concatenate([a.views_valid()[ka], b.views_valid()[kb]]))


def _merge_subset_px(a, ka, b, kb):
    if a.subset_px is None and b.subset_px is None:
        return None
    def side(r, k):
        return np.full(k.sum(), -1) if r.subset_px is None else r.subset_px[k]
    return np.concatenate([side(a, ka), side(b, kb)])
