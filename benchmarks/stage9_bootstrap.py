"""Can a parametric bootstrap give the scale of stage 9's two-view bar? (issue #13)

``stage9_bar.py`` found that stage 9's average holds issue #13's "60–75 % within 1σ, ≥ 93 %
within 2σ" with a bar of the map's noise-plus-bias form ``σ_w`` times one scale for the view,
if that scale is known (fitted to the truth: 1.07–2.18 on six cells), and that the two views'
disagreement cannot give it. This script tries the textbook way to get it from the data: a
**parametric bootstrap**. A pilot surface stands in for the truth; the second view is
re-rendered from the first by the pilot's parallax (inverse warp by fixed-point iteration,
cubic interpolation) with white noise of the two views' measured σ
(:func:`semlab.noise.image_noise_sigma`; ``--poisson``: variance linear in the local
intensity, fitted per view, as shot noise is); the subsets (21² affine IC-GN,
:func:`semlab.subset.icgn_refine`) and stage 9's map (the same call and parameters as the
real run, seeded by the bootstrap subsets) are run again, and their errors against the pilot
give the scale. Pilots:

- ``map``: the variational map itself (smooth: its walls are the map's own);
- ``average``: the map plus stage 9's correction at the points, ``(1 − w)(a − b)``,
  interpolated linearly (the average's surface: sharper walls, a little of the subsets' noise);
- ``sharpened``: the ``average`` pilot plus its own smoothing by the map, ``average − b*``
  with ``b*`` the map of the ``average`` pilot's bootstrap world (one step of Van Cittert
  deconvolution: a pilot corrected for the map's bias, as in a bias-corrected bootstrap; a
  third map);
- ``subsets``: the map plus ``a − b`` (the subsets' surface: sharp walls and all their noise).

Columns, for each cell: the scale fitted to the truth (the average's RMS error over its
``σ_w`` bar; the map's over ``σ_w``; the subsets' over ``σ_a``) and the bootstrap's, and the
real average's fraction within 1σ / 2σ with the ``σ_w`` bar times the bootstrap's scale
(issue #13's targets: 60–75 % / ≥ 93 %).

Run:  python benchmarks/stage9_bootstrap.py [--cells polished/realistic/-5/5@0] [--poisson]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.interpolate import griddata

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402
import stage9_bar as s9  # noqa: E402

from semlab import fusion, matching, noise, subset  # noqa: E402
from semlab.stats import robust_sd  # noqa: E402
from semlab.variational import _fill  # noqa: E402

PILOTS = ("map", "average", "sharpened", "subsets")


def record(exp):
    """Stage 9's inputs (:func:`stage9_bar.record_stage9`) and its map call's arguments and
    result (the last view pair's)."""
    call = {}
    real_vm = matching._variational_map

    def vm(view0, view1, seeds, params, tiling=None, calibration=None):
        dm = real_vm(view0, view1, seeds, params, tiling, calibration)
        call.update(view0=np.asarray(view0, float), view1=np.asarray(view1, float),
                    seeds=np.array(seeds), params=params, calibration=calibration, dm=dm)
        return dm

    matching._variational_map = vm
    try:
        rec = s9.record_stage9(exp)
    finally:
        matching._variational_map = real_vm
    return rec, call


def pilot_field(dm, rec, pilot):
    """The pilot's parallax ``(dx, dy)`` on the map's roi, ``(h, w)`` arrays in pixels."""
    h, w = dm.x1_px.shape
    Y, X = np.mgrid[dm.roi[1]:dm.roi[1] + h, dm.roi[0]:dm.roi[0] + w].astype(float)
    ok = np.asarray(dm.valid, bool) & np.isfinite(dm.x1_px) & np.isfinite(dm.y1_px)
    dx = _fill(np.where(ok, dm.x1_px - X, 0.0), ok)
    dy = _fill(np.where(ok, dm.y1_px - Y, 0.0), ok)
    if pilot != "map":
        a, b, sa, sw = rec["a"], rec["b"], rec["sa"], rec["sw"]
        m = np.isfinite(a) & np.isfinite(b) & np.isfinite(sa) & np.isfinite(sw)
        step = a - b if pilot == "subsets" else (a - b) * sw ** 2 / (sa ** 2 + sw ** 2)
        dx = dx + griddata(rec["p0"][m], step[m], (X, Y), method="linear", fill_value=0.0)
    return dx, dy


def _at(field, roi, p):
    return ndimage.map_coordinates(field, [p[:, 1] - roi[1], p[:, 0] - roi[0]], order=1,
                                   mode="nearest")


def noise_sd(img, poisson):
    """The view's noise σ: one number, or (``poisson``) per pixel with its variance linear in
    the local intensity (Gaussian σ 2 px), fitted to Immerkær's response in ten bins."""
    if not poisson:
        return noise.image_noise_sigma(img)
    r = ndimage.convolve(img, np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], float))[1:-1, 1:-1]
    smooth = ndimage.gaussian_filter(img, 2.0)
    inner = smooth[1:-1, 1:-1]
    edges = np.quantile(inner, np.linspace(0, 1, 11))
    xs, vs = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (inner >= lo) & (inner <= hi)
        xs.append(np.median(inner[m]))
        vs.append((robust_sd(r[m], about=0.0) / 6.0) ** 2)
    c1, c0 = np.polyfit(xs, vs, 1)
    return np.sqrt(np.clip(c0 + c1 * smooth, 0.05 * np.median(vs), None))


def render(view0, shape, roi, dx, dy, sd, rng):
    """The second view seen through the pilot: ``view0`` at ``x0`` with ``x0 + d(x0) = x1``
    for every view-1 pixel (20 fixed-point steps), plus ``N(0, sd)``."""
    Y1, X1 = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    X0, Y0 = X1.copy(), Y1.copy()
    for _ in range(20):
        c = [np.clip(Y0 - roi[1], 0, dx.shape[0] - 1), np.clip(X0 - roi[0], 0, dx.shape[1] - 1)]
        X0 = X1 - ndimage.map_coordinates(dx, c, order=1)
        Y0 = Y1 - ndimage.map_coordinates(dy, c, order=1)
    v = np.where(np.isfinite(view0), view0, np.nanmedian(view0))
    img = ndimage.map_coordinates(v, [Y0, X0], order=3, mode="nearest")
    return img + rng.normal(0.0, 1.0, img.shape) * sd


def scales(e_avg, bar, e_b, sw, e_a, sa):
    rms = lambda v: float(np.sqrt(np.mean(v ** 2)))  # noqa: E731
    return rms(e_avg / bar), rms(e_b / sw), rms(e_a / sa)


def bootstrap(rec, call, dx, dy, poisson=False, seed=0):
    """The three scales (average over ``σ_w`` bar, map over ``σ_w``, subsets over ``σ_a``) in a
    world where the pilot ``(dx, dy)`` (on the map's roi) is the truth, and that world's map's
    x-parallax on the pilot's grid."""
    rng = np.random.default_rng(seed)
    dm, v0, v1 = call["dm"], call["view0"], call["view1"]
    sd = noise_sd(np.nan_to_num(v1), poisson)
    sd0 = noise_sd(np.nan_to_num(v0), poisson)
    sd = np.hypot(np.median(sd0), sd) if np.shape(sd0) != np.shape(sd) else np.hypot(sd0, sd)
    view1 = render(v0, v1.shape, dm.roi, dx, dy, sd, rng)
    truth = lambda p: p + np.column_stack([_at(dx, dm.roi, p), _at(dy, dm.roi, p)])  # noqa: E731

    s0 = call["seeds"][:, 0]
    seeds = subset.icgn_refine(v0, view1, s0, truth(s0), half_window=10).pts
    ok = np.all(np.isfinite(seeds), axis=1)
    dmb = matching._variational_map(v0, view1, np.stack([s0, seeds], 1)[ok], call["params"],
                                    calibration=call["calibration"])
    p0 = rec["p0"]
    t = truth(p0)
    ra = subset.icgn_refine(v0, view1, p0, t, half_window=10)
    b = fusion.sample_parallax(dmb, p0)[0][:, 0]
    sw = fusion.sample_parallax(dmb, p0, sigma="weight_sigma_px")[1]
    a, sa = ra.pts[:, 0], ra.sigma_px[:, 0]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(sw) & np.isfinite(sa) & (sa > 0)
    a, sa, b, sw, t = a[ok], sa[ok], b[ok], sw[ok], t[ok, 0]
    wb = sa ** 2 / (sa ** 2 + sw ** 2)
    k = scales((1 - wb) * a + wb * b - t, np.hypot((1 - wb) * sa, wb * sw), b - t, sw, a - t, sa)
    h, w = dx.shape
    Y, X = np.mgrid[dm.roi[1]:dm.roi[1] + h, dm.roi[0]:dm.roi[0] + w].astype(float)
    xb = np.arange(dmb.roi[0], dmb.roi[0] + dmb.x1_px.shape[1])[None, :]
    ok = np.asarray(dmb.valid, bool) & np.isfinite(dmb.x1_px)
    bx = _fill(np.where(ok, dmb.x1_px - xb, 0.0), ok)
    return k, ndimage.map_coordinates(bx, [Y - dmb.roi[1], X - dmb.roi[0]], order=1,
                                      mode="nearest")


def truth_scales(exp, tilts, rec):
    """The real run's scales against the truth, and its average's error and ``σ_w`` bar."""
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(rec["b"]) & np.isfinite(rec["sw"]) & np.isfinite(rec["a"])
              & np.isfinite(rec["sa"]) & (rec["sa"] > 0))
    p0, a, sa, b, sw = (rec[k][ok] for k in ("p0", "a", "sa", "b", "sw"))
    wb = sa ** 2 / (sa ** 2 + sw ** 2)
    e_avg = s9.errors_px(exp, tilts, p0, (1 - wb) * a + wb * b)
    bar = np.hypot((1 - wb) * sa, wb * sw)
    e_a, e_b = s9.errors_px(exp, tilts, p0, a), s9.errors_px(exp, tilts, p0, b)
    return scales(e_avg, bar, e_b, sw, e_a, sa), e_avg, bar


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default=",".join(s9.CELLS),
                    help="REGIME/NOISE/T0/T1@SEED, comma-separated (default: %(default)s)")
    ap.add_argument("--poisson", action="store_true",
                    help="bootstrap noise with variance linear in intensity (shot noise)")
    args = ap.parse_args(argv)
    trio = lambda s: " / ".join(f"{v:.2f}" for v in s)  # noqa: E731
    print("| cell | seed | truth: average / map / subsets | "
          + " | ".join(f"pilot `{p}`: scales; average within 1σ / 2σ" for p in PILOTS)
          + " |\n" + "|---" * (3 + len(PILOTS)) + "|")
    for spec in args.cells.split(","):
        cell, regime, level, tilts, seed = s9.parse_cell(spec)
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            exp = am.make_cell(tmp, regime, level, tilts, seed=seed)
            rec, call = record(exp)
            real, e_avg, bar = truth_scales(exp, tilts, rec)
            cols, k_of = [], {}
            for pilot in PILOTS:
                if pilot == "sharpened":
                    dx, dy = pilot_field(call["dm"], rec, "average")
                    dx = 2 * dx - k_of["average"][1]
                    k, _ = bootstrap(rec, call, dx, dy, poisson=args.poisson, seed=1)
                else:
                    k_of[pilot] = bootstrap(rec, call, *pilot_field(call["dm"], rec, pilot),
                                            poisson=args.poisson)
                    k = k_of[pilot][0]
                w1, w2 = s9._within(e_avg, k[0] * bar)
                cols.append(f"{trio(k)}; {100 * w1:.0f} / {100 * w2:.0f} %")
        print(f"| {cell} | {seed} | {trio(real)} | " + " | ".join(cols) + " |", flush=True)
        print(f"<!-- {spec}: {time.perf_counter() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
