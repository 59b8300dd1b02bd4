"""A slip-band-like trapezoid of parallax: the first-difference prior against the others.

A 64×96 textured pair (``tests/test_variational.py::_pair``: texture σ 1.5 px, noise 0.15)
whose view 1 is view 0 moved by a band of x-parallax: 0 px, a ramp up over 8 px, a 1.2 px
top 12 px wide, a ramp down over 8 px. Each prior of :mod:`semlab.variational` refines the
same initial guess (:func:`semlab.heightmap.initial_guess`); reported: RMSE (px) over the
interior, on the band (ramps and top) and off it, the median of the top (truth 1.2), the
share within 1σ / 2σ, the prior scales and the time.

Run:  python benchmarks/variational_ramp.py      (about a minute on 2 cores)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from semlab import heightmap as hm, variational as va  # noqa: E402
from test_variational import _pair  # noqa: E402


def main():
    shape = (64, 96)
    x = np.arange(96)[None, :] * np.ones((64, 1))
    true = 1.2 * np.clip(np.minimum((x - 30) / 8.0, (58 - x) / 8.0), 0, 1)
    v0, v1 = _pair(shape, true, 0.15, seed=3, tex_sigma=1.5)
    g, _, _ = hm.initial_guess(v0, v1)
    p0 = g[..., 0] - x
    inner = (slice(10, -10), slice(10, -10))
    band = (true > 0)[inner]
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    runs = [("first differences (default)", va.VariationalParams()),
            ("second differences, s / 15", va.VariationalParams(prior_order=2, solver="direct")),
            ("second differences, 0.0107 px (s·√12 / 15)",
             va.VariationalParams(prior_order=2, solver="direct", prior_scale_px=0.0107)),
            ("TGV-like, slope scale s·√12 / 15 (rule)", va.VariationalParams(prior="tgv"))]
    runs += [(f"TGV-like, slope scale {f} px", va.VariationalParams(prior="tgv", slope_scale_px=f))
             for f in (0.005, 0.02, 0.05)]
    print("| prior | RMSE all | band | off band | top (1.2) | 1σ / 2σ | s, slope scale | time |")
    print("|---|---|---|---|---|---|---|---|")
    for name, prm in runs:
        t0 = time.perf_counter()
        par, sig, valid, info = va.refine_parallax(v0, v1, p0, params=prm, return_info=True)
        dt = time.perf_counter() - t0
        e = (par - true)[inner]
        z = np.abs(e) / sig[inner]
        top = float(np.median(np.median(par[10:-10], 0)[40:48]))
        print(f"| {name} | {rms(e):.3f} px | {rms(e[band]):.3f} | {rms(e[~band]):.3f} | "
              f"{top:.3f} | {100 * np.mean(z < 1):.0f} / {100 * np.mean(z < 2):.0f} % | "
              f"{info['prior_scale_px']:.4f}, {info.get('slope_scale_px', float('nan')):.4f} | "
              f"{dt:.1f} s |", flush=True)


if __name__ == "__main__":
    main()
