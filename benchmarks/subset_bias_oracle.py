"""How much of the sized automatic error is the subsets' model bias, and what could remove it?

The sized ``auto_match`` default (``target_sigma_px=0.05``) grows subsets until their noise σ
reaches the target; its error bars are too wide (issue #13: 79–87 % within 1σ) and its
heights are not 0.75× DeepFlow's error. This script uses the truth of accuracy-matrix cells
to split each accepted point's parallax error into noise and the subset's model bias, the
bias an *ideal* model-error estimate would report: ``validation.subset_model_bias`` of the
true parallax field over the point's own subset, each pixel weighted by its x information
(the squared x gradient of view 0 after the matcher's 1 px pre-smoothing). Then:

1. **Is the σ model right?** Coverage of the noise σ (``auto_match`` without its model-error
   term) combined with that oracle bias, against the default σ; the correlation of the error
   with the oracle bias; the error left after subtracting it.
2. **Can the bias be estimated from the matches?** Correlation with the error and with the
   oracle bias of ``match_sigma.curvature_bias`` (local quadrics through 12 / 24 / 48
   neighbours of the accepted parallax: the mean-curvature bias) and of the disagreement of
   half subsets (left/right, top/bottom halves of each point's subset matched by
   ``subset.icgn_refine(subset_offsets=...)``, the subset-splitting test of Poissant &
   Barthelat 2010), and of the variational dense map's parallax used in place of the true
   field (a plug-in: ``semlab.variational``, sharp at steps).
3. **What is the best any size choice could do?** Per point, at h = 10, 14, 20, 28, 40: the
   noise σ of an affine IC-GN subset and its oracle bias; the smallest predicted total error
   ``√(σ² + b²)`` over the sizes for square affine subsets, for second-order (quadratic)
   shape functions (σ scaled by the ratio of the two fits' centre variances) and for the
   square or one of its four halves. In nm and against DeepFlow at the same points, computed
   in the same run (``accuracy_matrix.dense_flows``).

Run:  python benchmarks/subset_bias_oracle.py                 # 2 cells, one after the other (each took 8–11 min beside the other on 2 shared cores)
      python benchmarks/subset_bias_oracle.py --cells polished/realistic/-5/5
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.stats import median_abs_deviation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

from semlab import heightmap, matching, reconstruct, validation, variational  # noqa: E402
from semlab.match_sigma import curvature_bias  # noqa: E402
from semlab.subset import icgn_refine, square_subset  # noqa: E402

CELLS = ("polished/realistic/-5/5", "real:fei/realistic/-5/5")
SIZES = (10, 14, 20, 28, 40)
HALVES = ("left", "right", "top", "bottom")
SMOOTH_PX = 1.0     # the matcher's pre-smoothing (``AutoMatchParams``)


def _cov(err, s):
    return f"{np.mean(np.abs(err) < s):.0%} / {np.mean(np.abs(err) < 2 * s):.0%}"


def _rms(a):
    a = np.asarray(a, float)
    return float(np.sqrt(np.mean(a[np.isfinite(a)] ** 2)))


def _corr(a, b):
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def _nan_min(arrays):
    """Elementwise minimum over axis 0 ignoring NaN (NaN where all are), without warnings."""
    a = np.array(arrays, float)
    m = np.min(np.where(np.isnan(a), np.inf, a), 0)
    return np.where(np.isinf(m), np.nan, m)


def _plugin_bias(v0, v1, p, h, info):
    """``subset_model_bias`` of the variational dense map's parallax (seeded by the matches),
    its holes filled by the nearest measured pixel: a plug-in for the unknown true field."""
    dm = variational.variational_parallax(v0, v1, seeds=p)
    x0, y0, x1, y1 = dm.roi
    field = np.full(v0.shape, np.nan)
    field[y0:y1, x0:x1] = np.where(dm.valid, dm.x1_px - np.arange(x0, x1)[None, :], np.nan)
    near = ndimage.distance_transform_edt(~np.isfinite(field), return_distances=False,
                                          return_indices=True)
    return validation.subset_model_bias(field[tuple(near)], p[:, 0], h, weight=info)[0]


def _matches(views):
    """The sized default and the same run without its model-error term (noise σ only)."""
    m = matching.auto_match(views, target_sigma_px=0.05, progress=False)
    orig = matching.parallax_model_error
    matching.parallax_model_error = lambda *a, **k: np.zeros(len(a[0]))
    try:
        m0 = matching.auto_match(views, target_sigma_px=0.05, progress=False)
    finally:
        matching.parallax_model_error = orig
    if not np.array_equal(m.valid, m0.valid):
        raise RuntimeError("the model error changed the accepted points; the split needs the same")
    return m, m0.sigma_px[m.valid]


def run_cell(cell):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    with tempfile.TemporaryDirectory() as tmp:
        exp = am.make_cell(Path(tmp), regime, noise, tilts)
        v0, v1 = (np.asarray(a, float) for a in exp.views()[:2])
        coef = heightmap.height_model_from_tilts(*tilts, exp.pixel_size_um).coef[0]
        nm_per_px = 1000 * abs(coef)
        # the true parallax (its non-affine part: the height over µm per pixel of parallax)
        gy, gx = np.mgrid[0:v0.shape[0], 0:v0.shape[1]]
        field = (validation.true_height_at(exp.truth_dir, np.column_stack([gx.ravel(), gy.ravel()]))
                 .reshape(v0.shape) / coef)
        info = ndimage.gaussian_filter(v0, SMOOTH_PX, order=(0, 1)) ** 2
        m, s_noise = _matches([v0, v1])
        p = m.pts[m.valid]
        par = p[:, 1, 0] - p[:, 0, 0]
        h = (m.subset_px[m.valid] - 1) // 2
        s_def = m.sigma_px[m.valid]
        z = reconstruct.heights_from_tilts(p, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
        zt = validation.true_height_at(exp.truth_dir, p[:, 0])
        # parallax error (px) after the gauge plane; its sign is that of the parallax
        err = np.sign(coef) * validation.height_errors(z, zt, p[:, 0])["err_um"] / abs(coef)
        flows, _ = am.dense_flows(v0, v1)
        df = am.score(exp, am.reference_matches(v0, v1, p[:, 0], flows)["DeepFlow"], tilts)
        b, _ = validation.subset_model_bias(field, p[:, 0], h, weight=info)

        print(f"\n## {cell}: {len(p)} accepted points, sized default RMSE {nm_per_px * _rms(err):.1f} nm, "
              f"DeepFlow at the same points {df['rmse']:.1f} nm ({nm_per_px:.1f} nm per px of parallax)\n")
        print("1. The σ model against the oracle bias\n")
        print("| σ | within 1σ / 2σ |\n|---|---|")
        print(f"| default (noise ⊕ plane-fit model error) | {_cov(err, s_def)} |")
        print(f"| noise only | {_cov(err, s_noise)} |")
        print(f"| noise ⊕ oracle bias | {_cov(err, np.hypot(s_noise, b))} |")
        print(f"\ncorr(error, oracle bias) {_corr(err, b):+.2f}; RMS error {_rms(err):.4f} px, "
              f"after subtracting the oracle bias {_rms(err - b):.4f} px "
              f"({nm_per_px * _rms(err - b):.1f} nm, {nm_per_px * _rms(err - b) / df['rmse']:.2f}× DeepFlow); "
              f"robust σ {median_abs_deviation(err, scale='normal'):.4f} → "
              f"{median_abs_deviation(err - b, scale='normal'):.4f} px\n")
        print("| subset | points | RMS error (px) | RMS oracle bias | median noise σ | median default σ "
              "| within 1σ / 2σ: default | noise | noise ⊕ oracle |")
        print("|---|---|---|---|---|---|---|---|---|")
        for hh in np.unique(h):
            w = h == hh
            if w.sum() >= 20:
                print(f"| {2 * hh + 1} px | {w.sum()} | {_rms(err[w]):.4f} | {_rms(b[w]):.4f} | "
                      f"{np.median(s_noise[w]):.4f} | {np.median(s_def[w]):.4f} | "
                      f"{_cov(err[w], s_def[w])} | {_cov(err[w], s_noise[w])} | "
                      f"{_cov(err[w], np.hypot(s_noise[w], b[w]))} |")

        print("\n2. Estimates of the bias from the matches\n")
        print("| estimate | corr with the error | corr with the oracle bias | RMS (px) "
              "| within 1σ / 2σ of noise ⊕ estimate |")
        print("|---|---|---|---|---|")
        for k in (12, 24, 48):
            c = curvature_bias(p[:, 0], par, h, k=k)
            print(f"| curvature_bias, k = {k} | {_corr(err, c):+.2f} | {_corr(b, c):+.2f} | "
                  f"{_rms(c):.4f} | {_cov(err, np.hypot(s_noise, c))} |")
        xs = {part: np.full(len(p), np.nan) for part in HALVES}
        for hh in np.unique(h):
            w = np.flatnonzero(h == hh)
            for part in HALVES:
                r = icgn_refine(v0, v1, p[w, 0], p[w, 1], half_window=int(hh), warp="affine",
                                smooth_sigma_px=SMOOTH_PX, subset_offsets=square_subset(int(hh), part))
                xs[part][w] = np.where(r.converged, r.pts[:, 0], np.nan)
        split = np.fmax(np.abs(xs["left"] - xs["right"]), np.abs(xs["top"] - xs["bottom"])) / 2
        split_est = np.nan_to_num(split)
        print(f"| half-subset disagreement / 2 ({np.isfinite(split).mean():.0%} of points) | "
              f"{_corr(np.abs(err), split):+.2f} (of \\|error\\|) | {_corr(np.abs(b), split):+.2f} "
              f"(of \\|bias\\|) | {_rms(split):.4f} | {_cov(err, np.hypot(s_noise, split_est))} |")

        plug = _plugin_bias(v0, v1, p, h, info)
        ok = np.isfinite(plug)
        print(f"| subset_model_bias of the variational dense map, plug-in ({ok.mean():.0%} of points) | "
              f"{_corr(err, plug):+.2f} | {_corr(b, plug):+.2f} | {_rms(plug):.4f} | "
              f"{_cov(err[ok], np.hypot(s_noise[ok], plug[ok]))} |")
        print(f"\nSubtracting the plug-in bias: RMS error {_rms(err[ok]):.4f} → {_rms(err[ok] - plug[ok]):.4f} px "
              f"(the oracle bias: {_rms(err[ok] - b[ok]):.4f} px)")

        print("\n3. The best size choice with the bias known (predicted total error √(σ² + b²))\n")
        tot = {"square affine": [], "square quadratic": [], "square or a half, affine": []}
        print("| h | converged | median noise σ (px) | RMS bias: affine | quadratic | best half "
              "| median σ ratio quadratic / affine |")
        print("|---|---|---|---|---|---|---|")
        for hh in SIZES:
            r = icgn_refine(v0, v1, p[:, 0], p[:, 1], half_window=hh, warp="affine",
                            smooth_sigma_px=SMOOTH_PX)
            s = np.where(r.converged, r.sigma_px[:, 0], np.nan)
            ba, va = validation.subset_model_bias(field, p[:, 0], hh, weight=info)
            bq, vq = validation.subset_model_bias(field, p[:, 0], hh, weight=info, quadratic=True)
            halves = [validation.subset_model_bias(field, p[:, 0], hh, weight=info, part=part)
                      for part in HALVES]
            t_half = _nan_min([np.sqrt(s ** 2 * vh / va + bh ** 2) for bh, vh in halves])
            b_half = np.array([bh for bh, _ in halves])
            best_half = b_half[np.argmin(np.where(np.isnan(b_half), np.inf, np.abs(b_half)), 0),
                               np.arange(len(p))]
            t_aff = np.sqrt(s ** 2 + ba ** 2)
            tot["square affine"].append(t_aff)
            tot["square quadratic"].append(np.sqrt(s ** 2 * vq / va + bq ** 2))
            tot["square or a half, affine"].append(_nan_min([t_aff, t_half]))
            print(f"| {hh} | {np.mean(r.converged):.0%} | {np.median(s[np.isfinite(s)]):.4f} | {_rms(ba):.4f} | "
                  f"{_rms(bq):.4f} | {_rms(best_half):.4f} | {np.median(np.sqrt(vq / va)[np.isfinite(vq / va)]):.2f} |",
                  flush=True)
        print("\n| shape | predicted RMS total error, best size per point | nm | ÷ DeepFlow |")
        print("|---|---|---|---|")
        for name, t in tot.items():
            best = _nan_min(t)
            print(f"| {name} | {_rms(best):.4f} px ({np.isfinite(best).mean():.0%} of points) | "
                  f"{nm_per_px * _rms(best):.1f} | {nm_per_px * _rms(best) / df['rmse']:.2f} |")
        print(f"| (the sized default, realised) | {_rms(err):.4f} px | {nm_per_px * _rms(err):.1f} | "
              f"{nm_per_px * _rms(err) / df['rmse']:.2f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", nargs="*", default=list(CELLS), help="cells regime/noise/t0/t1")
    args = ap.parse_args(argv)
    for cell in args.cells:
        run_cell(cell)


if __name__ == "__main__":
    main()
