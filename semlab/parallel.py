"""Large images and long series: overlapping tiles on a dask.distributed cluster.

Dense subset matching and tracking are local: a subset, or a track, only ever reads the
images within a bounded distance (the *reach*) of its reference point. The image is cut
into ``tile_px`` × ``tile_px`` core tiles; every point belongs to the tile whose core holds
its reference position, and a tile's task reads only its core plus a halo of at least the
reach. The tasks run on a dask.distributed cluster; their results are put back in the input
order, equal to the untiled run (tests: ``tests/test_parallel.py``).

- :func:`tiled_icgn` — :func:`semlab.subset.icgn_refine` over many points (a dense grid)
  in tiles. Halo: the subset extent under the largest admissible warp, the IC-GN
  divergence limit (``half_window``) and 32 px for the B-spline prefilter and the Gaussian
  pre-smoothing (the prefilter's boundary effect decays as 0.268^d: 1e-18 at 32 px). The
  current image's coefficient level is the whole image's (``coef_offset``), so the float32
  rounding of the spline table is the untiled one: equal to ~1e-12 px.
- :func:`tiled_track_reverse` — :func:`semlab.tracking.track_reverse` in tiles of seeds.
  Each tile also tracks the seeds of a helper band around its core (the normalised median
  test couples a track to its neighbours) and reads the frames over the helper band plus
  the reach: maximal motion, the LK window at the coarsest pyramid level, the IC-GN check.
  Tile origins are multiples of 2^max_level, so the LK pyramids of a tile are those of the
  whole frame, and each tile's frames carry the whole frame's contrast stretch (a pinning
  strip, see :func:`_pinned_crop`): the stretched frames and LK pyramids are bit-identical,
  the valid flags equal, the positions equal within the float32 arithmetic of OpenCV's LK
  (~1e-4 px, below its 1e-3 px stopping tolerance: a tile's coordinates are smaller numbers,
  rounded differently) and ~1e-7 px with ``method="subset"``.

Where the work runs (:func:`dask_client`): by default a local cluster on this machine
(threads, all cores, loopback only); ``scheduler="tcp://HOST:PORT"`` (or the environment
variable ``SEMLAB_SCHEDULER``, which ``semlab run --scheduler`` sets for the notebooks) sends
it to an existing dask.distributed cluster, whose workers must have semlab installed. Each
call shows a tqdm bar over tiles (the driver counts finished tasks, so it works on any
cluster). One task per worker thread (plus one) is in flight, so the driver holds only
their crops; pass ``np.memmap`` / tifffile-memmapped frames to read only what the tiles need.

Conventions: images are indexed ``[row, col]``; points are ``(N, 2)`` arrays of ``(x, y)``
in pixels, origin at the centre of the top-left pixel.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import math
import os
import uuid
import warnings
from dataclasses import dataclass, replace

import numpy as np

from .errors import SemlabError, TrackingError

__all__ = ["SCHEDULER_ENV", "INLINE", "DEFAULT_TILE_PX", "Tile", "plan_tiles", "dask_client",
           "limit_heap_growth", "release_freed_memory", "set_default_scheduler",
           "scheduler_scope", "check_scheduler", "map_tiles", "tiled_icgn",
           "tiled_track_reverse", "tiled_dense_parallax", "map_roi_tiles"]

#: Environment variable holding the default scheduler address (``tcp://HOST:PORT``).
SCHEDULER_ENV = "SEMLAB_SCHEDULER"
#: The ``scheduler`` that runs tiles in this thread, one after another (see :func:`dask_client`).
INLINE = "inline"
#: Default core tile size, pixels (a 1024² tile with its halo is ~30-300 MB of work arrays).
DEFAULT_TILE_PX = 1024
_SPLINE_MARGIN_PX = 32          # B-spline prefilter boundary effect: 0.268^32 ~ 5e-19
_ALIGN_PX = 16                  # tile origins and pinning strips: multiples of 2^4
_CONNECT_TIMEOUT = "10s"        # how long to wait for a scheduler that does not answer


@dataclass(frozen=True)
class Tile:
    """One core tile: rows ``y0:y1`` and columns ``x0:x1`` (half-open, pixels)."""

    y0: int
    y1: int
    x0: int
    x1: int

    def contains(self, pts):
        """(N,) bool: ``(x, y)`` points whose pixel (floor) lies in the core."""
        p = np.floor(np.asarray(pts, float))
        with np.errstate(invalid="ignore"):
            return ((p[:, 0] >= self.x0) & (p[:, 0] < self.x1) & (p[:, 1] >= self.y0)
                    & (p[:, 1] < self.y1))


def _round_up(v, unit):
    return int(math.ceil(v / unit) * unit)


def plan_tiles(shape, tile_px=DEFAULT_TILE_PX):
    """Core tiles covering an image.

    Parameters
    ----------
    shape : (H, W)
        Image size, pixels.
    tile_px : int
        Core tile size, pixels: a multiple of 16 and at least 64.

    Returns
    -------
    list of Tile, row-major; edge tiles are smaller.
    """
    if isinstance(tile_px, bool) or int(tile_px) != tile_px or tile_px < 64 or tile_px % _ALIGN_PX:
        raise SemlabError(f"tile_px must be an integer multiple of {_ALIGN_PX} and >= 64, "
                          f"got {tile_px!r}")
    h, w = (int(v) for v in shape)
    t = int(tile_px)
    return [Tile(y0, min(y0 + t, h), x0, min(x0 + t, w))
            for y0 in range(0, h, t) for x0 in range(0, w, t)]


# --------------------------------------------------------------------------- the cluster
def set_default_scheduler(address, check=True):
    """Make ``address`` (``tcp://HOST:PORT``) the default scheduler of this process and of
    the processes it starts (the notebooks of ``semlab run``), via ``SEMLAB_SCHEDULER``.
    ``None`` or ``""`` restores the local cluster.

    With ``check``, connect once first, so that a wrong address fails here (a
    :class:`~semlab.errors.SemlabError`) rather than in the middle of a run.
    """
    if not address:
        os.environ.pop(SCHEDULER_ENV, None)
        return
    if check:
        check_scheduler(address)
    os.environ[SCHEDULER_ENV] = _check_address(address)


def check_scheduler(address):
    """Connect once to the scheduler at ``address``: a :class:`~semlab.errors.SemlabError`
    naming the fix when it is not an address or nothing answers there."""
    with dask_client(_check_address(address)):
        pass


@contextlib.contextmanager
def scheduler_scope(address):
    """Within the ``with`` block, ``address`` is the default scheduler (``SEMLAB_SCHEDULER``);
    the previous default is restored afterwards, so two analyses with different clusters in
    one Jupyter kernel do not change each other's. ``None`` or ``""`` leaves it unchanged."""
    if not address:
        yield
        return
    before = os.environ.get(SCHEDULER_ENV)
    os.environ[SCHEDULER_ENV] = _check_address(address)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(SCHEDULER_ENV, None)
        else:
            os.environ[SCHEDULER_ENV] = before


def _check_address(address):
    a = str(address)
    if "://" not in a or not a.split("://", 1)[1]:
        raise SemlabError(f"scheduler {a!r} is not an address: give the dask scheduler's "
                          "address as tcp://HOST:PORT (printed by `dask scheduler`)")
    return a


def _requested_scheduler(scheduler):
    return scheduler if scheduler is not None else (os.environ.get(SCHEDULER_ENV) or None)


# set by limit_heap_growth: each tile gives its freed memory back when it is done
_TRIM_AFTER_TILE = [False]


@functools.lru_cache(maxsize=None)
def _libc():
    """glibc (ctypes), or None on other systems (looked up once: called after every tile)."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name or not hasattr(os, "uname") or os.uname().sysname != "Linux":
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.mallopt, libc.malloc_trim       # noqa: B018 (glibc has both)
    except (OSError, AttributeError):
        return None
    return libc


def limit_heap_growth(mmap_threshold_bytes=16 * 1024 * 1024, arena_max=2):
    """Make glibc's allocator give the freed work arrays of tiles back to the system (Linux).

    The tiles of a dense map or of the tiled matcher run in threads; each thread's malloc
    arena keeps the freed work arrays of its tiles (glibc raises its mmap threshold after
    every large free, so later arrays come from the arenas, which fragment), and the process
    grows with the number of tiles although no tile's arrays are kept. Three settings stop
    this (dask.distributed sets ``MALLOC_TRIM_THRESHOLD_`` on its workers for the same
    reason): a fixed mmap threshold (arrays above it are mapped and unmapped), a couple of
    arenas, and ``malloc_trim`` after every tile of :func:`map_tiles` in this process (the
    freed pages inside the arenas go back at once).

    The threshold is a trade: arrays below it are reused from the arenas without page
    faults, arrays above it cost fresh pages every time. The 3072×4096 ``semlab run`` of
    ``benchmarks/memory_large.py --run`` (2026-12-05, results in
    ``benchmarks/results/memory_large_run.md``), with stage 9's maps whole per matching
    tile: at 64 kB (the default until then) 2.60 GB and a 882 s stereo step; at 16 MB 2.91 GB
    and 671 s, but the whole 12.6 Mpx map then peaked at 3.54 GB; with the trim 2.96 GB and
    656 s, whole map 2.92 GB (its heightmap step 527 s, 1100 s at 64 kB). ``semlab run``
    calls it; call it first in a notebook kernel that maps large views.

    Parameters
    ----------
    mmap_threshold_bytes : int
        Allocations at least this large are mapped (and unmapped when freed).
    arena_max : int
        Most malloc arenas.

    Returns
    -------
    bool
        True when the settings took effect (a glibc system), else False (nothing done).
    """
    libc = _libc()
    if libc is None:
        return False
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8
    ok = bool(libc.mallopt(m_mmap_threshold, int(mmap_threshold_bytes))
              and libc.mallopt(m_trim_threshold, int(2 * mmap_threshold_bytes))
              and libc.mallopt(m_arena_max, int(arena_max)))
    _TRIM_AFTER_TILE[0] = ok
    return ok


def release_freed_memory():
    """Give the free pages of every malloc arena back to the system (glibc's
    ``malloc_trim(0)``); :func:`map_tiles` calls it after each tile once
    :func:`limit_heap_growth` took effect.

    Returns
    -------
    bool
        True when some memory was given back, False when none was or not on glibc.
    """
    libc = _libc()
    return bool(libc is not None and libc.malloc_trim(0))


def _tile_done():
    if _TRIM_AFTER_TILE[0]:
        release_freed_memory()


@contextlib.contextmanager
def dask_client(scheduler=None, processes=False, n_workers=None):
    """A dask.distributed client for the duration of a ``with`` block.

    Parameters
    ----------
    scheduler : str, distributed.Client or None
        ``"tcp://HOST:PORT"``: connect to that existing cluster (closed on exit, the cluster
        keeps running). A ``Client``: use it as it is (not closed). None: the address in
        ``SEMLAB_SCHEDULER`` if set, else a new local cluster, closed on exit.
        :data:`INLINE` (``"inline"``): no cluster (yields None; :func:`map_tiles` then runs
        the tiles one after another in this thread): for tiles cut inside a task that
        already runs on a cluster (stage 9 of :func:`semlab.matching.auto_match` in a tile
        of :func:`semlab.tiled_stereo.tiled_auto_match`).
    processes : bool
        Local cluster only: worker processes (one per core, one thread each) instead of one
        in-process worker with a thread per core (the default: no copies of the tiles).
    n_workers : int, optional
        Local cluster only: worker count (default: all cores).

    Yields
    ------
    distributed.Client, or None for ``INLINE``

    Raises
    ------
    SemlabError
        When the scheduler address is malformed or nothing answers there.
    """
    if isinstance(scheduler, str) and scheduler == INLINE:
        yield None
        return
    from distributed import Client, LocalCluster

    scheduler = _requested_scheduler(scheduler)
    if isinstance(scheduler, Client):
        yield scheduler
        return
    if scheduler is not None:
        address = _check_address(scheduler)
        try:
            client = Client(address, timeout=_CONNECT_TIMEOUT)
        except OSError as exc:
            raise SemlabError(f"no dask scheduler answers at {address} ({exc}): start one "
                              "(`dask scheduler`, then `dask worker ADDRESS` on each machine) "
                              "or leave out --scheduler to run on this machine") from None
        with client:
            yield client
        return
    ncores = os.cpu_count() or 1
    n = int(n_workers) if n_workers else (ncores if processes else 1)
    # every server on loopback: the scheduler and worker HTTP servers would otherwise bind
    # 0.0.0.0 (and warn when another cluster holds port 8787)
    kw = dict(dashboard_address="127.0.0.1:0", worker_dashboard_address="127.0.0.1:0")
    if processes:
        kw.update(host="127.0.0.1", threads_per_worker=1)
    else:
        kw.update(threads_per_worker=max(1, ncores // n))
    with LocalCluster(n_workers=n, processes=processes, **kw) as cluster, \
            Client(cluster) as client:
        yield client


def map_tiles(client, fn, jobs, n_jobs, desc="tiles", progress=True):
    """Run ``fn(*args)`` for every ``(index, args)`` of ``jobs`` on the cluster.

    One task per worker thread plus one are in flight: ``jobs`` is consumed lazily, so the
    driver only ever holds the arguments (tile crops) of the running tasks and the next.

    With ``client`` None (:data:`INLINE`) the tasks run here, one after another, in
    ``jobs`` order. After :func:`limit_heap_growth`, each task gives its freed memory back
    when it ends (:func:`release_freed_memory`, in the process that ran it).

    Yields
    ------
    (index, result) in completion order, with a tqdm bar over the ``n_jobs`` tasks. An
    exception in a task is raised here (the other tasks are cancelled).
    """
    from tqdm.auto import tqdm

    if client is None:
        with tqdm(total=n_jobs, desc=desc, unit="tile", disable=not progress) as bar:
            for i, args in jobs:
                result = fn(*args)
                _tile_done()
                bar.update()
                yield i, result
        return
    from distributed import as_completed

    limit = sum(client.nthreads().values()) + 1     # every thread busy, one tile queued
    jobs = iter(jobs)
    tag = uuid.uuid4().hex[:8]
    inflight = {}

    def submit():
        try:
            i, args = next(jobs)
        except StopIteration:
            return None
        # the crops go to the workers as data (scatter), not inside the task: a task
        # carrying them would be a "large graph" for the scheduler (and a warning > 10 MB)
        data = client.scatter([args], hash=False)[0]
        fut = client.submit(_call, fn, data, key=f"semlab-{desc.replace(' ', '-')}-{tag}-{i}",
                            pure=False)
        inflight[fut.key] = (i, fut, data)
        return fut

    first = [f for f in (submit() for _ in range(limit)) if f is not None]
    bar = tqdm(total=n_jobs, desc=desc, unit="tile", disable=not progress)
    try:
        pending = as_completed(first)
        for fut in pending:
            i, _, data = inflight.pop(fut.key)
            result = fut.result()
            fut.release()
            data.release()
            bar.update()
            nxt = submit()
            if nxt is not None:
                pending.add(nxt)
            yield i, result
    finally:
        bar.close()
        for _, fut, data in inflight.values():
            fut.cancel()
            data.release()


def _call(fn, args):
    try:
        return fn(*args)
    finally:
        _tile_done()


def _tiles_needed(shape, tile_px, scheduler):
    """False when the whole image is one tile and no cluster was asked for."""
    return _requested_scheduler(scheduler) is not None or max(shape) > tile_px


# --------------------------------------------------------------------------- dense IC-GN
def _box(lo_xy, hi_xy, margin, shape):
    """Rows/cols (y0, y1, x0, x1) covering [lo, hi] ± margin, clipped to the image, with
    the origin rounded down to a multiple of 16."""
    h, w = shape
    x0 = max(0, int(math.floor(lo_xy[0] - margin)) // _ALIGN_PX * _ALIGN_PX)
    y0 = max(0, int(math.floor(lo_xy[1] - margin)) // _ALIGN_PX * _ALIGN_PX)
    x1 = min(w, int(math.ceil(hi_xy[0] + margin)) + 1)
    y1 = min(h, int(math.ceil(hi_xy[1] + margin)) + 1)
    return y0, y1, x0, x1


def _coef_sum_task(crop, core, smooth_sigma_px):
    from .subset import prefilter_image

    c = prefilter_image(crop, smooth_sigma_px)
    y0, y1, x0, x1 = core
    return float(c[y0:y1, x0:x1].sum())


def _icgn_task(ref_crop, cur_crop, pr, pg, kw):
    from .subset import icgn_refine

    r = icgn_refine(ref_crop, cur_crop, pr, pg, **kw)
    return (r.pts, r.warp, r.zncc, r.converged, r.n_iter, r.sigma_px, r.reason,
            r.residual_ratio, r.noise_ratio)


def _coef_mean(client, img, tiles, smooth_sigma_px, progress):
    """Mean of the whole image's B-spline coefficients, summed over tiles."""
    margin = _SPLINE_MARGIN_PX + 3.0 * float(smooth_sigma_px or 0.0)

    def jobs():
        for i, t in enumerate(tiles):
            y0, y1, x0, x1 = _box((t.x0, t.y0), (t.x1 - 1, t.y1 - 1), margin, img.shape)
            core = (t.y0 - y0, t.y1 - y0, t.x0 - x0, t.x1 - x0)
            yield i, (np.asarray(img[y0:y1, x0:x1], np.float64), core, smooth_sigma_px)

    # fsum: exactly rounded whatever order the tiles finish in, so every run (local or on
    # a cluster) gets the same offset, bit for bit
    total = math.fsum(s for _, s in map_tiles(client, _coef_sum_task, jobs(), len(tiles),
                                              "spline tiles", progress))
    return total / img.size


def tiled_icgn(ref_img, cur_img, pts_ref, pts_guess, *, tile_px=DEFAULT_TILE_PX,
               scheduler=None, progress=False, **icgn_kw):
    """:func:`semlab.subset.icgn_refine` over many points, in overlapping tiles.

    Points are grouped by the core tile holding their reference pixel; each tile's task
    matches them on crops of both images with the halos described in the module docstring.
    The result equals the untiled ``icgn_refine`` (same points, same keywords) to ~1e-12 px
    (tested on a 4-tile grid, also through a loopback cluster).

    Parameters
    ----------
    ref_img, cur_img : (H, W) arrays
        Reference and current grey images (``np.memmap`` works: only crops are read).
    pts_ref, pts_guess : (N, 2) arrays
        Reference points and initial guesses ``(x, y)``, pixels.
    tile_px : int
        Core tile size, pixels (multiple of 16). When both images fit in one tile and no
        scheduler is given (argument or ``SEMLAB_SCHEDULER``), ``icgn_refine`` runs directly.
    scheduler : str, distributed.Client or None
        Where the tiles run (see :func:`dask_client`).
    progress : bool
        tqdm bars over tiles.
    **icgn_kw
        Keywords of ``icgn_refine`` (``half_window``, ``warp``, ``init_warp`` (N, 6),
        ``smooth_sigma_px``, ``subset_offsets``, ``ref_prefiltered``/``cur_prefiltered``
        (whole-image arrays, cropped here), ``max_iter``, ``tol_px``, ``noise_sigma``
        (default: measured as ``icgn_refine`` does, on the whole images and all the points'
        residuals: the tiles run a second time with the lowered noise when the median
        ``noise_ratio`` is below 1), ``coef_offset``).

    Returns
    -------
    semlab.subset.SubsetResult
        In the order of ``pts_ref``.
    """
    from .noise import image_noise_sigma
    from .subset import (OUTSIDE, SubsetResult, _as_image, _as_points, _calibration_factor,
                         _unsolved_outputs, icgn_refine)

    if "progress" in icgn_kw:
        raise SemlabError("give progress= to tiled_icgn itself, not as an icgn_refine keyword")
    ref, cur = np.asarray(ref_img), np.asarray(cur_img)
    if not _tiles_needed(ref.shape, tile_px, scheduler) and max(cur.shape) <= tile_px:
        return icgn_refine(ref_img, cur_img, pts_ref, pts_guess, progress=progress, **icgn_kw)
    _as_image(ref_img, "ref_img")
    _as_image(cur_img, "cur_img")
    pr = _as_points(pts_ref, "pts_ref")
    n = len(pr)
    pg = _as_points(pts_guess, "pts_guess", n)
    kw = dict(icgn_kw)
    h = int(kw.get("half_window", 10))
    smooth = float(kw.get("smooth_sigma_px", 0.0) or 0.0)
    so = kw.get("subset_offsets")
    ext = h if so is None else int(np.abs(np.asarray(so)).max())
    init = kw.pop("init_warp", None)
    if init is not None:
        init = np.broadcast_to(np.asarray(init, np.float64), (n, 6))
    ref_pf = kw.pop("ref_prefiltered", None)
    cur_pf = kw.pop("cur_prefiltered", None)
    margin = _SPLINE_MARGIN_PX + 3.0 * smooth
    calibrate = kw.get("noise_sigma") is None or (isinstance(kw["noise_sigma"], str)
                                                  and kw["noise_sigma"] == "calibrated")
    if calibrate:
        # one noise level per image, measured on the whole image as icgn_refine does, then
        # lowered to what all the tiles' residuals allow (second pass below)
        kw["noise_sigma"] = (image_noise_sigma(ref), image_noise_sigma(cur))

    finite = np.all(np.isfinite(pr), 1) & np.all(np.isfinite(pg), 1)
    X0 = np.where(finite[:, None], np.rint(np.nan_to_num(pr)), np.nan)
    tiles = plan_tiles(ref.shape, tile_px)
    members = [np.flatnonzero(finite & t.contains(X0)) for t in tiles]
    work = [(t, m) for t, m in zip(tiles, members) if len(m)]

    out_pts, out_w, out_z, out_c, out_k, out_s, out_rr, out_r = _unsolved_outputs(n)
    out_r[finite] = OUTSIDE               # finite points in no tile lie outside the image

    plans = []
    for t, m in work:
        x = X0[m]
        rb = _box(x.min(0), x.max(0), ext + margin, ref.shape)
        # reach in the current image: divergence limit h, sub-pixel offset, the subset under
        # the largest admissible warp (|A - I| <= 0.5 per entry, or the initial warp)
        grow = 2.0
        if init is not None:
            g = np.nan_to_num(init[m][:, [1, 2, 4, 5]])
            grow = max(grow, float(np.abs(g[:, :2] + [1, 0]).sum(1).max()),
                       float(np.abs(g[:, 2:] + [0, 1]).sum(1).max()))
        cb = _box(pg[m].min(0), pg[m].max(0), h + 2.0 + grow * (ext + 1) + margin, cur.shape)
        plans.append((m, rb, cb))

    def jobs():
        for i, (m, rb, cb) in enumerate(plans):
            tkw = dict(kw)
            if init is not None:
                tkw["init_warp"] = np.array(init[m])
            if ref_pf is not None:
                tkw["ref_prefiltered"] = np.asarray(ref_pf[rb[0]:rb[1], rb[2]:rb[3]])
            if cur_pf is not None:
                tkw["cur_prefiltered"] = np.asarray(cur_pf[cb[0]:cb[1], cb[2]:cb[3]])
            yield i, (np.asarray(ref[rb[0]:rb[1], rb[2]:rb[3]]),
                      np.asarray(cur[cb[0]:cb[1], cb[2]:cb[3]]),
                      pr[m] - [rb[2], rb[0]], pg[m] - [cb[2], cb[0]], tkw)

    out_q = np.full(n, np.nan)
    with dask_client(scheduler) as client:
        if "coef_offset" not in kw:
            kw["coef_offset"] = (float(np.mean(cur_pf)) if cur_pf is not None else
                                 _coef_mean(client, cur, plan_tiles(cur.shape, tile_px),
                                            smooth, progress))
        for attempt in range(2):
            for i, res in map_tiles(client, _icgn_task, jobs(), len(plans), "IC-GN tiles",
                                    progress):
                m, _, cb = plans[i]
                p, w, z, c, k, s, why, rr, q = res
                out_rr[m] = rr
                out_pts[m] = p + [cb[2], cb[0]]
                out_w[m] = w
                out_z[m], out_c[m], out_k[m], out_s[m], out_r[m] = z, c, k, s, why
                if attempt == 0:
                    out_q[m] = q
            # the default noise measurement of icgn_refine over all the points: the
            # image estimates scaled by the median residual ratio when it is below 1
            f = _calibration_factor(out_q) if calibrate and attempt == 0 else 1.0
            if f >= 1.0:
                break
            kw["noise_sigma"] = tuple(np.asarray(kw["noise_sigma"], float) * np.sqrt(f))
    # the translation part of the warp in whole-image coordinates (as icgn_refine: pts - pts_ref)
    out_w[:, 0] = out_pts[:, 0] - pr[:, 0]
    out_w[:, 3] = out_pts[:, 1] - pr[:, 1]
    reason = out_r.astype(str) if n else np.zeros(0, dtype="<U1")
    noise = kw["noise_sigma"]
    noise = np.full(2, np.nan) if isinstance(noise, str) else \
        np.broadcast_to(np.asarray(noise, np.float64), (2,)).copy()
    return SubsetResult(pts=out_pts, warp=out_w, zncc=out_z, converged=out_c, n_iter=out_k,
                        sigma_px=out_s, reason=reason, residual_ratio=out_rr,
                        noise_sigma=noise, noise_ratio=out_q)


# --------------------------------------------------------------------------- tracking
def _stretch(frame, name):
    """The contrast stretch :func:`semlab.tracking.normalize_frame` applies to a frame:
    ``(lo, hi, blank)`` (its default percentiles)."""
    from .tracking import _BLANK_REL_RANGE, _as_2d, normalize_frame

    a = np.asarray(_as_2d(frame, name), np.float64)
    finite = np.isfinite(a)
    if not finite.any():
        return 0.0, 0.0, True
    sig = inspect.signature(normalize_frame).parameters
    pct = [sig["low_pct"].default, sig["high_pct"].default]
    lo, hi = np.percentile(a[finite] if not finite.all() else a, pct)
    # normalize_frame's blank test, without its full-size stretched copy
    if not np.isfinite(hi - lo) or (hi - lo) <= _BLANK_REL_RANGE * max(abs(lo), abs(hi), 1e-300):
        return 0.0, 0.0, True
    return float(lo), float(hi), False


def _pinned_crop(crop, lo, hi, side, thick):
    """A crop of a frame that :func:`~semlab.tracking.normalize_frame` stretches exactly as
    it stretches the whole frame.

    The crop is clipped to ``[lo, hi]`` (NaN set to ``lo``; the stretch clips there anyway,
    so the stretched values are unchanged) and a strip of ``thick`` rows or columns is
    added on ``side`` (a side away from the image border, outside the tile's reach), half
    at ``lo`` and half at ``hi``: more than 1 % of the pixels at each, so the crop's 0.5 and
    99.5 percentiles are exactly ``lo`` and ``hi``.
    """
    a = np.asarray(crop, np.float64)
    a = np.where(np.isfinite(a), np.clip(a, lo, hi), lo)
    h, w = a.shape
    vertical = side in ("top", "bottom")
    strip = np.empty((thick, w) if vertical else (h, thick))
    half = thick // 2
    if vertical:
        strip[:half], strip[half:] = lo, hi
        return np.vstack([strip, a] if side == "top" else [a, strip])
    strip[:, :half], strip[:, half:] = lo, hi
    return np.hstack([strip, a] if side == "left" else [a, strip])


def _strip_thickness(crop_shape, side):
    h, w = crop_shape
    length = h if side in ("top", "bottom") else w
    # each half >= 1.1 % of all pixels: thick / 2 >= 0.011 (length + thick)
    return _round_up(0.03 * length + 4, _ALIGN_PX)


def _track_task(crops, stretch, seeds, side, thick, kw):
    from .tracking import TrackingWarning, _as_2d, track_reverse

    frames = []
    for k, (a, (lo, hi, blank)) in enumerate(zip(crops, stretch)):
        a = _as_2d(a, f"frame {k}")          # colour to grey, as track_reverse does
        if blank:
            shp = list(np.shape(a)[:2])
            shp[0 if side in ("top", "bottom") else 1] += thick
            frames.append(np.zeros(shp))
        else:
            frames.append(_pinned_crop(a, lo, hi, side, thick))
    with warnings.catch_warnings():
        # the blank-frame and lost-track warnings are about this tile only: the driver
        # re-issues them for the whole series
        warnings.simplefilter("ignore", TrackingWarning)
        try:
            t = track_reverse(frames, seeds, progress=False, **kw)
        except TrackingError as exc:
            if "every track was lost" not in str(exc):
                raise
            return None
    return t.xy, t.fb_error_px, t.valid, t.zncc, t.sigma_px, t.gap_frames, t.method, t.params


def _tracking_reach_px(kw, max_motion_px):
    """How far from a seed tracking reads the frames, pixels."""
    win = int(kw.get("win_size", 21))
    level = int(kw.get("max_level", 3))
    hw = kw.get("subset_half_window") or win // 2
    # the LK window at the coarsest pyramid level, with the pyramid and derivative filters
    lk = (2 ** level) * (win // 2 + 3)
    return float(max_motion_px) + max(lk, 2 * int(hw) + 2 + _SPLINE_MARGIN_PX)


def tiled_track_reverse(frames, seeds, *, tile_px=DEFAULT_TILE_PX, max_motion_px=64.0,
                        halo_px=None, scheduler=None, progress=True, **track_kw):
    """:func:`semlab.tracking.track_reverse` in tiles of seeds, on a dask cluster.

    Each tile tracks the seeds of its core and, as helpers, those within ``halo_px`` of the
    core (their results are discarded: they give the core tracks the neighbours the
    normalised median test sees in the untiled run), on crops of every frame that extend
    ``halo_px`` + the reach beyond the core. Crops carry the whole frame's contrast stretch
    and start at multiples of 16 px (so of 2^max_level for max_level <= 4), hence the LK
    pyramids and the stretched values are the untiled ones. Result (tested): the valid
    flags and gaps of the untiled run; positions within the float32 rounding of OpenCV's LK
    (``method="lk"``: ~1e-4 px, under its 1e-3 px stopping tolerance, because a tile's
    coordinates are smaller numbers) or of the IC-GN spline table (``method="subset"``:
    ~1e-7 px; tracking's IC-GN rounds the table relative to the tile's level, see
    :func:`tiled_icgn`). With ``method="subset"`` the predicted ``sigma_px`` is 0-9 %
    lower than untiled (median 7 % on the test series): ``track_reverse`` has its IC-GN
    measure the image noise per call, here on the tile's crop and its pinning strip (whose
    flat pixels lower the median noise response); a validity decision at ``max_sigma_px``
    can then differ. LK's ``sigma_px`` is unaffected (equal to 4e-4 relative).
    A track's neighbours influence it through the median test only:
    a difference at the helper band's outer edge would have to travel ``halo_px`` through
    neighbour after neighbour to reach the core.

    Parameters
    ----------
    frames : sequence of F (H, W) arrays, chronological (frame 0 = earliest)
        ``np.memmap`` or tifffile-memmapped frames are read tile by tile.
    seeds : (N, 2) array of (x, y) pixels in the last frame
    tile_px : int
        Core tile size, pixels (multiple of 16). When the frames fit in one tile and no
        scheduler is given, ``track_reverse`` runs directly.
    max_motion_px : float
        Largest distance between a point's position in the last frame and in any frame,
        pixels (motion plus drift). Tracks that move further may differ from the untiled run.
    halo_px : float, optional
        Width of the helper-seed band, pixels (default 64: several rings of neighbours at
        the usual seed spacing of 7-20 px).
    scheduler : str, distributed.Client or None
        Where the tiles run (see :func:`dask_client`).
    progress : bool
        tqdm bars over frames (contrast) and tiles.
    **track_kw
        Keywords of ``track_reverse`` (``method``, ``win_size``, ``max_level``, ...,
        ``seed_kind``). With ``register`` the frames' transforms are estimated once on the
        whole frames (:func:`semlab.registration.as_registration`), handed to every tile
        in its own pixels, and each crop is widened by the drift of its corners.

    Returns
    -------
    semlab.tracking.Tracks

    Raises
    ------
    TrackingError
        As ``track_reverse``: too few frames, a blank last frame, every track lost.
    """
    from tqdm.auto import tqdm

    from .tracking import Tracks, _check_track_loss, _seed_kinds, track_reverse

    kw = dict(track_kw)
    kw.pop("progress", None)
    frames = list(frames) if not (isinstance(frames, np.ndarray) and frames.ndim == 3) \
        else [frames[k] for k in range(len(frames))]
    if len(frames) < 2:
        return track_reverse(frames, seeds, progress=progress, **kw)  # its own error
    shape = np.shape(frames[-1])[:2]
    if not _tiles_needed(shape, tile_px, scheduler):
        return track_reverse(frames, seeds, progress=progress, **kw)
    seeds = np.asarray(seeds, np.float64)
    level = int(kw.get("max_level", 3))
    if level > 4:
        raise SemlabError(f"tiled tracking aligns tiles to 16 px: max_level <= 4, got {level}")
    n = len(seeds) if seeds.ndim == 2 else 0
    kind = kw.pop("seed_kind", None)
    kinds = _seed_kinds(kind, n)
    F = len(frames)
    it = range(F)
    if progress:
        it = tqdm(it, desc="frame contrast", unit="frame")
    stretch = [_stretch(frames[k], f"frame {k}") for k in it]
    if stretch[-1][2] or n == 0 or not np.isfinite(seeds).all() or len(kinds) != n:
        # the untiled run raises the right error (blank reference, no or bad seeds)
        return track_reverse(frames, seeds, progress=progress, seed_kind=kind, **kw)
    for k, f in enumerate(frames):
        if np.shape(f)[:2] != shape:
            return track_reverse(frames, seeds, progress=progress, seed_kind=kind, **kw)

    reg = None
    if kw.get("register") is not None:
        # the frames' global transforms, estimated once on the whole frames; each tile gets
        # them in its own coordinates, and its crop also covers the drift
        from .registration import as_registration

        reg = as_registration(kw["register"], frames)
    reach = _tracking_reach_px(kw, max_motion_px)
    halo = _round_up(64 if halo_px is None else halo_px, _ALIGN_PX)
    H, W = shape
    plans = []
    for t in plan_tiles(shape, tile_px):
        core = t.contains(seeds)
        if not core.any():
            continue
        r = reach
        if reg is not None:
            c = np.array([[t.x0 - halo, t.y0 - halo], [t.x1 + halo, t.y0 - halo],
                          [t.x0 - halo, t.y1 + halo], [t.x1 + halo, t.y1 + halo]], float)
            r += max(float(np.abs(T(c) - c).max()) for T in reg.transforms)
        r = _round_up(r, _ALIGN_PX)
        y0, y1 = max(0, t.y0 - halo - r), min(H, t.y1 + halo + r)
        x0, x1 = max(0, t.x0 - halo - r), min(W, t.x1 + halo + r)
        with np.errstate(invalid="ignore"):
            helper = ((seeds[:, 0] >= t.x0 - halo) & (seeds[:, 0] < t.x1 + halo)
                      & (seeds[:, 1] >= t.y0 - halo) & (seeds[:, 1] < t.y1 + halo))
        members = np.flatnonzero(helper | core)
        free = [s for s, inner in (("bottom", y1 < H), ("top", y0 > 0), ("right", x1 < W),
                                   ("left", x0 > 0)) if inner]
        if not free:      # the crop is the whole frame: no stretch pinning needed
            side, thick = "bottom", 0
        else:
            side = free[0]
            thick = _strip_thickness((y1 - y0, x1 - x0), side)
        plans.append((members, core[members], (y0, y1, x0, x1), side, thick))

    def jobs():
        for i, (m, _, (y0, y1, x0, x1), side, thick) in enumerate(plans):
            crops = [np.asarray(f[y0:y1, x0:x1]) for f in frames]
            shift = np.array([x0 - (thick if side == "left" else 0),
                              y0 - (thick if side == "top" else 0)], float)
            tkw = kw if reg is None else dict(kw, register=_local_registration(
                reg, shift, (y1 - y0 + (thick if side in ("top", "bottom") else 0),
                             x1 - x0 + (thick if side in ("left", "right") else 0))))
            yield i, (crops, stretch, seeds[m] - shift, side, thick, tkw)

    xy = np.full((F, n, 2), np.nan)
    fb = np.full((F, n), np.nan)
    valid = np.zeros((F, n), bool)
    zn = np.full((F, n), np.nan)
    sig = np.full((F, n), np.nan)
    gap = np.zeros((F, n), int)
    ref = F - 1
    xy[ref], fb[ref], valid[ref], zn[ref], sig[ref] = seeds, 0.0, True, 1.0, 0.0
    method, params = kw.get("method", "lk"), {}
    with dask_client(scheduler) as client:
        for i, res in map_tiles(client, _track_task, jobs(), len(plans), "tracking tiles",
                                progress):
            m, core, (y0, _, x0, _), side, thick = plans[i]
            if res is None:
                continue              # every track of the tile lost: they stay invalid
            txy, tfb, tv, tz, ts, tg, method, params = res
            idx = m[core]
            shift = np.array([x0 - (thick if side == "left" else 0),
                              y0 - (thick if side == "top" else 0)], float)
            xy[:, idx] = txy[:, core] + shift
            fb[:, idx], valid[:, idx], zn[:, idx] = tfb[:, core], tv[:, core], tz[:, core]
            sig[:, idx], gap[:, idx] = ts[:, core], tg[:, core]
    _check_track_loss(valid, [k for k in range(ref) if stretch[k][2]])
    return Tracks(xy=xy, fb_error_px=fb, valid=valid, zncc=zn, sigma_px=sig, gap_frames=gap,
                  seed_kind=kinds, reference_frame=ref, method=method, params=params,
                  registration=reg)


def _local_registration(reg, origin, shape):
    """``reg`` in the pixels of a crop whose pixel (0, 0) is ``origin`` (x, y) of the frame."""
    from .transform2d import Transform2D

    S = Transform2D(np.array([[1.0, 0.0, origin[0]], [0.0, 1.0, origin[1]], [0.0, 0.0, 1.0]]))
    return replace(reg, transforms=[S.inverse() @ T @ S for T in reg.transforms],
                   shape=tuple(shape))


# --------------------------------------------------------------------------- dense map
def __getattr__(name):
    # the tiled dense map lives with the run's other tiled stereo steps
    # (semlab.tiled_stereo, which imports this module)
    if name in ("tiled_dense_parallax", "map_roi_tiles"):
        from . import tiled_stereo

        return getattr(tiled_stereo, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
