"""Where stage 9's error is: beside the band walls or on the flat parts (issue #13).

For each cell of :mod:`accuracy_matrix` (same experiments, same scoring): the automatic points
(fixed 21×21 subsets, the default) and, at their view-0 positions, the subset matches alone,
the variational map alone (:func:`semlab.variational.variational_parallax`, seeded by them, as
stage 9 computes it), stage 9's average, and OpenCV DeepFlow (default settings). Points are
split by the steepest true slope within 10 px (``< 2``, ``2–20``, ``> 20`` nm/px: flat, flank,
wall). Per part: height RMSE, share of the average's squared error, and the fraction within
1σ / 2σ of the map's two σ modes (``posterior+bias``, the default, and ``noise+bias``); and the
correlation of the subset match's error with the map's, for fixed and for noise-sized subsets.

Run:  python benchmarks/stage9_walls.py [--cells polished/realistic/-5/5,polished/low/-5/5]
                                        [--seed 1]
                                        [--var KEY=VALUE ...]  (the maps' VariationalParams)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402
from bench_args import variational_params  # noqa: E402

from semlab import fusion, reconstruct, validation, variational  # noqa: E402

CELLS = ("polished/realistic/-5/5", "polished/low/-5/5")
PARTS = (("flat < 2", 0, 2), ("flank 2–20", 2, 20), ("wall > 20", 20, np.inf))


def _errors(exp, pts, tilts):
    """Height errors (nm) of matches ``pts`` (N, 2, 2), least-squares plane removed."""
    z = reconstruct.heights_from_tilts(pts, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
    zt = validation.true_height_at(exp.truth_dir, pts[:, 0])
    return 1000 * validation.height_errors(z, zt, pts[:, 0], plane="lsq")["err_um"]


def _nm_per_px(exp, tilts):
    """Height (nm) of one pixel of x-parallax for the tilt pair."""
    return 1000 * abs(reconstruct.parallax_height(1.0, 0.0, *tilts, exp.pixel_size_um)
                      - reconstruct.parallax_height(0.0, 0.0, *tilts, exp.pixel_size_um))


def _map_at(v0, v1, seeds, p0, mode, vparams):
    dm = variational.variational_parallax(v0, v1, seeds=seeds,
                                          params=replace(vparams, sigma_mode=mode))
    xy1, s = fusion.sample_parallax(dm, p0)
    return np.stack([p0, xy1], 1), s


def run(cell, tmp, vparams, seed=0):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    exp = am.make_cell(tmp, regime, noise, tilts, seed=seed)
    v0, v1 = exp.views()[:2]
    fused = am.semlab_heights(exp, "auto", auto={"variational_params": vparams})
    sub = am.semlab_heights(exp, "auto", auto={"variational_fusion": False})
    p0 = sub.pts[:, 0]
    z = 1000 * np.load(exp.truth_dir / "height_view0.npy")
    slope = ndimage.maximum_filter(np.hypot(*np.gradient(z)), size=21)
    slope = ndimage.map_coordinates(slope, [p0[:, 1], p0[:, 0]], order=0)
    nm_per_px = _nm_per_px(exp, tilts)
    e = {"average": _errors(exp, fused.pts, tilts), "subsets": _errors(exp, sub.pts, tilts)}
    sig = {}
    for mode in ("posterior+bias", "noise+bias"):
        pts, s = _map_at(v0, v1, sub.pts, p0, mode, vparams)
        e["map"], sig[mode] = _errors(exp, pts, tilts), nm_per_px * s
    flows, _ = am.dense_flows(v0, v1)
    e["DeepFlow"] = _errors(exp, am.reference_matches(v0, v1, p0, flows)["DeepFlow"], tilts)
    sized = am.semlab_heights(exp, "auto", auto={"variational_fusion": False,
                                                 "target_sigma_px": 0.05})
    pts_s, _ = _map_at(v0, v1, sized.pts, sized.pts[:, 0], "posterior+bias", vparams)
    corr = {"fixed": np.corrcoef(e["subsets"], e["map"])[0, 1],
            "sized": np.corrcoef(_errors(exp, sized.pts, tilts), _errors(exp, pts_s, tilts))[0, 1]}
    lines = [f"### {cell}" + (f", seed {seed}" if seed else ""), "",
             f"{len(p0)} points; correlation of the subset match's error with the map's: fixed "
             f"{corr['fixed']:+.2f}, noise-sized (0.05 px, its own {len(sized.pts)} points) "
             f"{corr['sized']:+.2f}", "",
             "| part (true slope, nm/px) | points | average | subsets | map | DeepFlow | share of "
             "the average's squared error | map σ posterior+bias: median, within 1σ / 2σ | "
             "noise+bias |", "|---|---|---|---|---|---|---|---|---|"]
    tot = np.sum(e["average"] ** 2)
    for name, lo, hi in PARTS + (("all", 0, np.inf),):
        m = (slope >= lo) & (slope < hi)
        rms = " | ".join(f"{np.sqrt(np.mean(e[k][m] ** 2)):.1f}"
                         for k in ("average", "subsets", "map", "DeepFlow"))
        cal = " | ".join(f"{np.median(sig[k][m]):.1f} nm, {100 * np.mean(abs(e['map'][m]) < sig[k][m]):.0f}"
                         f" / {100 * np.mean(abs(e['map'][m]) < 2 * sig[k][m]):.0f} %"
                         for k in ("posterior+bias", "noise+bias"))
        lines.append(f"| {name} | {m.sum()} | {rms} | {100 * np.sum(e['average'][m] ** 2) / tot:.0f} %"
                     f" | {cal} |")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", default=",".join(CELLS))
    ap.add_argument("--seed", type=int, default=0, help="the cells' seed (as accuracy_matrix)")
    ap.add_argument("--var", action="append", default=[], metavar="KEY=VALUE",
                    help="a VariationalParams field of the maps (stage 9's and the map "
                    "alone's), e.g. --var norm_sigma_px=5 (repeatable)")
    args = ap.parse_args(argv)
    vparams = variational_params(args.var)
    with tempfile.TemporaryDirectory() as tmp:
        for cell in args.cells.split(","):
            print(run(cell, tmp, vparams, args.seed) + "\n", flush=True)


if __name__ == "__main__":
    main()
