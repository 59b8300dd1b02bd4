"""Speed and accuracy of semlab.subset (ZNCC search + IC-GN) on DIC Challenge sample 5.

Sample 5 (DIC Challenge 1.0): ``Sample5 Reference.tif`` vs
``Sample5-001 X0.10 Y0.10 N2 C100 R20.tif``, a uniform shift of +0.10 px in x and y
(the speckle of image 001 sits at larger x and y: matched position = reference + 0.1),
with noise and a different contrast. Prints a markdown table of the RMS error over a grid
of subsets and the throughput (points per second, wall clock with up to 2 threads, and per CPU-second, which does
not depend on what else runs on the machine).

Run: ``python benchmarks/subset_speed.py``
"""

import time
from pathlib import Path

import numpy as np
import tifffile

from semlab.subset import icgn_refine, zncc_match

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "dic_challenge" / "sample5"


def grid(shape, margin, step):
    xs = np.arange(margin, shape[1] - margin, step, dtype=float)
    ys = np.arange(margin, shape[0] - margin, step, dtype=float)
    X, Y = np.meshgrid(xs, ys)
    return np.stack([X.ravel(), Y.ravel()], 1)


def main():
    ref = tifffile.imread(DATA / "Sample5 Reference.tif").astype(float)
    cur = tifffile.imread(DATA / "Sample5-001 X0.10 Y0.10 N2 C100 R20.tif").astype(float)
    print("| half_window | subset | warp | smooth σ px | points | ZNCC pts/s | IC-GN pts/s "
          "| IC-GN pts/CPU-s | mean iters | mean u, v (px) | RMS error (px) | median σ est (px) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for h, warp, sig in [(10, "affine", 0.0), (10, "affine", 0.8), (10, "translation", 0.0),
                         (15, "affine", 0.0), (15, "affine", 0.8), (20, "affine", 0.8)]:
        pts = grid(ref.shape, h + 6, 4)
        t0 = time.perf_counter()
        p0, _ = zncc_match(ref, cur, pts, pts, half_window=h, search_px=3)
        t1 = time.perf_counter()
        c1 = time.process_time()
        r = icgn_refine(ref, cur, pts, p0, half_window=h, warp=warp, smooth_sigma_px=sig)
        t2 = time.perf_counter()
        cpu = time.process_time() - c1
        u = r.pts - pts
        rms = np.sqrt(np.nanmean((u - 0.1) ** 2))
        mu = np.nanmean(u, 0)
        print(f"| {h} | {2 * h + 1}×{2 * h + 1} | {warp} | {sig} | {len(pts)} "
              f"| {len(pts) / (t1 - t0):.0f} | {len(pts) / (t2 - t1):.0f} | {len(pts) / cpu:.0f} "
              f"| {r.n_iter.mean():.2f} | {mu[0]:.4f}, {mu[1]:.4f} | {rms:.4f} "
              f"| {np.nanmedian(r.sigma_px):.4f} |")


if __name__ == "__main__":
    main()
