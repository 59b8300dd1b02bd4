"""Can two views tell the error of stage 9's average? The data behind its 1σ (issue #13).

Stage 9 of :func:`semlab.matching.auto_match` averages each point's subset match ``a`` (1σ
``σ_a``) with the variational map ``b``; with two views the map is weighed by its
noise-plus-bias σ ``σ_w`` and the average's bar comes from its posterior σ ``σ_p``
(:func:`semlab.fusion.inverse_variance`). That bar is conservative on flat parts (issue #13
asks for 60–75 % of the errors within 1σ). For accuracy-matrix cells
(:func:`accuracy_matrix.make_cell`, same experiments and scoring), stage 9's inputs are
recorded at its call and scored against the truth, in pixels of x-parallax:

- ``corr``: correlation of the subset match's error with the map's;
- ``agree``: median of ``(b − a)² / (σ_a² + σ_w²)`` over that of χ²₁ (0.455): below 1, the
  two disagree *less* than even the noise-plus-bias σ says, so their disagreement (the only
  thing two views measure twice) cannot show an excess error of the map;
- the map's RMS error in the lowest and the highest quarter of the map's own local slope
  (a quadratic fit to each point's 9 nearest points, the median gradient removed) beside the
  median ``σ_w`` and ``σ_p`` there: the map's error grows with its slope, ``σ_w`` does not;
- the average's fraction within 1σ / 2σ with three bars: ``σ_p`` (the default), ``σ_w``, and
  an **oracle** ``sqrt(σ_w² + ℓ² |∇b|²)`` whose length ``ℓ`` is fitted to the truth (median
  of error² / bar² equal to χ²₁'s): what a bar that follows the map's slope could at best do,
  with the ``ℓ`` the data cannot give (fitted to ``b − a`` instead, ``ℓ = 0`` on every cell);
- the ``σ_w`` bar times **one scale for the view** fitted to the truth (the average's RMS
  error over that bar), and the fractions it gives: a bar of this form holds if its scale is
  known;
- what two views could give that scale from: the map is about the efficient estimate of the
  same pixels (``cov(e_a, e_b) / E e_b²`` near 1, the nested-estimator relation of Hausman's
  test), so ``E e_b² = E e_a² − E (b − a)²``; with the subsets' predicted σ for ``E e_a²``
  the estimate ``(E σ_a² − E d²) / E e_b²`` shows how far a few per cent of conservatism in
  ``σ_a`` throws it (the difference of two numbers of about the same size).

Run:  python benchmarks/stage9_bar.py [--cells polished/realistic/-5/5@0,real:fei/low/-5/5@0]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402
from stage9_walls import _errors, _nm_per_px  # noqa: E402

from semlab import fusion  # noqa: E402
from semlab.fusion import CHI2_1_MEDIAN  # noqa: E402

CELLS = ("polished/low/-5/5@1", "polished/realistic/-5/5@0", "polished/realistic/0/8@1",
         "speckle/realistic/0/8@0", "real:fei/low/-5/5@0", "real:quartz/realistic/-5/5@1")


def record_stage9(exp):
    """Run automatic matching (fixed subsets, stage 9 on) and return stage 9's inputs at its
    (last) call: view-0 points ``p0``, subset x ``a`` and ``σ_a``, map x ``b``, ``σ_p``, ``σ_w``."""
    rec = {}
    real_iv, real_sp = fusion.inverse_variance, fusion.sample_parallax

    def iv(a, sa, b, sb, weight_sigma_b=None, shared_sigma=None):
        rec.update(a=np.array(a)[:, 0], sa=np.array(sa), b=np.array(b)[:, 0],
                   sp=np.array(sb), sw=np.array(weight_sigma_b), sm=np.array(shared_sigma))
        return real_iv(a, sa, b, sb, weight_sigma_b=weight_sigma_b, shared_sigma=shared_sigma)

    def sp(dense, pts, sigma="sigma_px"):
        if sigma == "sigma_px":
            rec["p0"] = np.array(pts)
        return real_sp(dense, pts, sigma)

    fusion.inverse_variance, fusion.sample_parallax = iv, sp
    try:
        am.semlab_heights(exp, "auto", auto={"target_sigma_px": None})
    finally:
        fusion.inverse_variance, fusion.sample_parallax = real_iv, real_sp
    return rec


def errors_px(exp, tilts, p0, x1):
    """Height error (plane removed) of view-1 x positions ``x1`` at ``p0``, in parallax px
    (:func:`stage9_walls._errors`, converted)."""
    pts = np.stack([p0, np.column_stack([x1, p0[:, 1]])], 1)
    return _errors(exp, pts, tilts) / _nm_per_px(exp, tilts)


def local_slope(p, f, k=9):
    """|∇f| at each point from a quadratic fit to its ``k`` nearest points, the median
    gradient (the tilt pair's uniform parallax gradient) removed."""
    _, nb = cKDTree(p).query(p, k)
    g = np.empty((len(p), 2))
    for i, idx in enumerate(nb):
        d = p[idx] - p[i]
        A = np.column_stack([np.ones(k), d, d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2])
        g[i] = np.linalg.lstsq(A, f[idx], rcond=None)[0][1:3]
    return np.hypot(*(g - np.median(g, axis=0)).T)


def fit_length(r2, base, g2):
    """The ``ℓ ≥ 0`` (grid of 0.05 px) with median ``r² / (base + ℓ² g²)`` at χ²₁'s median."""
    for ell in np.arange(0.0, 40.0, 0.05):
        if np.median(r2 / (base + ell * ell * g2)) <= CHI2_1_MEDIAN:
            return float(ell)
    return np.inf


def analyse(exp, tilts, rec):
    """One row of the table (a dict)."""
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(rec["b"]) & np.isfinite(rec["sp"]) & np.isfinite(rec["sw"])
              & np.isfinite(rec["a"]) & (rec["sa"] > 0) & np.isfinite(rec["sa"]))
    p0, a, sa, b, sp, sw = (rec[k][ok] for k in ("p0", "a", "sa", "b", "sp", "sw"))
    ea, eb = errors_px(exp, tilts, p0, a), errors_px(exp, tilts, p0, b)
    g = local_slope(p0, b - p0[:, 0])
    lo, hi = g <= np.quantile(g, 0.25), g >= np.quantile(g, 0.75)

    # stage 9's average (weighted by σ_w) and its error, scored against each bar below
    wb = sa ** 2 / (sa ** 2 + sw ** 2)
    e_avg = errors_px(exp, tilts, p0, (1 - wb) * a + wb * b)
    bar = lambda s_map: np.hypot((1 - wb) * sa, wb * s_map)  # noqa: E731
    average = lambda s_map: _within(e_avg, bar(s_map))  # noqa: E731

    ell = fit_length(eb ** 2, sw ** 2, g ** 2)
    rms = lambda v: float(np.sqrt(np.mean(v ** 2)))  # noqa: E731
    # one scale for the view, fitted to the truth: the average's RMS error over its σ_w bar
    scale = rms(e_avg / bar(sw))
    return {"n": int(ok.sum()), "corr": float(np.corrcoef(ea, eb)[0, 1]),
            "agree": float(np.median((b - a) ** 2 / (sa ** 2 + sw ** 2)) / CHI2_1_MEDIAN),
            "ell_d": fit_length((b - a) ** 2, sa ** 2 + sw ** 2, g ** 2), "ell": ell,
            "lo": (rms(eb[lo]), np.median(sw[lo]), np.median(sp[lo])),
            "hi": (rms(eb[hi]), np.median(sw[hi]), np.median(sp[hi])),
            "post": average(sp), "nb": average(sw),
            "oracle": average(np.sqrt(sw ** 2 + ell ** 2 * g ** 2)),
            "scaled": (scale, *_within(e_avg, scale * bar(sw))),
            "nested": (float(np.mean(ea * eb) / np.mean(eb ** 2)),
                       float((np.mean(sa ** 2) - np.mean((b - a) ** 2)) / np.mean(eb ** 2)))}


def parse_cell(spec):
    """``REGIME/NOISE/T0/T1@SEED`` (seed optional, default 0): ``(cell, regime, noise,
    (t0, t1), seed)``."""
    cell, _, seed = spec.partition("@")
    regime, noise, t0, t1 = cell.split("/")
    return cell, regime, noise, (float(t0), float(t1)), int(seed or 0)


def _within(e, s):
    """Fractions of ``|e|`` within ``s`` and ``2 s``."""
    return float(np.mean(np.abs(e) < s)), float(np.mean(np.abs(e) < 2 * s))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default=",".join(CELLS),
                    help="REGIME/NOISE/T0/T1@SEED, comma-separated (default: %(default)s)")
    args = ap.parse_args(argv)
    print("| cell | seed | points | corr | agree | ℓ from b − a / truth (px) | map error, "
          "flattest ¼: RMS, σ_w, σ_p (px) | steepest ¼ | average within 1σ / 2σ: σ_p "
          "(default) | σ_w | oracle | σ_w × one scale fitted to the truth: scale, within 1σ / "
          "2σ | cov(e_a, e_b) / E e_b², (E σ_a² − E d²) / E e_b² |\n"
          + "|---" * 13 + "|")
    pct = lambda f: f"{100 * f[0]:.0f} / {100 * f[1]:.0f} %"  # noqa: E731
    trio = lambda t: " / ".join(f"{v:.3f}" for v in t)  # noqa: E731
    for spec in args.cells.split(","):
        cell, regime, noise, tilts, seed = parse_cell(spec)
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            exp = am.make_cell(tmp, regime, noise, tilts, seed=seed)
            r = analyse(exp, tilts, record_stage9(exp))
        print(f"| {cell} | {seed} | {r['n']} | {r['corr']:+.2f} | {r['agree']:.2f} | "
              f"{r['ell_d']:.2f} / {r['ell']:.2f} | {trio(r['lo'])} | {trio(r['hi'])} | "
              f"{pct(r['post'])} | {pct(r['nb'])} | {pct(r['oracle'])} | "
              f"{r['scaled'][0]:.2f}, {pct(r['scaled'][1:])} | "
              f"{r['nested'][0]:.2f}, {r['nested'][1]:.2f} |", flush=True)
        print(f"<!-- {spec}: {time.perf_counter() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
