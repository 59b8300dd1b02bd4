"""Subset matches, the variational map and their average at the automatic points (issue #13).

Cells of :mod:`accuracy_matrix` (same experiments, same scoring). semlab's automatic
matching is run twice: as by default, where stage 9 averages each accepted point's subset
match with the variational parallax map's estimate there (``variational_fusion``), and with
the subset matches alone (``variational_fusion=False``; the same accepted points). At their
view-0 positions the variational map (:func:`semlab.variational.variational_parallax`,
seeded by the subset matches, as stage 9 computes it) is also scored alone, and OpenCV
DeepFlow (default settings) is sampled at the same points. #13's target: the automatic
heights at <= 0.75× DeepFlow's RMSE at the same points.

Run:  python benchmarks/variational_points.py            # 3 cells, ~2-4 min each on 2 cores
      python benchmarks/variational_points.py --cells polished/realistic/0/8,real:fei/low/0/8
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

from semlab import fusion, heightmap, variational  # noqa: E402

CELLS = ("polished/realistic/-5/5", "polished/realistic/0/8", "real:fei/realistic/-5/5")


def run(cell, tmp):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    exp = am.make_cell(tmp, regime, noise, tilts)
    v0, v1 = exp.views()[:2]
    t = time.perf_counter()
    fused = am.semlab_heights(exp, "auto")
    secs = time.perf_counter() - t
    sh = am.semlab_heights(exp, "auto", auto={"variational_fusion": False})
    if not np.array_equal(sh.pts[:, 0], fused.pts[:, 0]):
        raise RuntimeError(f"{cell}: stage 9 changed the accepted points")
    p0 = sh.pts[:, 0]
    par = variational.variational_parallax(v0, v1, seeds=sh.pts)
    xy1, s = fusion.sample_parallax(par, p0)
    var_pts = np.stack([p0, xy1], 1)
    # heights' σ from the map's parallax σ (the same linear height model as the matrix)
    z_err = abs(heightmap.height_model_from_tilts(*tilts, exp.pixel_size_um).coef[0]) * s
    flows, _ = am.dense_flows(v0, v1)
    refs = am.reference_matches(v0, v1, p0, flows)
    rows = {"semlab auto": am.score(exp, fused.pts, tilts, fused.z_err_um),
            "subsets alone": am.score(exp, sh.pts, tilts, sh.z_err_um),
            "variational": am.score(exp, var_pts, tilts, z_err),
            "DeepFlow": am.score(exp, refs["DeepFlow"], tilts)}
    return rows, len(p0), secs


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default=",".join(CELLS))
    args = ap.parse_args(argv)
    lines = ["| cell | points | semlab auto (stage 9) | ÷ DeepFlow | within 1σ / 2σ | "
             "subsets alone | ÷ DeepFlow | within 1σ / 2σ | variational alone | ÷ DeepFlow | "
             "DeepFlow | auto_match time |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for cell in args.cells.split(","):
            rows, n, secs = run(cell, tmp)
            d = rows["DeepFlow"]["rmse"]
            cols = []
            for name in ("semlab auto", "subsets alone", "variational"):
                r = rows[name]
                cols.append(f"{r['rmse']:.1f} nm | {r['rmse'] / d:.2f}")
                if name != "variational":
                    cols[-1] += f" | {100 * r['in1']:.0f} / {100 * r['in2']:.0f} %"
            line = f"| {cell} | {n} | " + " | ".join(cols) + f" | {d:.1f} nm | {secs:.0f} s |"
            print(line, flush=True)
            lines.append(line)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
