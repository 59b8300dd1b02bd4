"""Three or more views: stage 9's held-out views against the two-view agreement scale alone (#13).

With three or more views stage 9 of :func:`semlab.matching.auto_match` runs the two-view
mechanism on every view pair (the map's local agreement scale,
:func:`semlab.fusion.agreement_scale`, noise-plus-bias σ as the weight) and keeps a view's
average only if it predicts the other views' subset matches better than the subset matches
alone (:func:`semlab.fusion.held_out_error`; since 2026-12-07: before, the held-out views
scaled the map's posterior σ, ``fusion.held_out_scale``, and the results file of 2026-12-07
06:09–06:21 UTC compares that scale). ``--mode agreement`` leaves the held-out views out
(``_held_out_positions`` made to find none): the two-view mechanism alone. It measures:

- ``--cells``: accuracy-matrix cells (``benchmarks/accuracy_matrix.py --sets =auto``, the
  same scoring; e.g. the four three-view cells), written to ``--out``;
- ``--brassica``: the real four-view Brassica pollen crop of
  ``tests/test_real_and_large.py::test_real_brassica_series_error_bars_hold_pair_to_pair``:
  the heights of view pairs (0,1), (2,3), (1,2) compared pairwise
  (:func:`semlab.validation.pair_height_differences`, the test's check): the fraction
  within 1σ / 2σ of each difference and its robust SD (µm at a pixel size of 1).

Run:  python benchmarks/stage9_three_view_scale.py --mode agreement --brassica
      python benchmarks/stage9_three_view_scale.py --mode heldout --cells polished/realistic/-5/0/5 --seed 1 --out m.md
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def brassica(data_root):
    """One line: the pair-to-pair check of the four Brassica views."""
    from semlab.io import read_image
    from semlab.matching import auto_match
    from semlab.reconstruct import estimate_tilts
    from semlab.validation import pair_height_differences

    d = Path(data_root) / "real_sem" / "brassica"
    ims = [read_image(d / f"Brassica0{i}.jpg").data[100:420, 200:648] for i in range(1, 5)]
    v = auto_match(ims, progress=False).only_valid()
    v = v.select(np.isfinite(v.sigma_px) & (v.sigma_px > 0))
    tilt = estimate_tilts(v.pts, progress=False).tilt_deg
    out = [f"{c['pairs'][0][0]}{c['pairs'][0][1]}–{c['pairs'][1][0]}{c['pairs'][1][1]}: "
           f"{100 * c['within_1sigma']:.0f} / {100 * c['within_2sigma']:.0f} %, robust SD "
           f"{c['robust_sd_um']:.2f}"
           for c in pair_height_differences(v.pts, tilt, v.sigma_px, ((0, 1), (2, 3), (1, 2)))]
    return f"{len(v.pts)} points; " + "; ".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("heldout", "agreement"), default="heldout")
    ap.add_argument("--brassica", action="store_true")
    ap.add_argument("--data-root", default=str(HERE.parent.parent / "shared" / "data"))
    ap.add_argument("--cells", default=None)
    ap.add_argument("--seed", default="0")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.mode == "agreement":
        from semlab import matching
        matching._held_out_positions = lambda *a, **k: None
    if args.brassica:
        print(f"brassica, {args.mode}: {brassica(args.data_root)}", flush=True)
    if args.cells:
        sys.argv = ["accuracy_matrix.py", "--sets", "=auto", "--seed", args.seed,
                    "--cells", args.cells] + (["--out", args.out] if args.out else [])
        sys.path.insert(0, str(HERE))
        runpy.run_path(str(HERE / "accuracy_matrix.py"), run_name="__main__")


if __name__ == "__main__":
    main()
