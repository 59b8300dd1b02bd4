"""The run's stereo steps on large views: automatic matching and the dense map in tiles.

A 3072×4096 pair does not fit the untiled stereo chain in a few GB: the automatic matcher
(:func:`semlab.matching.auto_match`) and the dense map (:func:`semlab.heightmap.dense_parallax`)
hold whole-image flow fields, B-spline tables and subset work arrays. Both are local
(a grid point's match, or a map pixel, depends on the images near it), so they are run
here on overlapping tiles, on the dask cluster of :mod:`semlab.parallel`:

- :func:`tiled_auto_match` — ``auto_match`` on crops of every view: view 0's grid is cut
  into core tiles, each matched with a halo of ``halo_px`` (the reach of the neighbour
  filters, of the band orientation and of the adaptive subsets); the crop of another view
  is placed by the global affine map (:func:`global_affine`, features of views downsampled
  to ``prior_max_side_px``, found once and handed to every tile). Each grid point is kept
  from the tile whose core holds it (the overlaps are discarded, so no point twice). Equal
  to the untiled run within the IC-GN tolerance but for the band-aware choice of ~2 % of
  the points (test): each tile measures its own flow and image noise.
- :func:`map_roi_tiles` — any per-window dense method on core tiles of a region of view 0:
  ``fn(crops, roi, points, *args)`` on crops that reach ``reach_px`` beyond the tile.
- :func:`tiled_parallax` — a dense method with :func:`~semlab.heightmap.dense_parallax`'s
  signature (the default; a variational refinement can be plugged in) over ``roi`` in
  tiles, with one calibration for every tile (image noise, view 1's spline mean, σ factor
  and fusion τ measured once on a central window): equal to one untiled call with that
  calibration within the IC-GN tolerance (test).
- :func:`tiled_dense_parallax` — ``dense_parallax`` per tile, each tile calibrated on
  itself (each tile bit for bit its own call; also exported by :mod:`semlab.parallel`).

When to tile is one recorded object, :class:`TilingParams` (``min_pixels``: views with more
pixels than this are tiled by the run).

Conventions: images ``[row, col]``; points ``(x, y)`` pixels, origin at the centre of the
top-left pixel; ``roi = (x0, y0, x1, y1)`` half-open in view-0 pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .errors import GeometryError, SemlabError
from .parallel import _box, dask_client, map_tiles, plan_tiles

__all__ = ["TilingParams", "DEFAULT_TILING", "global_affine", "tiled_auto_match", "run_auto_match",
           "map_roi_tiles", "tiled_parallax", "tiled_dense_parallax"]


@dataclass(frozen=True)
class TilingParams:
    """When and how the run's stereo steps are tiled (recorded with the results).

    Attributes
    ----------
    min_pixels : int
        Views with more pixels than this are matched and mapped in tiles (default 2048²:
        a 2048×2048 pair still runs untiled in ~2 GB).
    tile_px : int
        Core tile of the automatic matching, pixels (multiple of 16).
    halo_px : int
        Grid points this far beyond a matching tile's core are matched with it (and
        discarded): the reach of the neighbour filters (8 nearest neighbours, twice), of
        the band orientation (2 half windows) and of the largest adaptive subset.
    dense_tile_px : int
        Core tile of the dense map, pixels (multiple of 16; a subset at every pixel: a
        256² tile with its halo holds ~0.4 GB of work arrays, benchmarks/memory_large.py).
    variational_tile_px : int
        Core tile of a variational map (:mod:`semlab.variational`; multiple of 16): its
        solve covers the tile and a ``margin_px`` band and holds ~0.75 kB per pixel at its
        peak (the multigrid set-up): ~0.3 GB for a 512² tile (a 1216² window: 1.1 GB;
        2026-12-05). Also the windows of stage 9 of :func:`~semlab.matching.auto_match`
        on views of more than ``map_min_pixels`` pixels.
    max_parallax_px : float
        Largest parallax left once a tile's view-1 crop is shifted by the median of its
        seeds' parallax (or the global affine), pixels: the crops reach this far.
    prior_max_side_px : int
        The global affine prior is found on views downsampled to at most this side.
    map_min_pixels : int
        Height maps of more pixels than this are mapped in tiles whatever the views' size
        (default 512²): an untiled map holds ~3.7 kB of work arrays per pixel (11.5 GB
        for a 1536×2048 map, 1.4 GB in 256 px tiles; 2026-12-01).
    """

    min_pixels: int = 2048 * 2048
    tile_px: int = 1024
    halo_px: int = 96
    dense_tile_px: int = 256
    variational_tile_px: int = 512
    max_parallax_px: float = 48.0
    prior_max_side_px: int = 1024
    map_min_pixels: int = 512 * 512

    def __post_init__(self):
        for name in ("min_pixels", "tile_px", "halo_px", "dense_tile_px",
                     "variational_tile_px", "prior_max_side_px", "map_min_pixels"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 0:
                raise SemlabError(f"TilingParams.{name} must be a whole number >= 0, got {v!r}")
        for name in ("tile_px", "dense_tile_px", "variational_tile_px"):
            plan_tiles((1, 1), getattr(self, name))       # its own check: multiple of 16
        if not self.max_parallax_px >= 0:
            raise SemlabError(f"TilingParams.max_parallax_px must be >= 0 pixels, got "
                              f"{self.max_parallax_px!r}")
        if self.prior_max_side_px < 64:
            raise SemlabError("TilingParams.prior_max_side_px must be >= 64 pixels, got "
                              f"{self.prior_max_side_px!r}")

    def tiles(self, shape):
        """True when views of ``shape`` (H, W) are tiled."""
        return int(shape[0]) * int(shape[1]) > self.min_pixels

    def tiles_map(self, shape, roi=None):
        """True when the height map of ``roi`` ((x0, y0, x1, y1), default the whole view)
        on views of ``shape`` (H, W) is mapped in tiles."""
        x0, y0, x1, y1 = roi if roi is not None else (0, 0, shape[1], shape[0])
        return self.tiles(shape) or (int(x1) - int(x0)) * (int(y1) - int(y0)) > self.map_min_pixels


#: The run's tiling (``semlab run`` and :class:`semlab.Analysis`).
DEFAULT_TILING = TilingParams()


# --------------------------------------------------------------------------- global prior
def global_affine(images, ref_view=0, detector="sift", ratio=0.8, max_features=5000,
                  seed=0, max_side_px=1024):
    """Global 2D affine maps from the reference view to every view, on downsampled views.

    Parameters
    ----------
    images : sequence of V (H, W) arrays
    ref_view : int
    detector, ratio, max_features, seed
        As in :class:`semlab.matching.AutoMatchParams`.
    max_side_px : int
        The views are reduced (area averaging) by the smallest integer factor ``f`` that
        brings their longer side to at most this.

    Returns
    -------
    affine : list of V (2, 3) arrays
        ``M[j]`` maps ``(x, y)`` of the reference view to view ``j``, full-resolution
        pixels (identity for the reference).
    features : dict
        ``{j: (src, dst)}``, the feature matches (full-resolution pixels) of every other
        view (the ``features`` of :func:`semlab.matching.auto_match`).

    Raises
    ------
    GeometryError
        Fewer than 6 feature matches with a view.
    """
    import cv2

    from .match_prior import _robust_affine, _to_uint8, fit_affine
    from .registration import match_features

    h, w = np.shape(images[ref_view])[:2]
    f = max(1, int(math.ceil(max(h, w) / float(max_side_px))))

    def small(im):
        a = np.asarray(im, np.float32)
        if f > 1:
            a = cv2.resize(a, (w // f, h // f), interpolation=cv2.INTER_AREA)
        return _to_uint8(a)

    c = (f - 1) / 2.0          # centre of the first f×f block, full-resolution pixels
    ref8, cache = small(images[ref_view]), {}
    out, feats = [], {}
    for j, im in enumerate(images):
        if j == ref_view:
            out.append(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
            continue
        src, dst = match_features(ref8, small(im), ratio=ratio, detector=detector,
                                  n_max=max_features, cache=cache)
        if len(src) < 6:
            raise GeometryError(f"only {len(src)} feature matches between views {ref_view} and "
                                f"{j} (downsampled {f}×); the views do not overlap or have too "
                                "little texture")
        _, inl = _robust_affine(src, dst, 2.0, seed)
        Ms = fit_affine(src[inl], dst[inl]) if inl.sum() >= 3 else fit_affine(src, dst)
        L, t = Ms[:, :2], Ms[:, 2]
        # x_full = f x_small + c:  M_full(x) = L x - L c + f t + c
        out.append(np.column_stack([L, -L @ [c, c] + f * t + c]))
        feats[j] = (f * src + c, f * dst + c)
    return out, feats


def _shifted_box(box, offset, shape):
    """``box`` (y0, y1, x0, x1) moved by the integer ``offset`` (dx, dy), kept inside
    ``shape`` (its size unchanged)."""
    y0, y1, x0, x1 = box
    h, w = shape
    dx, dy = int(offset[0]), int(offset[1])
    dx = min(max(dx, -x0), w - x1)
    dy = min(max(dy, -y0), h - y1)
    return y0 + dy, y1 + dy, x0 + dx, x1 + dx


# --------------------------------------------------------------------------- auto_match
def _match_task(crops, params, features):
    from .matching import auto_match

    try:
        r = auto_match(crops, params, progress=False, features=features)
    except GeometryError as exc:          # e.g. a featureless tile: its points stay invalid
        return str(exc)
    return r.pts, r.zncc, r.valid, r.sigma_px, r.reason, r.subset_px, r.views_valid(), \
        r.view_sigma_px


def tiled_auto_match(images, params=None, *, tiling=None, scheduler=None, progress=True,
                     **overrides):
    """:func:`semlab.matching.auto_match` of large views, in overlapping tiles.

    Called like ``auto_match`` (an :class:`~semlab.matching.AutoMatchParams` and/or its
    fields as keywords). The grid is ``auto_match``'s (same points, same order,
    ``source_index`` its index); each core tile of ``tiling.tile_px`` is matched on crops
    reaching ``tiling.halo_px`` beyond it (crop origins on the grid's lattice, so a tile's
    grid is the whole grid's), the crop of view ``j`` shifted by the global affine map
    (:func:`global_affine`). Points outside a tile's core are dropped from its result.

    Every tile gets the feature matches of the whole views (:func:`global_affine`, in its
    crops' pixels), so it fits the same affine prior (the untiled run's when the views'
    longer side is at most ``tiling.prior_max_side_px``; from downsampled views beyond).
    Differences from the untiled run (tested on a 6-tile scene, README "tiled against
    untiled"): each tile computes its own dense flow (the starting guesses), image noise
    (the IC-GN σ, hence the band-aware square/oriented choice of a few per cent of points)
    and texture noise; with ``smooth_sigma_px=None`` each tile chooses its own
    pre-smoothing; the multi-view threshold (3+ views) is per tile. A tile where
    ``auto_match`` fails (too few features: a featureless corner) leaves its points
    invalid with the reason.

    Parameters
    ----------
    images : sequence of V (H, W) arrays (``np.memmap`` works: only crops are read)
    params : AutoMatchParams, optional
        ``spacing_px`` must be a whole number of pixels and ``max_points`` None.
    tiling : TilingParams, optional
    scheduler : str, distributed.Client or None
        Where the tiles run (see :func:`semlab.parallel.dask_client`).
    progress : bool
    **overrides
        Fields of ``AutoMatchParams``.

    Returns
    -------
    MatchResult
        ``params`` is the ``AutoMatchParams`` used.
    """
    from .match_result import MatchResult, _check_ref_view
    from .matching import _auto_params

    p = _auto_params(params, overrides)
    t = tiling or DEFAULT_TILING
    ims = list(images)
    if len(ims) < 2 or any(np.ndim(im) != 2 for im in ims) or \
            len({np.shape(im) for im in ims}) != 1:
        from .match_result import _check_images

        _check_images(ims)              # its error
    v = len(ims)
    ref = _check_ref_view(p.ref_view, v)
    s = float(p.spacing_px)
    if not s.is_integer() or s < 1:
        raise SemlabError(f"tiled matching needs spacing_px a whole number of pixels (the "
                          f"tiles share the grid's lattice), got {p.spacing_px!r}")
    if p.max_points is not None:
        raise SemlabError("tiled matching keeps every grid point: give max_points=None "
                          "(or a larger spacing_px)")
    s = int(s)
    hgt, wid = np.shape(ims[ref])
    margin = int(p.half_window + p.search_px + 3)
    xs = np.arange(margin, wid - margin, s)
    ys = np.arange(margin, hgt - margin, s)
    if len(xs) == 0 or len(ys) == 0:
        raise GeometryError(f"images of {wid}×{hgt} px are too small for half_window="
                            f"{p.half_window} and search_px={p.search_px}")
    nx = len(xs)
    M, feats = global_affine(ims, ref, p.detector, p.ratio, p.max_features, p.seed,
                      t.prior_max_side_px)
    halo = int(t.halo_px)
    plans = []
    for tile in plan_tiles((hgt, wid), t.tile_px):
        ix = np.flatnonzero((xs >= tile.x0) & (xs < tile.x1))
        iy = np.flatnonzero((ys >= tile.y0) & (ys < tile.y1))
        if len(ix) == 0 or len(iy) == 0:
            continue
        # crop origin on the grid's lattice (multiples of the spacing): the crop's grid
        # arange(margin, ..., s) is then the whole grid's
        x0 = max(0, (tile.x0 - halo - margin) // s * s)
        y0 = max(0, (tile.y0 - halo - margin) // s * s)
        x1, y1 = min(wid, tile.x1 + halo + margin), min(hgt, tile.y1 + halo + margin)
        centre = np.array([(x0 + x1 - 1) / 2.0, (y0 + y1 - 1) / 2.0])
        boxes = [(y0, y1, x0, x1) if j == ref else _shifted_box(
            (y0, y1, x0, x1), np.round(M[j][:, :2] @ centre + M[j][:, 2] - centre), (hgt, wid))
            for j in range(v)]
        plans.append((tile, boxes, (iy[:, None] * nx + ix[None, :]).ravel()))
    tp = replace(p, ref_view=ref, max_points=None)

    def jobs():
        for i, (_, boxes, _) in enumerate(plans):
            b0 = np.array([boxes[ref][2], boxes[ref][0]], float)
            # every feature match, in the crops' pixels: each tile fits the whole views'
            # affine prior (the same inliers, the same map)
            fj = {j: (src - b0, dst - [boxes[j][2], boxes[j][0]])
                  for j, (src, dst) in feats.items()}
            yield i, ([np.asarray(im[b[0]:b[1], b[2]:b[3]], np.float64)
                       for im, b in zip(ims, boxes)], tp, fj)

    gx, gy = np.meshgrid(xs.astype(float), ys.astype(float))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(grid)
    out = np.full((n, v, 2), np.nan)
    out[:, ref] = grid
    zn = np.full((n, v), -1.0)
    zn[:, ref] = 1.0
    valid = np.zeros(n, bool)
    sigma = np.full(n, np.nan)
    reason = np.full(n, "not matched in its tile", dtype=object)
    side = np.zeros(n, int)
    vv = np.zeros((n, v), bool)             # per view, as auto_match's view_valid
    vsig = np.full((n, v), np.nan)
    with dask_client(scheduler) as client:
        for i, res in map_tiles(client, _match_task, jobs(), len(plans), "matching tiles",
                                progress):
            tile, boxes, core_idx = plans[i]
            if isinstance(res, str):
                reason[core_idx] = (f"tile x {tile.x0}:{tile.x1}, y {tile.y0}:{tile.y1}: "
                                    f"{res}")
                continue
            pts, z, ok, sg, why, sub, t_vv, t_vsig = res
            b = boxes[ref]
            col = np.rint((pts[:, ref, 0] + b[2] - margin) / s).astype(int)
            row = np.rint((pts[:, ref, 1] + b[0] - margin) / s).astype(int)
            gidx = row * nx + col
            keep = np.isin(gidx, core_idx)
            gidx = gidx[keep]
            for j, bj in enumerate(boxes):
                out[gidx, j] = pts[keep, j] + [bj[2], bj[0]]
            zn[gidx], valid[gidx], sigma[gidx] = z[keep], ok[keep], sg[keep]
            reason[gidx], side[gidx] = why[keep], sub[keep]
            vv[gidx] = t_vv[keep]
            if t_vsig is not None:
                vsig[gidx] = t_vsig[keep]
    sigma[~(vv[:, ref] & (vv.sum(1) >= 2))] = np.nan
    if progress:
        from tqdm.auto import tqdm
        tqdm.write(f"tiled auto_match: {valid.sum()} of {n} grid points accepted "
                   f"({len(plans)} tiles)")
    return MatchResult(pts=out, zncc=zn, valid=valid, sigma_px=sigma,
                       reason=reason.astype(str), ref_view=ref, kind=np.full(n, "auto"),
                       source_index=np.arange(n), subset_px=side, params=p,
                       view_valid=vv, view_sigma_px=vsig)


def run_auto_match(images, *, tiling=None, progress=True, **kw):
    """The run's automatic matching: :func:`semlab.matching.auto_match`, or
    :func:`tiled_auto_match` for views of more than ``tiling.min_pixels`` pixels (default
    :data:`DEFAULT_TILING`). ``kw``: fields of ``AutoMatchParams`` (and ``scheduler``)."""
    from .matching import auto_match

    t = tiling or DEFAULT_TILING
    if t.tiles(np.shape(images[0])[:2]):
        return tiled_auto_match(images, tiling=t, progress=progress, **kw)
    kw.pop("scheduler", None)
    return auto_match(images, progress=progress, **kw)


# --------------------------------------------------------------------------- dense maps
def map_roi_tiles(fn, images, roi, reach_px, *, tile_px=512, points=None, args=(),
                  scheduler=None, progress=True, desc="dense tiles", offsets=None, done=None,
                  pass_origins=False):
    """Apply a dense per-window method to core tiles of a region, on the cluster.

    Parameters
    ----------
    fn : callable
        ``fn(crops, roi_local, points_local, *args) -> (arrays, extra)``: ``crops`` the
        images cut to boxes reaching ``reach_px`` beyond the tile, ``roi_local`` the tile in
        the first crop's pixels, ``points_local`` the ``points`` inside every box, in crop
        pixels (or None); ``arrays`` a dict of ``(h, w)`` arrays over the tile, ``extra``
        anything (returned per tile). Positions in ``arrays`` stay in crop pixels (add
        ``origins``). A module-level function (it runs on the workers).
    images : sequence of (H, W) arrays, one shape
    roi : (x0, y0, x1, y1)
        Half-open window of the first image's pixels.
    reach_px : float
        How far beyond a tile the method reads the images, pixels.
    tile_px : int
    points : (N, V, 2) array, optional
        Points of the images (``[:, k]`` in image ``k``), handed to every tile in its crops'
        pixels (those inside every crop).
    args : tuple
        More arguments of ``fn`` (the same for every tile).
    offsets : callable, optional
        ``offsets(box) -> list of (dx, dy)``: integer shift of each image's crop from the
        first's (e.g. the median parallax of the tile's seeds); default no shift.
    done : dict, optional
        ``{(x0, y0, x1, y1): (arrays, extra)}``: core tiles already computed (by an earlier
        call on the same images with the same ``reach_px`` and ``offsets``, so the same
        crops): pasted, not run again.
    pass_origins : bool
        Call ``fn(crops, roi_local, points_local, *args, origins=origins)``, ``origins`` the
        crops' ``(x0, y0)`` in their images (for results tied to image coordinates).

    Returns
    -------
    arrays : dict of (h, w) arrays over ``roi``
        Floats are NaN, bools False, ints 0 where no tile wrote.
    origins : list of lists of (x0, y0)
        Each tile's crop origin in every image, tile order.
    extras : list
        ``extra`` of each tile, tile order.
    rois : list of (x0, y0, x1, y1)
        Each core tile, image pixels, tile order.
    """
    H, W = np.shape(images[0])[:2]
    plans = []
    for t in plan_tiles((roi[3] - roi[1], roi[2] - roi[0]), tile_px):
        r = (roi[0] + t.x0, roi[1] + t.y0, roi[0] + t.x1, roi[1] + t.y1)
        box = _box((r[0], r[1]), (r[2] - 1, r[3] - 1), reach_px, (H, W))
        offs = offsets(box) if offsets is not None else [(0, 0)] * len(images)
        boxes = [_shifted_box(box, o, (H, W)) for o in offs]
        plans.append((r, boxes))
    pts = None if points is None else np.asarray(points, float)

    def local_points(boxes):
        if pts is None:
            return None
        keep = np.ones(len(pts), bool)
        shift = np.zeros((len(boxes), 2))
        for k, (y0, y1, x0, x1) in enumerate(boxes):
            with np.errstate(invalid="ignore"):
                keep &= ((pts[:, k, 0] >= x0) & (pts[:, k, 0] <= x1 - 1)
                         & (pts[:, k, 1] >= y0) & (pts[:, k, 1] <= y1 - 1))
            shift[k] = (x0, y0)
        return pts[keep] - shift[None]

    done = dict(done or {})

    def jobs():
        for i, (r, boxes) in enumerate(plans):
            if r in done:
                continue
            y0, _, x0, _ = boxes[0]
            crops = [np.asarray(im[b[0]:b[1], b[2]:b[3]]) for im, b in zip(images, boxes)]
            kw = {"origins": [(b[2], b[0]) for b in boxes]} if pass_origins else {}
            yield i, (fn, crops, (r[0] - x0, r[1] - y0, r[2] - x0, r[3] - y0),
                      local_points(boxes), args, kw)

    shape = (roi[3] - roi[1], roi[2] - roi[0])
    arrays, extras = {}, [None] * len(plans)

    def results():
        for i, (r, _) in enumerate(plans):
            if r in done:
                yield i, done[r]
        left = sum(r not in done for r, _ in plans)
        if left:
            with dask_client(scheduler) as client:
                yield from map_tiles(client, _roi_task, jobs(), left, desc, progress)

    for i, (res, extra) in results():
        (rx0, ry0, rx1, ry1), _ = plans[i]
        sl = (slice(ry0 - roi[1], ry1 - roi[1]), slice(rx0 - roi[0], rx1 - roi[0]))
        for name, a in res.items():
            if name not in arrays:
                a = np.asarray(a)
                fill = False if a.dtype == bool else (
                    0 if np.issubdtype(a.dtype, np.integer) else np.nan)
                arrays[name] = np.full(shape, fill, a.dtype)
            arrays[name][sl] = a
        extras[i] = extra
    origins = [[(b[2], b[0]) for b in boxes] for _, boxes in plans]
    return arrays, origins, extras, [r for r, _ in plans]


def _roi_task(fn, crops, roi, points, args, kw):
    return fn(crops, roi, points, *args, **kw)


def _epipolar_moved(e, origins, sign):
    """The epipolar relation ``y1 − y0 = e0 + e1 x0 + e2 y0 + e3 (x1 − x0)`` of image
    pixels in the pixels of crops at ``origins`` ((x, y) of view 0's and view 1's crop)
    (``sign`` +1), or back (−1): only ``e0`` changes."""
    (ax, ay), (bx, by) = origins[0], origins[1]
    e = np.asarray(e, float).copy()
    e[0] += sign * (e[1] * ax + e[2] * ay + e[3] * (bx - ax) - (by - ay))
    return e.tolist()


def _plane_moved(c, origins, sign):
    """The parallax plane ``x1 − x0 = c0 + cx x0 + cy y0`` of image pixels in the pixels of
    crops at ``origins`` (``sign`` +1), or back (−1): only ``c0`` changes."""
    (ax, ay), (bx, by) = origins[0], origins[1]
    c = np.asarray(c, float).copy()
    c[0] += sign * (c[1] * ax + c[2] * ay - (bx - ax))
    return c.tolist()


def _parallax_tile(crops, roi, points, method, params, calibration, origins):
    """One tile of :func:`tiled_parallax` (positions in crop pixels; the calibration's
    epipolar relation and parallax plane in image pixels, moved to the crops' and back)."""
    cal = dict(calibration)
    moves = (("epipolar", _epipolar_moved), ("parallax_plane", _plane_moved))
    for key, move in moves:
        if cal.get(key) is not None:
            cal[key] = move(cal[key], origins, +1)
    p = method(crops[0], crops[1], seeds=points, roi=roi, params=params, calibration=cal)
    out = dict(p.calibration)
    for key, move in moves:
        if out.get(key) is not None:
            out[key] = move(out[key], origins, -1)
    arrays = {"x1_px": p.x1_px, "y1_px": p.y1_px, "sigma_px": p.sigma_px,
              "sigma_y_px": p.sigma_y_px, "valid": np.asarray(p.valid, bool), "zncc": p.zncc}
    if getattr(p, "weight_sigma_px", None) is not None:
        arrays["weight_sigma_px"] = p.weight_sigma_px
    return arrays, (p.sigma_scale, out)


def _dense_method(method):
    if method is None:
        from .heightmap import dense_parallax

        return dense_parallax
    if not callable(method):
        raise SemlabError(f"method must be a function with dense_parallax's signature, got "
                          f"{method!r}")
    return method


def _assemble(arrays, origins, plans, roi, params, scales, calibration):
    """Paste the tiles' view-1 positions into image pixels and build the DenseParallax."""
    from .heightmap import DenseParallax

    x1p, y1p = arrays["x1_px"], arrays["y1_px"]
    for (rx0, ry0, rx1, ry1), org in zip(plans, origins):
        sl = (slice(ry0 - roi[1], ry1 - roi[1]), slice(rx0 - roi[0], rx1 - roi[0]))
        x1p[sl] += org[1][0]
        y1p[sl] += org[1][1]
    valid = arrays["valid"]
    zn = np.where(valid, arrays["zncc"], -1.0)
    sc = [k for k in scales if k is not None and np.isfinite(k)]
    return DenseParallax(x1_px=x1p, y1_px=y1p, sigma_px=arrays["sigma_px"],
                         sigma_y_px=arrays["sigma_y_px"], valid=valid, zncc=zn, roi=roi,
                         sigma_scale=float(np.median(sc)) if sc else float("nan"),
                         params=params, calibration=dict(calibration or {}),
                         weight_sigma_px=arrays.get("weight_sigma_px"))


def _seed_offsets(seeds, default):
    """Per-tile integer shift of view 1's crop: the median parallax of the seeds in the
    tile's box, else ``default``."""
    s = None if seeds is None else np.asarray(seeds, float)
    if s is not None:
        s = s[np.all(np.isfinite(s.reshape(len(s), -1)), 1)]

    def offsets(box):
        y0, y1, x0, x1 = box
        d = default
        if s is not None and len(s):
            inside = ((s[:, 0, 0] >= x0) & (s[:, 0, 0] < x1) & (s[:, 0, 1] >= y0)
                      & (s[:, 0, 1] < y1))
            if inside.sum() >= 6:
                d = np.median(s[inside, 1] - s[inside, 0], axis=0)
        return [(0, 0), tuple(int(v) for v in np.rint(d))]

    return offsets


def tiled_parallax(view0, view1, seeds=None, roi=None, params=None, *, method=None,
                   calibration=None, tiling=None, scheduler=None, progress=True):
    """Dense correspondences of a region of view 0 in view 1, in tiles, one calibration.

    Every tile is ``method(crop0, crop1, seeds=local_seeds, roi=tile, params=params,
    calibration=calibration)`` on crops reaching ``params.margin_px()`` + the IC-GN search
    pad + ``tiling.max_parallax_px`` beyond the tile; view 1's crop is shifted by the median
    parallax of the seeds in the tile (so the parallax a crop must hold is the *variation*
    around it). The calibration is measured once (image noise as the matcher measures it,
    :func:`semlab.noise.calibrated_noise_sigma` at the seeds; a subset map's view-1 B-spline
    mean on the whole view; a variational map's epipolar relation fitted on all the seeds;
    σ factor, fusion τ, a variational map's prior scale, and what the seeds do not give, by
    ``method`` on the tile holding the centre of ``roi``, whose map is kept) and given to
    every tile, so the map equals one untiled ``method(view0, view1, seeds, roi, params,
    calibration=...)`` call within the IC-GN tolerance (the tiles' initial guesses are
    their crops' flow: tested). The epipolar relation is recorded in image pixels; each
    tile gets it in its crops' pixels (views rotated in the image plane: tested).

    The tile size is ``params.tile_px(tiling)`` (``tiling.dense_tile_px`` for the subset
    map, ``tiling.variational_tile_px`` for the variational map) and what the tiles share
    beyond the noise is ``params.shared_calibration(...)``.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    seeds : (N, 2, 2) array, optional
        Sparse matches ``[:, v] = (x, y)`` in view ``v`` (e.g. the run's stereo points).
    roi : (x0, y0, x1, y1), optional
        Default: the whole view.
    params : semlab.heightmap.DenseParams, optional
    method : callable, optional
        A dense method with :func:`~semlab.heightmap.dense_parallax`'s signature and result
        (default ``params.dense_method()``: ``dense_parallax`` for ``DenseParams``,
        :func:`~semlab.variational.variational_parallax` for ``VariationalParams``).
    calibration : dict, optional
        Keys of ``dense_parallax``'s ``calibration``; missing ones are measured as above.
    tiling : TilingParams, optional
    scheduler, progress : see :func:`semlab.parallel.tiled_icgn`.

    Returns
    -------
    semlab.heightmap.DenseParallax
        Over ``roi``, with the shared ``calibration``.
    """
    from .heightmap import DenseParams, _as_view, _check_roi
    from .noise import with_seed_noise

    p = params or DenseParams()
    fn = _dense_method(method or p.dense_method())
    t = tiling or DEFAULT_TILING
    v0, v1 = np.asarray(view0), np.asarray(view1)
    if v0.shape != v1.shape or v0.ndim != 2:
        _as_view(v0, "view0")
        _as_view(v1, "view1")
        raise SemlabError(f"view0 and view1 must have one shape, got {v0.shape} and {v1.shape}")
    roi = _check_roi(roi, v0.shape)
    # the matcher's calibrated noise at the seeds; without seeds the calibration tile
    # measures it the same way on its dense subsets (icgn_refine's default)
    cal = with_seed_noise(calibration, v0, v1, seeds)
    reach = p.margin_px() + float(t.max_parallax_px) + 2 * int(p.half_window) + 10
    seeds = None if seeds is None else np.asarray(seeds, float)[:, :2]
    default = (0.0, 0.0)
    if seeds is not None and len(seeds):
        fin = np.all(np.isfinite(seeds.reshape(len(seeds), -1)), 1)
        if fin.any():
            default = np.median(seeds[fin, 1] - seeds[fin, 0], axis=0)
    offsets = _seed_offsets(seeds, default)
    # what the method's tiles must share beyond the noise (the subset map: view 1's B-spline
    # level; the variational map: the epipolar relation fitted once on all the seeds, in
    # image pixels, each tile getting it in its crops' pixels)
    cal = p.shared_calibration(v0, v1, seeds, cal)
    tile_px = p.tile_px(t)
    done = {}
    if not {"sigma_factor", "zncc_tau", "noise_sigma"} <= set(cal):
        # the σ factor and fusion τ (a variational map: epipolar relation and prior scale)
        # of the tile holding the centre of roi, shared by every tile; that tile's map is
        # kept (with them it is what the tiling would compute again)
        cx, cy = (roi[0] + roi[2]) // 2, (roi[1] + roi[3]) // 2
        croi = next((roi[0] + k.x0, roi[1] + k.y0, roi[0] + k.x1, roi[1] + k.y1)
                    for k in plan_tiles((roi[3] - roi[1], roi[2] - roi[0]), tile_px)
                    if k.x0 <= cx - roi[0] < k.x1 and k.y0 <= cy - roi[1] < k.y1)
        carrays, corigins, extras, cplans = map_roi_tiles(
            _parallax_tile, [v0, v1], croi, reach, tile_px=_round16(max(croi[2] - croi[0],
                                                                         croi[3] - croi[1])),
            points=seeds, args=(fn, p, cal), scheduler=scheduler, progress=progress,
            desc="dense calibration", offsets=offsets, pass_origins=True)
        cal = {**extras[0][1], **cal}
        if croi == roi:
            # the region is one tile: the calibration window is the map
            return _assemble(carrays, corigins, cplans, roi, p, [extras[0][0]], cal)
        done[croi] = (carrays, extras[0])
    arrays, origins, extras, plans = map_roi_tiles(
        _parallax_tile, [v0, v1], roi, reach, tile_px=tile_px, points=seeds,
        args=(fn, p, cal), scheduler=scheduler, progress=progress, offsets=offsets, done=done,
        pass_origins=True)
    return _assemble(arrays, origins, plans, roi, p, [e[0] for e in extras], cal)


def _round16(v):
    return max(64, int(math.ceil(v / 16.0)) * 16)


def tiled_dense_parallax(view0, view1, roi=None, params=None, *, max_parallax_px=32.0,
                         tile_px=512, scheduler=None, progress=True):
    """:func:`semlab.heightmap.dense_parallax` of a large pair, tile by tile on the cluster.

    Each core tile is one ``dense_parallax(view0, view1, roi=tile)`` call, run on crops of
    both views that reach ``params.margin_px()`` + ``max_parallax_px`` + the IC-GN search
    pad beyond the tile, so it is that call bit for bit (tested) while holding only the
    crops. A window's result depends only on the images within ``margin_px`` of it, except
    for its initial guess (DIS flow of the window, not of the whole image: IC-GN converges to
    the same match within its tolerance) and its σ scale (measured per tile, so it is
    local). :func:`tiled_parallax` shares one calibration between the tiles instead.

    Parameters
    ----------
    view0, view1 : (H, W) arrays
    roi : (x0, y0, x1, y1), optional
        Half-open window of view-0 pixels; default the whole image.
    params : semlab.heightmap.DenseParams, optional
    max_parallax_px : float
        Largest |parallax| (view-1 position minus view-0 position), pixels. Larger
        parallax (tall objects: use seeds and :func:`tiled_parallax`) is clipped at the
        crop and flagged invalid near it.
    tile_px : int
        Core tile size, pixels (multiple of 16; a dense tile holds one subset per pixel).
    scheduler, progress : see :func:`semlab.parallel.tiled_icgn`.

    Returns
    -------
    semlab.heightmap.DenseParallax
        Over ``roi``; ``sigma_scale`` is the median of the tiles' scales.
    """
    from .heightmap import DenseParams, _as_view, _check_roi

    p = params or DenseParams()
    v0, v1 = np.asarray(view0), np.asarray(view1)
    if v0.shape != v1.shape:
        _as_view(v0, "view0")
        raise SemlabError(f"view0 and view1 must have one shape, got {v0.shape} and {v1.shape}")
    roi = _check_roi(roi, v0.shape)
    reach = p.margin_px() + float(max_parallax_px) + 2 * int(p.half_window) + 10
    arrays, origins, extras, plans = map_roi_tiles(
        _own_tile, [v0, v1], roi, reach, tile_px=tile_px, args=(p,), scheduler=scheduler,
        progress=progress)
    return _assemble(arrays, origins, plans, roi, p, [e[0] for e in extras], None)


def _own_tile(crops, roi, points, params):
    from .heightmap import dense_parallax

    p = dense_parallax(crops[0], crops[1], roi=roi, params=params)
    return ({"x1_px": p.x1_px, "y1_px": p.y1_px, "sigma_px": p.sigma_px,
             "sigma_y_px": p.sigma_y_px, "valid": np.asarray(p.valid, bool), "zncc": p.zncc},
            (p.sigma_scale, None))
