"""Stage 9's two-view weight on real views without truth: pair-to-pair consistency (issue #13).

On the real four-view ``pollen_pot1`` series (``../shared/data/real_sem``; tilts unknown),
each pair ``(0, j)``, ``j = 1, 2, 3``, is matched on its own by :func:`semlab.matching.auto_match`
(two views: stage 9 takes the two-view path). At the grid points accepted in all three pairs,
under affine cameras each pair's x-parallax is a linear function of another's and of the
position, ``p_0j = a p_01 + b + c x + d y``; fitted robustly (three rounds, residuals beyond 4 ×
1.4826 MAD dropped), its residual is what the two matches disagree on. Reported per pair
``(01, 0j)`` and region (grain / substrate): the robust SD of the residual (px), and the
fraction within the predicted 1σ / 2σ ``sqrt(σ_0j² + a² σ_01²)`` (the two matches share view
0's noise, so that σ is not exact). Three weightings of stage 9 side by side in one run:
the subset matches alone (``variational_fusion=False``), the map's σ scaled by its agreement
with the subsets over the whole view (one ``k``: the default until the local scale), and
scaled by the agreement of each point's 100 nearest (``fusion.agreement_scale(..., xy=...)``,
the default since). (Until then the script compared the map weighed by its posterior σ with
its noise-plus-bias σ: ``git show 913ab20:benchmarks/stage9_pairs_real.py``.)

Run:  python benchmarks/stage9_pairs_real.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from semlab import fusion
from semlab.io import read_image
from semlab.matching import auto_match
from semlab.stats import robust_sd

ROOT = Path(__file__).resolve().parents[1]
POLLEN = ROOT.parent / "shared" / "data" / "real_sem" / "pollen_pot1"
sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_surface import SUBSTRATE_R, _ellipse_r  # noqa: E402


def _fit(p1, pj, xy, use):
    X = np.column_stack([p1, np.ones(len(p1)), xy[:, 0], xy[:, 1]])
    fit = use.copy()
    for _ in range(3):
        beta = np.linalg.lstsq(X[fit], pj[fit], rcond=None)[0]
        r = pj - X @ beta
        mad = robust_sd(r[use])
        fit = use & (np.abs(r - np.median(r[use])) <= 4 * mad)
    return beta, r


def run(mode, ims):
    real = fusion.agreement_scale
    if mode == "whole view":    # the former scale: one k for the whole view

        def whole_view(*a, xy=None, **k):
            return real(*a, **k)

        fusion.agreement_scale = whole_view
    try:
        kw = {"variational_fusion": False} if mode == "subsets" else {}
        return [auto_match([ims[0], ims[j]], progress=False, **kw) for j in (1, 2, 3)]
    finally:
        fusion.agreement_scale = real


def main():
    if not POLLEN.is_dir():
        print(f"(skipped: {POLLEN} not present)")
        return
    ims = [read_image(POLLEN / f"pot1_0{i}.jpg").data for i in range(4)]
    print("| map's scale | pair | region | points | robust SD of residual (px) | within 1σ / 2σ "
          "| median predicted σ (px) |\n|---|---|---|---|---|---|---|")
    for mode in ("subsets", "whole view", "local"):
        t = time.perf_counter()
        ms = run(mode, ims)
        ok = np.all([m.valid for m in ms], axis=0)
        xy = ms[0].pts[:, 0]
        r_el = _ellipse_r(xy)
        p = [m.pts[:, 1, 0] - m.pts[:, 0, 0] for m in ms]
        s = [m.sigma_px for m in ms]
        for k in (1, 2):
            beta, r = _fit(p[0], p[k], xy, ok)
            sig = np.hypot(s[k], beta[0] * s[0])
            for name, reg in (("grain", r_el < 1.0), ("substrate", r_el > SUBSTRATE_R)):
                u = ok & reg & np.isfinite(sig)
                rr = r[u] - np.median(r[u])
                print(f"| {mode} | (0,1)–(0,{k + 1}) | {name} | {u.sum()} | {robust_sd(rr):.3f} "
                      f"| {100 * np.mean(np.abs(rr) < sig[u]):.0f} % / "
                      f"{100 * np.mean(np.abs(rr) < 2 * sig[u]):.0f} % | {np.median(sig[u]):.3f} |",
                      flush=True)
        print(f"<!-- {mode}: {time.perf_counter() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
