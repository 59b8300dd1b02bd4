"""Variational heights at the automatic matches' points vs DeepFlow there (issue #13 target).

A few cells of :mod:`accuracy_matrix` (same experiments, same scoring): semlab's automatic
matching gives its points; at their view-0 positions the variational parallax map
(:func:`semlab.variational.variational_parallax`, seeded by those matches) is sampled
bilinearly and scored against the truth like every method of the matrix, next to semlab's
own automatic heights and OpenCV DeepFlow (default settings) sampled at the same points.
#13's target: the automatic heights at <= 0.75× DeepFlow's RMSE at the same points.

Run:  python benchmarks/variational_points.py            # 3 cells, ~2-4 min each on 2 cores
      python benchmarks/variational_points.py --cells polished/realistic/0/8
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

from semlab import heightmap, variational  # noqa: E402

CELLS = ("polished/realistic/-5/5", "polished/realistic/0/8", "real:fei/realistic/-5/5")


def run(cell, tmp):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    exp = am.make_cell(tmp, regime, noise, tilts)
    v0, v1 = exp.views()[:2]
    sh = am.semlab_heights(exp, "auto")
    p0 = sh.pts[:, 0]
    t = time.perf_counter()
    par = variational.variational_parallax(v0, v1, seeds=sh.pts)
    secs = time.perf_counter() - t
    c = [p0[:, 1], p0[:, 0]]
    take = lambda a: ndimage.map_coordinates(np.nan_to_num(a), c, order=1)  # noqa: E731
    ok = ndimage.map_coordinates(par.valid.astype(float), c, order=1) > 0.999
    x1 = np.where(ok, take(par.x1_px), np.nan)
    y1 = np.where(ok, take(par.y1_px), np.nan)
    var_pts = np.stack([p0, np.column_stack([x1, y1])], 1)
    # heights' σ from the map's parallax σ (the same linear height model as the matrix)
    s = take(par.sigma_px)
    z_err = abs(heightmap.height_model_from_tilts(*tilts, exp.pixel_size_um).coef[0]) * s
    flows, _ = am.dense_flows(v0, v1)
    refs = am.reference_matches(v0, v1, p0, flows)
    rows = {"semlab auto": am.score(exp, sh.pts, tilts, sh.z_err_um),
            "variational": am.score(exp, var_pts, tilts, z_err),
            "DeepFlow": am.score(exp, refs["DeepFlow"], tilts)}
    return rows, len(p0), secs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default=",".join(CELLS))
    args = ap.parse_args(argv)
    lines = ["| cell | points | semlab auto | variational at the points | DeepFlow | "
             "variational ÷ DeepFlow | variational within 1σ / 2σ | map time |",
             "|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for cell in args.cells.split(","):
            rows, n, secs = run(cell, tmp)
            a, v, d = rows["semlab auto"], rows["variational"], rows["DeepFlow"]
            line = (f"| {cell} | {n} | {a['rmse']:.1f} nm | {v['rmse']:.1f} nm ({v['n']}) | "
                    f"{d['rmse']:.1f} nm | {v['rmse'] / d['rmse']:.2f} | "
                    f"{100 * v['in1']:.0f} / {100 * v['in2']:.0f} % | {secs:.0f} s |")
            print(line, flush=True)
            lines.append(line)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
