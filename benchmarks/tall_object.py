"""Automatic matching on a tall object: hundreds of pixels of parallax.

Run:  python benchmarks/tall_object.py

A synthetic textured dome 25 µm tall (Gaussian, σ = 8 µm) seen at ±9° at 0.03 µm/px,
1024×768 px: ~250 px of parallax that varies over the view, so no global affine map
describes the pair. Matched with semlab.matching.auto_match with and without the dense
parallax prior; errors against the exact projections. The scene is the one of
tests/test_matching.py (DomeScene).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from semlab.matching import auto_match  # noqa: E402
from test_matching import S_UM, DomeScene  # noqa: E402


def main():
    tilts = (-9.0, 9.0)
    sc = DomeScene(amp_um=25.0, radius_um=8.0, shape=(768, 1024), margin_px=200, seed=5)
    ims = [sc.render(tilts[0], seed=1), sc.render(tilts[1], gain=0.8, offset=12, seed=2)]
    h, w = sc.shape
    vv, uu = np.mgrid[0:h:8, 0:w:8]
    par = np.diff(np.stack([sc.project(*sc.material(uu.ravel(), vv.ravel(), tilts[0]), t)[:, 0]
                            for t in tilts]), axis=0)
    print(f"parallax range over the view: {np.ptp(par):.0f} px\n")
    print("| prior | accepted matches | of the grid | median / max error (px) | height RMSE (nm) | time (s) |")
    print("|---|---|---|---|---|---|")
    t0, t1 = np.deg2rad(tilts)
    for name, below in (("global affine", 0.0), ("dense, from the feature matches", 0.5)):
        t = time.perf_counter()
        m = auto_match(ims, progress=False, dense_prior_below=below)
        dt = time.perf_counter() - t
        v = m.only_valid()
        x, y = sc.material(v.pts[:, 0, 0], v.pts[:, 0, 1], tilts[0])
        err = np.hypot(*(v.pts[:, 1] - sc.project(x, y, tilts[1])).T)
        c = sc.c[0]
        z = S_UM * ((v.pts[:, 1, 0] - c) * np.cos(t0) - (v.pts[:, 0, 0] - c) * np.cos(t1)) \
            / np.sin(t1 - t0)
        rmse = 1000 * np.sqrt(np.mean((z - sc.z(x, y)) ** 2))
        print(f"| {name} | {len(v)} | {m.valid.mean():.0%} | {np.median(err):.3f} / "
              f"{err.max():.2f} | {rmse:.1f} | {dt:.1f} |")


if __name__ == "__main__":
    main()
