"""Peak memory of dense matching and tracking on a 3072×4096 pair, tiled and untiled.

Each case runs in a fresh Python process (so its peak is its own); the peak is the largest
resident set of the process plus its children (worker processes), sampled every 50 ms with
psutil, and the kernel's ``ru_maxrss`` of the process. Target (issue #9): <= 3 GB for a
3072×4096 pair.

Cases:

- ``icgn_tiled``: :func:`semlab.parallel.tiled_icgn` (1024 px tiles, the default local
  cluster: threads, all cores) of a grid of subsets (``--spacing``) from view 0 into view 1;
- ``icgn_untiled``: the same points with one :func:`semlab.subset.icgn_refine` call;
- ``track_tiled`` / ``track_untiled``: :func:`semlab.parallel.tiled_track_reverse` /
  :func:`semlab.tracking.track_reverse` (LK) of Shi–Tomasi seeds over ``--frames`` frames;
- ``dense_tiled``: :func:`semlab.parallel.tiled_dense_parallax` (a subset at every pixel,
  256 px tiles) over a central ``--dense-roi`` square of the pair (the whole 12.6 Mpx map
  takes too long for a benchmark; a tile's memory does not depend on the image size).

- ``match_tiled`` / ``match_untiled``: :func:`semlab.tiled_stereo.tiled_auto_match` /
  :func:`semlab.matching.auto_match` (defaults: 8 px grid) of the ``--run`` experiment's
  two views (read as uint16);
- ``--run``: a synthetic 3072×4096 experiment (±5° pair of a slip-banded surface, written
  as 16-bit TIFFs by :func:`write_experiment`) through ``semlab run --only 04`` (the stereo
  step, automatic matching in tiles, and the heightmap step, tiled, over ``--map-roi``; the
  notebook 04 kernel included). The peak is that of the ``semlab`` process plus all its
  children (notebook kernel), sampled every 0.2 s; the process alone and its children alone
  (the kernel) are also reported.

The images: band-limited random texture (Gaussian-filtered white noise, σ 1.5 px), view 1
rendered with a smooth parallax field of ±4 px, the frames with a displacement growing to
3 px, plus noise. Run::

    python benchmarks/memory_large.py                 # all four cases, ~5-10 min on 2 cores
    python benchmarks/memory_large.py --cases icgn_tiled --size 1536x2048
    python benchmarks/memory_large.py --run --map-roi 512       # semlab run, ~15 min on 2 cores
    python benchmarks/memory_large.py --run --map-roi 0         # the whole 12.6 Mpx map, ~25 min
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CASES = ("icgn_tiled", "icgn_untiled", "track_tiled", "track_untiled", "dense_tiled",
         "match_tiled", "match_untiled")


def texture(shape, seed):
    import cv2

    rng = np.random.default_rng(seed)
    a = rng.standard_normal(shape, dtype=np.float32)
    return cv2.GaussianBlur(a, (0, 0), 1.5) * 40.0 + 128.0


def warped(img, ux, uy, noise, seed):
    import cv2

    h, w = img.shape
    xx = np.ascontiguousarray(np.broadcast_to(np.arange(w, dtype=np.float32)[None, :] + ux, (h, w)))
    yy = np.ascontiguousarray(np.broadcast_to(np.arange(h, dtype=np.float32)[:, None] + uy, (h, w)))
    out = cv2.remap(img, xx, yy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return out + np.random.default_rng(seed).normal(0, noise, img.shape).astype(np.float32)


def parallax(shape, amp_px):
    h, w = shape
    y = np.arange(h, dtype=np.float32)[:, None]
    x = np.arange(w, dtype=np.float32)[None, :]
    return (amp_px * np.sin(x / 300.0) * np.cos(y / 400.0)).astype(np.float32)


class PeakSampler:
    """Largest RSS of this process plus its children, sampled in a thread."""

    def __init__(self, period_s=0.05):
        import psutil

        self.proc = psutil.Process()
        self.peak = 0
        self.period = period_s
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _rss(self):
        total = self.proc.memory_info().rss
        for c in self.proc.children(recursive=True):
            try:
                total += c.memory_info().rss
            except Exception:          # a worker that just exited
                pass
        return total

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(self.period)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self._rss())


def surface_um(shape, pixel_size_um):
    """Height field (µm) on the view-0 grid: three slip-band ribbons with 0.1-0.3 µm steps
    (tanh edges 0.1 µm wide) on a slow ±0.2 µm undulation."""
    h, w = shape
    y = np.arange(h, dtype=np.float32)[:, None] * pixel_size_um
    x = np.arange(w, dtype=np.float32)[None, :] * pixel_size_um
    z = 0.2 * np.sin(x / 25.0) * np.cos(y / 30.0)
    n = x * np.float32(0.5) + y * np.float32(0.866)
    for c, wid, a in ((30.0, 6.0, 0.3), (60.0, 4.0, -0.15), (85.0, 8.0, 0.2)):
        z = z + a * 0.5 * (np.tanh((n - c + wid / 2) / 0.1) - np.tanh((n - c - wid / 2) / 0.1))
    return z.astype(np.float32)


def write_experiment(folder, size=(3072, 4096), pixel_size_um=0.03, tilts=(-5.0, 5.0)):
    """A synthetic ±5° stereo experiment of ``size`` (H, W) pixels in ``folder``.

    View ``k`` at tilt θ shows at pixel ``u`` the texture at
    ``x = cx + (u - cx) / cos θ - z sin θ / (s cos θ)`` (first order in the height),
    so the parallax is ``2 z sin 5° / s`` (±3 px here); 16-bit, Gaussian noise 1 % of the
    texture's contrast.
    """
    import cv2
    import tifffile

    folder = Path(folder)
    (folder / "end_state").mkdir(parents=True, exist_ok=True)
    h, w = size
    base = texture((h, w), 0)
    z = surface_um((h, w), pixel_size_um)
    cx = (w - 1) / 2.0
    names = []
    for k, t in enumerate(tilts):
        th = np.deg2rad(t)
        u = np.arange(w, dtype=np.float32)[None, :]
        xs = cx + (u - cx) / np.cos(th) - z * np.float32(np.sin(th) / (pixel_size_um * np.cos(th)))
        ys = np.ascontiguousarray(np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w)))
        img = cv2.remap(base, xs.astype(np.float32), ys, cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REFLECT)
        img = img + np.random.default_rng(5 + k).normal(0, 0.4, img.shape).astype(np.float32)
        name = f"end_state/view_{k}.tif"
        tifffile.imwrite(folder / name, np.clip(img * 200.0, 0, 65535).astype(np.uint16))
        names.append(name)
        del xs, img
    (folder / "experiment.toml").write_text(
        f'name = "memory_large {h}x{w}"\npixel_size_um = {pixel_size_um}\n\n[stereo]\n'
        f'views = {names!r}\ntilt_deg = {list(tilts)!r}\n'.replace("'", '"'))
    return folder


def run_semlab(size, map_roi, keep=None):
    """``semlab run --only 04`` on a synthetic experiment; the peak RSS of its processes."""
    import shutil
    import tempfile

    import psutil

    tmp = Path(tempfile.mkdtemp(prefix="semlab_memory_run_"))
    try:
        h, w = size
        t0 = time.perf_counter()
        exp = write_experiment(tmp / "exp", size)
        t_write = time.perf_counter() - t0
        c = int(map_roi)
        semlab = Path(sys.executable).with_name("semlab")
        cmd = [str(semlab), "run", str(exp), "--out", str(tmp / "out"), "--only", "04",
               "--set", "n_boot=0"]
        roi = [0, 0, w, h]   # map_roi 0: the whole view-0 grid
        if c > 0:
            x0, y0 = (w - c) // 2 // 16 * 16, (h - c) // 2 // 16 * 16
            roi = [x0, y0, x0 + c, y0 + c]
            cmd += ["--set", f"heightmap_roi={roi}"]
        t0 = time.perf_counter()
        proc = psutil.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        log = []
        reader = threading.Thread(target=lambda: log.extend(proc.stdout), daemon=True)
        reader.start()
        peak_all = peak_own = peak_children = 0
        while proc.poll() is None:
            try:
                own = proc.memory_info().rss
                children = sum(_rss(ch) for ch in proc.children(recursive=True))
            except psutil.NoSuchProcess:
                break
            peak_own, peak_all = max(peak_own, own), max(peak_all, own + children)
            peak_children = max(peak_children, children)
            time.sleep(0.2)
        proc.wait()
        reader.join(5)
        seconds = time.perf_counter() - t0
        if proc.returncode:
            print("".join(log[-60:]), file=sys.stderr)
            raise SystemExit(f"semlab run failed ({proc.returncode})")
        import json as _json

        import tifffile

        out = tmp / "out"
        z = tifffile.imread(out / "heightmap.tif")
        cal = _json.loads((out / "calibration.json").read_text())
        pts = np.loadtxt(out / "points3d.csv", delimiter=",", skiprows=1, usecols=0, ndmin=1)
        # heights against the surface: the map is above the points' reference plane, so
        # compare after removing the best plane (the reference is a fit)
        zt = surface_um((h, w), 0.03)[roi[1]:roi[3], roi[0]:roi[2]]
        ok = np.isfinite(z)
        yy, xx = np.nonzero(ok)
        A = np.column_stack([xx, yy, np.ones(len(xx))]).astype(float)
        d = (z[ok] - zt[ok]).astype(float)
        coef, *_ = np.linalg.lstsq(A, d, rcond=None)
        rmse_nm = float(np.sqrt(np.mean((d - A @ coef) ** 2)) * 1e3)
        steps, step_peaks = {}, {}
        for line in (out / ".semlab" / "steps.jsonl").read_text().splitlines():
            e = _json.loads(line)
            if e.get("event") == "computed":
                steps[e["step"]] = round(float(e["seconds"]), 1)
                step_peaks[e["step"]] = e.get("peak_rss_gb")
        info = {"case": "semlab_run", "size": f"{h}x{w}, " + (f"map {c}x{c} ROI" if c > 0 else "whole map"),
                "stereo_s": steps.get("stereo"), "heightmap_s": steps.get("heightmap"),
                "points": int(len(pts)), "map_valid": float(ok.mean()),
                "map_rmse_nm": round(rmse_nm, 1), "write_s": round(t_write, 1),
                "seconds": round(seconds, 1), "peak_rss_gb": round(peak_all / 1e9, 3),
                "semlab_process_gb": round(peak_own / 1e9, 3),
                # its children: the notebook 04 kernel (and the cluster's workers, if any)
                "children_gb": round(peak_children / 1e9, 3),
                # the process's own peak so far (getrusage) after each step it computed:
                # exact, where the 0.2 s samples can miss a short peak
                "semlab_peak_after_step_gb": step_peaks,
                "tiled": "auto_match_tiling" in cal,
                "ru_maxrss_gb": round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
                                      * 1024 / 1e9, 3)}
        if keep:
            shutil.copytree(out, keep, dirs_exist_ok=True)
        return info
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _rss(p):
    try:
        return p.memory_info().rss
    except Exception:                    # a process that just exited
        return 0


def run_case(case, size, spacing, n_frames, dense_roi=512):
    """Run one case in this process; returns a dict of numbers."""
    from semlab import parallel
    from semlab.subset import icgn_refine
    from semlab.tracking import shi_tomasi_seeds, track_reverse

    h, w = size
    info = {"case": case, "size": f"{h}x{w}"}
    if case.startswith("match"):
        # the --run experiment's views, written and read back before the sampling starts
        import shutil
        import tempfile

        import tifffile

        tmp = Path(tempfile.mkdtemp(prefix="semlab_memory_match_"))
        write_experiment(tmp, (h, w))
        views = [tifffile.imread(tmp / f"end_state/view_{k}.tif") for k in range(2)]
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        base = texture((h, w), 0)
    with PeakSampler() as peak:
        t0 = time.perf_counter()
        if case.startswith("match"):
            # tiled_auto_match (12 tiles at 3072×4096) / one auto_match
            from semlab.matching import auto_match
            from semlab.tiled_stereo import tiled_auto_match

            fn = tiled_auto_match if case == "match_tiled" else auto_match
            m = fn(views, progress=True)
            info.update(points=len(m.pts), converged=int(m.valid.sum()))
        elif case == "dense_tiled":
            par = parallax((h, w), 4.0)
            view1 = warped(base, par, np.float32(0), 2.0, 1)
            c = dense_roi
            x0, y0 = (w - c) // 2, (h - c) // 2
            t0 = time.perf_counter()
            d = parallel.tiled_dense_parallax(base, view1, roi=(x0, y0, x0 + c, y0 + c),
                                              tile_px=256, progress=True)
            info.update(points=int(c * c), converged=int(d.valid.sum()),
                        size=f"{h}x{w}, {c}x{c} ROI")
        elif case.startswith("icgn"):
            par = parallax((h, w), 4.0)
            view1 = warped(base, par, np.float32(0), 2.0, 1)
            xs = np.arange(16, w - 16, spacing, dtype=float)
            ys = np.arange(16, h - 16, spacing, dtype=float)
            gx, gy = np.meshgrid(xs, ys)
            pts = np.column_stack([gx.ravel(), gy.ravel()])
            # view 1 = view 0 sampled at x + par: a view-0 point sits at x - par in view 1
            guess = pts + np.column_stack([-par[gy.astype(int).ravel(), gx.astype(int).ravel()],
                                           np.zeros(len(pts))]) + 0.3
            t0 = time.perf_counter()
            if case == "icgn_tiled":
                r = parallel.tiled_icgn(base, view1, pts, guess, tile_px=1024, progress=True)
            else:
                r = icgn_refine(base, view1, pts, guess, progress=True)
            info.update(points=len(pts), converged=int(r.converged.sum()))
        else:
            # frames rendered one at a time into .npy files and memory-mapped, as a long
            # series would be read (tifffile.memmap): the driver does not hold them
            import tempfile

            tmp = tempfile.mkdtemp(prefix="semlab_memory_large_")
            frames = []
            for k in range(n_frames):
                a = (n_frames - 1 - k) / max(n_frames - 1, 1)
                f = Path(tmp) / f"frame_{k:03d}.npy"
                np.save(f, warped(base, parallax((h, w), 3.0 * a),
                                  parallax((w, h), 2.0 * a).T.copy(), 2.0, 10 + k))
                frames.append(np.load(f, mmap_mode="r"))
            del base
            seeds = shi_tomasi_seeds(frames[-1], quality=0.05, max_corners=20000)
            t0 = time.perf_counter()
            if case == "track_tiled":
                t = parallel.tiled_track_reverse(frames, seeds, tile_px=1024, max_motion_px=16,
                                                 progress=True)
            else:
                t = track_reverse(frames, seeds, progress=True)
            info.update(points=len(seeds), frames=n_frames,
                        valid_steps=float(t.valid[:-1].mean()))
            del frames
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
        info["seconds"] = round(time.perf_counter() - t0, 1)
    info["peak_rss_gb"] = round(peak.peak / 1e9, 3)
    info["ru_maxrss_gb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9, 3)
    return info


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--size", default="3072x4096", help="HxW (default 3072x4096)")
    p.add_argument("--spacing", type=int, default=16, help="grid spacing of the subsets, px")
    p.add_argument("--frames", type=int, default=3, help="frames of the tracking cases")
    p.add_argument("--dense-roi", type=int, default=512, help="side of the dense_tiled ROI, px")
    p.add_argument("--one", default="", help=argparse.SUPPRESS)   # run one case here
    p.add_argument("--run", action="store_true",
                   help="semlab run (stereo + heightmap) on a synthetic experiment instead")
    p.add_argument("--map-roi", type=int, default=512,
                   help="side of the central height-map ROI of --run, px (default 512; 0: whole map)")
    p.add_argument("--keep", default="", help="--run: copy the results to this folder")
    args = p.parse_args(argv)
    h, w = (int(v) for v in args.size.lower().split("x"))
    if args.run:
        r = run_semlab((h, w), args.map_roi, args.keep or None)
        print(r)
        print(f"\nmemory_large.py --run, {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores\n")
        print("| run | size | stereo points | map valid | map RMSE vs truth (nm, plane removed) "
              "| time: stereo, heightmap, whole run (s) | peak RSS, semlab + children (GB) "
              "| semlab process (GB) |")
        print("|---|---|---|---|---|---|---|---|")
        print(f"| semlab run --only 04 | {r['size']} | {r['points']} | {r['map_valid']:.1%} | "
              f"{r['map_rmse_nm']} | {r['stereo_s']}, {r['heightmap_s']}, {r['seconds']} | "
              f"{r['peak_rss_gb']} | {r['semlab_process_gb']} |")
        return 0
    if args.one:
        print("RESULT " + json.dumps(run_case(args.one, (h, w), args.spacing, args.frames,
                                              args.dense_roi)))
        return 0
    rows = []
    for case in args.cases.split(","):
        cmd = [sys.executable, __file__, "--one", case, "--size", args.size, "--spacing",
               str(args.spacing), "--frames", str(args.frames), "--dense-roi",
               str(args.dense_roi)]
        out = subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ))
        res = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT ")]
        if out.returncode or not res:
            print(out.stdout[-2000:], out.stderr[-4000:], file=sys.stderr)
            raise SystemExit(f"case {case} failed")
        rows.append(json.loads(res[0][7:]))
        print(rows[-1], flush=True)
    print(f"\nmemory_large.py, {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores\n")
    print("| case | size | points | converged / valid steps | time (s) | "
          "peak RSS, process + workers (GB) | ru_maxrss (GB) |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        extra = f" × {r['frames']} frames" if "frames" in r else ""
        ok = (f"{r['converged'] / r['points']:.1%}" if "converged" in r
              else f"{r['valid_steps']:.1%}")
        print(f"| {r['case']} | {r['size']} | {r['points']}{extra} | {ok} | {r['seconds']} | "
              f"{r['peak_rss_gb']} | {r['ru_maxrss_gb']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
