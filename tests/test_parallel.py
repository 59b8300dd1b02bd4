"""Tiles on dask.distributed: tiled dense IC-GN and tracking equal the untiled runs, also on
a cluster started on loopback inside the test; the scheduler argument of the API and CLI."""

import sys

import numpy as np
import pytest
from scipy import ndimage

from semlab import parallel
from semlab.errors import SemlabError
from semlab.subset import icgn_refine
from semlab.tracking import normalize_frame, shi_tomasi_seeds, track_reverse


def _pair(h=300, w=420, seed=0):
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.normal(size=(h + 40, w + 40)), 2.0) * 50 + 100
    ref = img[20:20 + h, 20:20 + w]
    # a smooth parallax: 1.3 px in x, -0.7 px in y, plus a slow wave
    yy, xx = np.mgrid[0:h + 40, 0:w + 40].astype(float)
    cur = ndimage.map_coordinates(img, [yy - 0.7 + 0.3 * np.sin(xx / 50), xx + 1.3], order=3,
                                  mode="mirror")[20:20 + h, 20:20 + w]
    cur = cur + rng.normal(0, 0.5, cur.shape)
    xs, ys = np.arange(5, w - 5, 7.0), np.arange(5, h - 5, 7.0)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    guess = pts + [1.3, -0.7] + rng.normal(0, 0.3, pts.shape)
    pts[3] = np.nan                                        # a NaN input point
    return ref, cur, pts, guess


def _series(h=256, w=352, n_frames=4, seed=0, drift_px=(0.0, 0.0)):
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.normal(size=(h, w)), 1.5)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    frames = []
    for k in range(n_frames):
        a = (n_frames - 1 - k) / (n_frames - 1)           # motion grows towards the end
        # material motion, plus a stage drift growing towards the early frames
        ux = a * (3.0 * np.sin(yy / 90.0) + 0.01 * xx) + (n_frames - 1 - k) * drift_px[0]
        uy = a * 2.0 * np.cos(xx / 70.0) + (n_frames - 1 - k) * drift_px[1]
        im = ndimage.map_coordinates(base, [yy + uy, xx + ux], order=3, mode="mirror")
        # brightness and contrast drift between frames, and noise
        frames.append((im * (0.6 + 0.1 * k) + 0.05 * k) * 100 + rng.normal(0, 2, (h, w)) + 1000)
    return frames


def _assert_same_subsets(a, b, pos_tol):
    assert np.array_equal(a.converged, b.converged)
    assert np.array_equal(a.reason, b.reason)
    assert np.array_equal(a.n_iter, b.n_iter)
    ok = a.converged
    d = np.abs(a.pts[ok] - b.pts[ok]).max(axis=1)
    assert d.max() <= pos_tol
    assert np.abs(a.warp[ok] - b.warp[ok]).max() <= pos_tol
    assert np.abs(a.zncc - b.zncc).max() <= 1e-9
    assert np.abs(a.sigma_px[ok] - b.sigma_px[ok]).max() <= 1e-9
    assert np.abs(a.residual_ratio[ok] - b.residual_ratio[ok]).max() <= 1e-6
    # the default noise is calibrated on the median residual ratio of all the subsets,
    # which the tiles reproduce to their float32 rounding (~1e-8 relative)
    assert np.allclose(a.noise_sigma, b.noise_sigma, rtol=1e-7, atol=0)
    ok_q = np.isfinite(a.noise_ratio)
    assert np.array_equal(ok_q, np.isfinite(b.noise_ratio))
    assert np.allclose(a.noise_ratio[ok_q], b.noise_ratio[ok_q], rtol=1e-6)
    assert np.isnan(b.pts[~ok]).all()
    return d


# ------------------------------------------------------------------------------ tiles
def test_plan_tiles_cover_the_image_once():
    tiles = parallel.plan_tiles((300, 420), 128)
    assert len(tiles) == 3 * 4
    cover = np.zeros((300, 420), int)
    for t in tiles:
        cover[t.y0:t.y1, t.x0:t.x1] += 1
    assert (cover == 1).all()
    for bad in (100, 32, 128.5, True):
        with pytest.raises(SemlabError, match="tile_px"):
            parallel.plan_tiles((300, 420), bad)


@pytest.mark.parametrize("smooth", [0.0, 0.8])
def test_tiled_icgn_equals_untiled(smooth):
    ref, cur, pts, guess = _pair()
    init = np.zeros((len(pts), 6))
    init[:, 1] = 0.01
    a = icgn_refine(ref, cur, pts, guess, half_window=10, smooth_sigma_px=smooth,
                    init_warp=init)
    import dask
    import distributed  # noqa: F401  (its config keys exist before config.set saves them)

    # the tiles' crops are scattered to the workers, never sent inside the task graph:
    # distributed warns about graphs above this threshold (10 MB by default), and under
    # -W error that warning would fail here
    with dask.config.set({"distributed.admin.large-graph-warning-threshold": "64kB"}):
        b = parallel.tiled_icgn(ref, cur, pts, guess, half_window=10, smooth_sigma_px=smooth,
                                init_warp=init, tile_px=128)       # 3 × 4 tiles
    assert a.converged.sum() > 0.9 * len(pts)
    assert {"subset leaves the image", "NaN input point"} <= set(a.reason)
    d = _assert_same_subsets(a, b, 2e-8)
    # the float32 spline samples of a tile see coordinates 2-8x smaller, rounded differently:
    # a few subsets differ by up to ~1e-8 px, the others by ~1e-13 px
    assert np.median(d) <= 1e-12


def test_tiled_icgn_single_tile_is_icgn_refine(monkeypatch):
    monkeypatch.delenv(parallel.SCHEDULER_ENV, raising=False)
    ref, cur, pts, guess = _pair(h=120, w=160)
    a = icgn_refine(ref, cur, pts, guess)
    b = parallel.tiled_icgn(ref, cur, pts, guess, tile_px=1024)
    assert np.array_equal(a.pts, b.pts, equal_nan=True)


def test_pinned_crop_keeps_the_frame_stretch():
    f = _series(n_frames=2)[0]
    f[10, 10] = np.nan
    full, _ = normalize_frame(f)
    lo, hi, blank = parallel._stretch(f, "frame 0")
    assert not blank and lo < hi
    for flat in (np.full((64, 64), 7.0), np.full((64, 64), np.nan)):       # as normalize_frame
        assert parallel._stretch(flat, "flat")[2] and normalize_frame(flat)[1]
    y0, y1, x0, x1 = 32, 200, 48, 300            # a crop with another intensity histogram
    for side in ("top", "bottom", "left", "right"):
        thick = parallel._strip_thickness((y1 - y0, x1 - x0), side)
        c, _ = normalize_frame(parallel._pinned_crop(f[y0:y1, x0:x1], lo, hi, side, thick))
        c = {"top": c[thick:], "bottom": c[:-thick], "left": c[:, thick:],
             "right": c[:, :-thick]}[side]
        assert np.array_equal(c, full[y0:y1, x0:x1])


@pytest.mark.parametrize("method,pos_tol,median_tol", [("lk", 2e-3, 1e-4),
                                                       ("subset", 5e-5, 1e-7)])
def test_tiled_tracking_equals_untiled(method, pos_tol, median_tol):
    frames = _series()
    seeds = shi_tomasi_seeds(frames[-1], quality=0.05, max_corners=600)
    a = track_reverse(frames, seeds, method=method, progress=False)
    b = parallel.tiled_track_reverse(frames, seeds, method=method, tile_px=128,
                                     max_motion_px=8, halo_px=48, progress=False)
    assert a.valid[:-1].mean() > 0.8
    assert np.array_equal(a.valid, b.valid)
    assert np.array_equal(a.gap_frames, b.gap_frames)
    assert np.array_equal(np.isnan(a.xy), np.isnan(b.xy))
    # LK positions are those of its IC-GN agreement check (measured 2026-12-01: max 2.3e-4,
    # median 1.5e-8 px; the bound keeps OpenCV LK's own 1e-3 px stopping tolerance);
    # IC-GN subsets: the spline table rounded relative to the tile's own level (measured:
    # max 2e-5, median 1.6e-8 px)
    d = np.abs(a.xy - b.xy).max(axis=2)[:-1]
    assert np.nanmax(d) <= pos_tol and np.nanmedian(d) <= median_tol
    assert np.nanmax(np.abs(a.zncc - b.zncc)) <= 1e-3
    assert b.params == a.params and b.method == a.method
    if method == "lk":
        # LK's predicted sigma comes from the ZNCC and the reference window: the same
        v = a.valid[:-1]
        assert np.allclose(b.sigma_px[:-1][v], a.sigma_px[:-1][v], rtol=1e-3, atol=0)


def test_tiled_dense_parallax_is_the_per_tile_call():
    from semlab.heightmap import dense_parallax

    ref, cur, _, _ = _pair(h=96, w=128)
    tiled = parallel.tiled_dense_parallax(ref, cur, tile_px=64, progress=False)   # 2 × 2
    per_tile = np.full(tiled.x1_px.shape, np.nan)
    for t in parallel.plan_tiles(ref.shape, 64):          # the same windows on whole images
        d = dense_parallax(ref, cur, roi=(t.x0, t.y0, t.x1, t.y1))
        per_tile[t.y0:t.y1, t.x0:t.x1] = d.x1_px
    assert tiled.valid.mean() > 0.8
    # measured: 3e-14 px (the crop offset added back to each position)
    assert np.nanmax(np.abs(per_tile - tiled.x1_px)) <= 1e-12
    assert np.array_equal(np.isnan(per_tile), np.isnan(tiled.x1_px))
    # against one call on the whole pair: the window's own flow guess, IC-GN tol 1e-3 px
    # (measured on 160x200: same valid mask, median 8e-5 px, max 5e-3 px)
    whole = dense_parallax(ref, cur)
    both = whole.valid & tiled.valid
    assert both.sum() >= 0.97 * whole.valid.sum()
    d = np.abs(whole.x1_px - tiled.x1_px)[both]
    assert np.median(d) <= 1e-3 and d.max() <= 0.05


def test_tiled_tracking_with_registration_equals_untiled():
    from semlab.registration import register_frames

    frames = _series(drift_px=(6.0, -4.0))               # 18 / -12 px of drift at frame 0
    seeds = shi_tomasi_seeds(frames[-1], quality=0.05, max_corners=600, border_px=40)
    reg = register_frames(frames, model="translation")
    a = track_reverse(frames, seeds, register=reg, progress=False)
    b = parallel.tiled_track_reverse(frames, seeds, register="translation", tile_px=128,
                                     max_motion_px=8, halo_px=48, progress=False)
    assert a.valid[:-1].mean() > 0.8
    # the registration estimated once on the whole frames, the same transforms
    for ta, tb in zip(a.registration.transforms, b.registration.transforms):
        assert np.allclose(ta.matrix, tb.matrix, atol=1e-9)
    assert np.array_equal(a.valid, b.valid)
    d = np.abs(a.xy - b.xy).max(axis=2)[:-1]
    assert np.nanmax(d) <= 2e-3 and np.nanmedian(d) <= 1e-4


# ------------------------------------------------------------------------------ cluster
@pytest.fixture(scope="module")
def loopback_cluster():
    """A dask.distributed cluster on 127.0.0.1: a scheduler and two worker processes.

    No warning filter is needed under -W error: every server (the scheduler's and the
    workers' HTTP servers too) is bound to 127.0.0.1 port 0. With the defaults the scheduler
    binds 0.0.0.0:8787 and, when another cluster on the machine holds that port, warns
    "Port 8787 is already in use" (a UserWarning), which would fail the test.
    """
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address="127.0.0.1:0",
                      worker_dashboard_address="127.0.0.1:0") as cluster:
        yield cluster.scheduler_address


def test_cluster_runs_equal_the_local_run(loopback_cluster, monkeypatch, capsys):
    monkeypatch.delenv(parallel.SCHEDULER_ENV, raising=False)
    assert loopback_cluster.startswith("tcp://127.0.0.1:")
    ref, cur, pts, guess = _pair()
    local = parallel.tiled_icgn(ref, cur, pts, guess, tile_px=128)
    remote = parallel.tiled_icgn(ref, cur, pts, guess, tile_px=128, scheduler=loopback_cluster,
                                 progress=True)
    # the same tiles computed in other processes: the same numbers, bit for bit
    for f in ("pts", "warp", "zncc", "sigma_px"):
        assert np.array_equal(getattr(local, f), getattr(remote, f), equal_nan=True)
    assert np.array_equal(local.reason, remote.reason)
    _assert_same_subsets(icgn_refine(ref, cur, pts, guess), remote, 2e-8)
    assert "IC-GN tiles" in capsys.readouterr().err          # the progress bar

    frames = _series(n_frames=3)
    seeds = shi_tomasi_seeds(frames[-1], quality=0.05, max_corners=300)
    kw = dict(tile_px=128, max_motion_px=8, halo_px=48)
    t_local = parallel.tiled_track_reverse(frames, seeds, progress=False, **kw)
    # the address through the environment, as `semlab run --scheduler` passes it on
    parallel.set_default_scheduler(loopback_cluster)
    t_remote = parallel.tiled_track_reverse(frames, seeds, progress=True, **kw)
    assert "tracking tiles" in capsys.readouterr().err
    assert np.array_equal(t_local.xy, t_remote.xy, equal_nan=True)
    assert np.array_equal(t_local.valid, t_remote.valid)
    # with a cluster asked for, even a one-tile image goes there (and gives the same result)
    small = parallel.tiled_icgn(ref[:100, :100], cur[:100, :100], pts[:20], guess[:20])
    assert np.array_equal(small.pts, icgn_refine(ref[:100, :100], cur[:100, :100], pts[:20],
                                                 guess[:20]).pts, equal_nan=True)
    parallel.set_default_scheduler("")
    import os

    assert parallel.SCHEDULER_ENV not in os.environ


def test_bad_scheduler_addresses(monkeypatch):
    monkeypatch.delenv(parallel.SCHEDULER_ENV, raising=False)
    with pytest.raises(SemlabError, match="tcp://HOST:PORT"):
        parallel.set_default_scheduler("127.0.0.1:8786")
    monkeypatch.setattr(parallel, "_CONNECT_TIMEOUT", "1s")
    with pytest.raises(SemlabError, match="no dask scheduler answers at tcp://127.0.0.1:9"):
        parallel.set_default_scheduler("tcp://127.0.0.1:9")
    import os

    assert parallel.SCHEDULER_ENV not in os.environ


def test_cli_run_takes_a_scheduler(monkeypatch, tmp_path, capsys):
    from semlab.cli import build_parser, main

    monkeypatch.delenv(parallel.SCHEDULER_ENV, raising=False)
    args = build_parser().parse_args(["run", "exp", "--out", "o", "--scheduler", "tcp://h:1"])
    assert args.scheduler == "tcp://h:1"
    assert build_parser().parse_args(["run", "exp", "--out", "o"]).scheduler == ""
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"),
                 "--scheduler", "nonsense"]) == 2
    assert "tcp://HOST:PORT" in capsys.readouterr().err


def test_an_analysis_scheduler_applies_to_that_analysis_only(loopback_cluster, monkeypatch,
                                                             small_experiment, tmp_path):
    import os

    import semlab

    monkeypatch.delenv(parallel.SCHEDULER_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))   # the probe's cache entry goes there
    a = semlab.Analysis(small_experiment, scheduler=loopback_cluster, progress=False)
    assert parallel.SCHEDULER_ENV not in os.environ     # the process default is untouched
    seen = []
    a._cached("probe", {}, lambda: seen.append(os.environ.get(parallel.SCHEDULER_ENV)))
    assert seen == [loopback_cluster]                   # ... but its steps run on its cluster
    assert parallel.SCHEDULER_ENV not in os.environ
    monkeypatch.setenv(parallel.SCHEDULER_ENV, "tcp://127.0.0.1:1")
    with parallel.scheduler_scope(loopback_cluster):
        assert os.environ[parallel.SCHEDULER_ENV] == loopback_cluster
    assert os.environ[parallel.SCHEDULER_ENV] == "tcp://127.0.0.1:1"   # restored


def test_limit_heap_growth_takes_effect_with_glibc():
    import platform

    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert parallel.limit_heap_growth() is glibc


_TRIM_SCRIPT = """
import sys, os, numpy as np
from semlab import parallel
rss = lambda: int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
assert parallel.limit_heap_growth()
parallel._TRIM_AFTER_TILE[0] = sys.argv[1] == "trim"
keep = []
def tile(k):
    work = [np.ones(1 << 17) for _ in range(200)]   # 200 arrays of 1 MB, under the threshold
    keep.append(np.ones(1 << 18))                   # a 2 MB result allocated after them
    return len(work)
before = rss()
for _ in parallel.map_tiles(None, tile, ((i, (i,)) for i in range(3)), 3, progress=False):
    pass
print((rss() - before) / 1e6)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_tiles_give_their_freed_work_arrays_back():
    """After limit_heap_growth each tile's freed arrays below the mmap threshold go back to
    the system (malloc_trim), even under a result allocated after them; without the trim
    the process keeps them (~200 MB here). Each case in its own process."""
    import platform
    import subprocess

    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc")
    grown = {}
    for case in ("trim", "none"):
        out = subprocess.run([sys.executable, "-c", _TRIM_SCRIPT, case], capture_output=True,
                             text=True, check=True)
        grown[case] = float(out.stdout.split()[-1])
    assert grown["trim"] < 40 and grown["none"] > 150, grown
