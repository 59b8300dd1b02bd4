"""Refined clicks before/after their own curvature bias and information-offset check.

Run:  python benchmarks/clicks_sigma.py real:fei/low/0/8,real:quartz/realistic/0/8 0,1,2
      (cells as in ``accuracy_matrix.py --cells``; seeds comma-separated; ~10 s per cell)

For each cell and seed (the accuracy matrix's scenes, 384×512 px, 50 clicks) the default
refined clicks (information-sized subsets) with ``curvature_neighbours=None,
max_info_offset=None`` (before 2026-12-01 23:40) and with the defaults, each scored as
``accuracy_matrix.py`` scores them: height RMSE (nm), points, fractions within 1σ / 2σ, and
ECC 15 px at the same points. Prints one line per cell.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

VARIANTS = {"before": {"target_sigma_px": 0.05, "curvature_neighbours": None,
                       "max_info_offset": None},
            "after": {"target_sigma_px": 0.05}}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    cells = [am._parse_cell(c) for c in argv[0].split(",")]
    seeds = [int(s) for s in (argv[1] if len(argv) > 1 else "0").split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for regime, noise, tilts in cells:
                exp = am.make_cell(tmp, regime, noise, tilts, seed)
                v0, v1 = exp.views()[:2]
                flows, _ = am.dense_flows(v0, v1)
                line = f"{regime:12s} {noise:9s} {tilts[0]:+g}/{tilts[1]:+g} seed {seed}"
                for name, kw in VARIANTS.items():
                    sh = am.semlab_heights(exp, "refined", refine=kw)
                    r = am.score(exp, sh.pts, tilts, sh.z_err_um)
                    ecc = am.score(exp, am.reference_matches(v0, v1, sh.pts[:, 0], flows)
                                   ["ECC 15px"], tilts)
                    line += (f" | {name}: {r['rmse']:5.1f} nm N {r['n']} within 1σ/2σ "
                             f"{r['in1']:.2f}/{r['in2']:.2f} ECC {ecc['rmse']:5.1f}")
                print(line, flush=True)


if __name__ == "__main__":
    main()
