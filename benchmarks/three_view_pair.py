"""Three views against their own outer pair, the same draw, at the same points (issue #13).

A three-view cell of ``benchmarks/accuracy_matrix.py`` (e.g. −5/0/+5°) is matched by
:func:`semlab.matching.auto_match` three ways, on the same images:

- ``three views``: all views, the defaults (at ab3d6fa, the results file's code: stage 9's
  map σ scaled by the held-out view, ``fusion.held_out_scale``; since 2026-12-07 the
  two-view mechanism on each pair, kept where the held-out view says so,
  :func:`semlab.fusion.held_out_error`);
- ``three views, agreement``: all views, stage 9 with the two-view agreement scale on every
  view pair (``_held_out_positions`` made to find no held-out view, as
  ``stage9_three_view_scale.py --mode agreement``);
- ``outer pair``: only the first and the last view (a two-view run: noise-plus-bias weight,
  agreement scale);

and with stage 9 off (the subsets alone, where the three runs agree to the digit on the
outer view's positions). Heights come from the views each run matched (the known tilts,
``reconstruct.heights_from_tilts``), scored against the truth (plane of the error removed,
``validation.height_errors``) at the points all runs accepted in all their views, beside
OpenCV DeepFlow from view 0 to every other view at the same points, through the same
three-view heights. It separates what the multi-view stages cost from what the draw of the
scene does: last session's 13.5 against 16.0 nm came from two different draws.

Run:  python benchmarks/three_view_pair.py --cells polished/realistic/-5/0/5 --seed 1
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import accuracy_matrix as am  # noqa: E402

from semlab import matching, reconstruct, validation  # noqa: E402
from semlab.stats import robust_sd  # noqa: E402


def _accepted(ims, agreement=False, **kw):
    """``{view-0 (x, y): (V, 2) positions}`` of the points accepted in every view."""
    held = matching._held_out_positions
    if agreement:
        matching._held_out_positions = lambda *a, **k: None
    try:
        r = matching.auto_match(ims, progress=False, **kw)
    finally:
        matching._held_out_positions = held
    ok = r.valid & np.all(np.isfinite(r.pts.reshape(len(r.pts), -1)), axis=1)
    return {tuple(np.round(p[0], 3)): p for p in r.pts[ok]}


def _errors_nm(exp, pts, tilts):
    """Height RMSE and robust σ (nm) of matches ``pts`` (N, V, 2) made at ``tilts`` (V
    views, or the first and last of them when V is 2), plane of the error removed."""
    tilts = tilts if pts.shape[1] == len(tilts) else (tilts[0], tilts[-1])
    z = reconstruct.heights_from_tilts(pts, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
    zt = validation.true_height_at(exp.truth_dir, pts[:, 0])
    e = validation.height_errors(z, zt, pts[:, 0])
    return 1000 * e["rmse_um"], 1000 * robust_sd(e["err_um"])


def run_cell(regime, noise, tilts, seed):
    """One results row (a markdown line) for a cell."""
    exp = am.make_cell(tempfile.mkdtemp(), regime, noise, tilts, seed)
    views = exp.views()[:len(tilts)]
    outer = [views[0], views[-1]]
    res = {"three views": _accepted(views),
           "three views, agreement": _accepted(views, agreement=True),
           "outer pair": _accepted(outer)}
    subsets = {"three views": _accepted(views, variational_fusion=False),
               "outer pair": _accepted(outer, variational_fusion=False)}
    keys = sorted(set.intersection(*[set(r) for r in list(res.values())
                                     + list(subsets.values())]))
    p0 = np.array(keys, float)
    flows = {j: am.dense_flows(views[0], views[j])[0] for j in range(1, len(views))}
    df = am.multiview_reference_matches(views, p0, 0, flows)["DeepFlow"]
    df_rmse, df_rsig = _errors_nm(exp, df, tilts)
    at_keys = lambda r: np.array([r[k] for k in keys])  # noqa: E731
    cols = []
    for r in res.values():
        rmse, rsig = _errors_nm(exp, at_keys(r), tilts)
        cols.append(f"{rmse:.1f} / {rsig:.1f} nm, {rmse / df_rmse:.2f}×")
    sub = [f"{_errors_nm(exp, at_keys(r), tilts)[0]:.1f}" for r in subsets.values()]
    n_all = ", ".join(str(len(r)) for r in res.values())
    return (f"| {regime} {noise} {am.tilts_label(tilts)} | {seed} | {len(keys)} ({n_all}) | "
            + " | ".join(cols) + f" | {df_rmse:.1f} / {df_rsig:.1f} nm | " + " / ".join(sub)
            + " |")


HEAD = ("| cell | seed | points scored (accepted: three views, agreement, pair) | three views "
        "(default): RMSE / robust σ, ÷ DeepFlow | three views, agreement scale | outer pair "
        "alone | DeepFlow (three views) | subsets alone: three views / pair (RMSE, nm) |\n"
        "|---|---|---|---|---|---|---|---|")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", required=True,
                    help="comma-separated REGIME/NOISE/T0/T1/T2 (accuracy_matrix.py's form)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    cells = [am._parse_cell(c) for c in args.cells.split(",")]
    if any(len(t) < 3 for _, _, t in cells):
        raise SystemExit("--cells: give three or more tilts per cell (REGIME/NOISE/T0/T1/T2)")
    print(HEAD, flush=True)
    for regime, noise, tilts in cells:
        t0 = time.perf_counter()
        print(run_cell(regime, noise, tilts, args.seed), flush=True)
        print(f"<!-- {regime}/{noise}/{'/'.join(f'{t:g}' for t in tilts)}@{args.seed}: "
              f"{time.perf_counter() - t0:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
