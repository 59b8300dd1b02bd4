"""Accuracy and speed of semlab.reconstruct / semlab.surface on synthetic matches.

Run: ``.venv/bin/python benchmarks/bench_reconstruct.py`` — prints markdown tables.

Scene: 15 × 11 µm field (512 × 384 px at 0.03 µm/px), level base plane with a y slope,
30 % of the points on slip-band extrusions/intrusions of 0.05–0.3 µm; matches are the exact
affine projections (semlab.camera) plus Gaussian noise of σ px on x and y in every view,
with a different unknown tilt-axis offset per view. Heights are compared after removing the
robust reference plane from both the truth and the estimate.
"""

import time

import numpy as np

from semlab.camera import project_affine
from semlab.reconstruct import estimate_tilts, heights_from_tilts
from semlab.surface import bootstrap_heights, fit_reference_plane, heights_above_plane, \
    height_sigma

S = 0.03


def scene(n, rng):
    x = rng.uniform(0, 512, n) * S
    y = rng.uniform(0, 384, n) * S
    band = rng.random(n) < 0.3
    z = 0.2 + 0.01 * y + np.where(band, rng.uniform(0.05, 0.3, n) * rng.choice([-1, 1], n), 0)
    return np.column_stack([x, y, z])


def views(xyz, tilts, sigma, rng):
    pts = np.stack([project_affine(xyz, t, S, (256.0 + 7 * i, 192.0 - 3 * i))
                    for i, t in enumerate(tilts)], 1)
    return pts + rng.normal(0, sigma, pts.shape)


def rel(xyz):
    return heights_above_plane(xyz, fit_reference_plane(xyz))


def height_table(n=500, trials=20):
    print("\n### Height RMS error (known tilts, unknown per-view offsets), N = %d, %d trials\n"
          % (n, trials))
    print("| tilts (deg) | σ match (px) | predicted σ_z (nm) | RMS error (nm) "
          "| bootstrap σ_z (nm) |")
    print("|---|---|---|---|---|")
    for tilts in [(-5.0, 5.0), (-5.0, 0.0, 5.0), (0.0, 8.0)]:
        for sigma in (0.01, 0.02, 0.05, 0.1, 0.5):
            rng = np.random.default_rng(0)
            errs = []
            for _ in range(trials):
                xyz = scene(n, rng)
                res = heights_from_tilts(views(xyz, tilts, sigma, rng), tilts, S)
                errs.append(rel(res.xyz_um) - rel(xyz))
            rms = np.sqrt(np.mean(np.square(errs)))
            boot = np.median(bootstrap_heights(views(xyz, tilts, sigma, rng), tilts, S,
                                               n_boot=50, sigma_px=sigma, progress=False))
            print(f"| {tilts} | {sigma} | {1e3 * height_sigma(sigma, tilts, S):.1f} | "
                  f"{1e3 * rms:.1f} | {1e3 * boot:.1f} |")


def tilt_table(n=200, trials=20):
    tilts = np.array([-5.0, 0.0, 5.0])
    print("\n### Tilt recovery, 3 views (-5, 0, 5) deg, N = %d, %d trials (level-plane offset)\n"
          % (n, trials))
    print("| σ match (px) | RMS tilt error (deg) | max tilt error (deg) | mean bootstrap σ (deg) "
          "| height RMS with estimated tilts (nm) |")
    print("|---|---|---|---|---|")
    for sigma in (0.0, 0.01, 0.02, 0.05, 0.1):
        rng = np.random.default_rng(1)
        e, sig, hz = [], [], []
        for _ in range(trials):
            xyz = scene(n, rng)
            est = estimate_tilts(views(xyz, tilts, sigma, rng), pixel_size_um=S, n_boot=50,
                                 progress=False)
            e.append(est.tilt_deg - tilts)
            sig.append(est.tilt_sigma_deg)
            hz.append(rel(est.xyz) - rel(xyz))
        e = np.array(e)
        print(f"| {sigma} | {np.sqrt(np.mean(e ** 2)):.2g} | {np.abs(e).max():.2g} | "
              f"{np.mean(sig):.2g} | {1e3 * np.sqrt(np.mean(np.square(hz))):.2g} |")


def speed_table():
    rng = np.random.default_rng(2)
    print("\n### Speed (this machine, single run)\n")
    print("| call | N | time (s) |")
    print("|---|---|---|")
    tilts = (-5.0, 0.0, 5.0)
    for n in (1000, 10000):
        xyz = scene(n, rng)
        pts = views(xyz, tilts, 0.02, rng)
        for name, fn in [
            ("heights_from_tilts", lambda: heights_from_tilts(pts, tilts, S)),
            ("fit_reference_plane", lambda: fit_reference_plane(xyz)),
            ("estimate_tilts(n_boot=200)",
             lambda: estimate_tilts(pts, S, n_boot=200, progress=False)),
            ("bootstrap_heights(n_boot=200, sigma_px)",
             lambda: bootstrap_heights(pts, tilts, S, n_boot=200, sigma_px=0.02,
                                       progress=False)),
        ]:
            t0 = time.perf_counter()
            fn()
            print(f"| {name} | {n} | {time.perf_counter() - t0:.3f} |")


if __name__ == "__main__":
    height_table()
    tilt_table()
    speed_table()
