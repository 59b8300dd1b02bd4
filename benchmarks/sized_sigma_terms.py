"""Which term of the automatic σ is conservative where information-sized subsets grew?

Two checks (issue #13's error bars, the sized ``auto_match`` default):

1. ``--cells``: cells of :mod:`accuracy_matrix` (same experiments). ``auto_match`` with
   ``target_sigma_px=0.05`` is run as it is and with its model-error term
   (``match_sigma.parallax_model_error``) and/or its a posteriori residual factor
   (``match_sigma.aposteriori_sigma``) switched off; per subset side: the robust spread of
   the parallax error (heights against the truth after removing the plane of the error,
   divided by the height per pixel of parallax), the median σ, and the fraction within 1σ
   and 2σ; and, as an alternative model error, the noise σ combined with the magnitude of
   ``match_sigma.curvature_bias`` (local quadrics through 12 / 24 / 48 neighbours), and,
   on the accepted points alone, the plane-fit model error and that curvature bias with the
   quadric fits' model error.
2. ``--monte-carlo``: the noise part alone. One polished scene at −5/+5°, realistic
   detector; the points of one fixed-subset ``auto_match`` (16 px grid) refined by
   ``subset.icgn_refine`` (affine, 1 px pre-smoothing) in 12 new noise draws at h = 10, 14,
   20, 28: the spread of the x position over the draws against the predicted σ_x.

Run:  python benchmarks/sized_sigma_terms.py            # both, 2 cells, ~10 min on 2 cores
      python benchmarks/sized_sigma_terms.py --cells polished/realistic/-5/5
      python benchmarks/sized_sigma_terms.py --monte-carlo
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import median_abs_deviation

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

from semlab import heightmap, matching, reconstruct, synth, validation  # noqa: E402
from semlab.match_sigma import curvature_bias  # noqa: E402
from semlab.subset import icgn_refine  # noqa: E402
from semlab.synth_texture import detect  # noqa: E402

CELLS = ("polished/realistic/-5/5", "real:fei/realistic/-5/5")
VARIANTS = ("default", "no model error", "no a posteriori factor", "neither")


def robust_sd(a):
    return float(median_abs_deviation(a, scale="normal"))


def _table(title, ex, s, side_px, um_per_px):
    print(f"\n{title}: {len(ex)} points, RMSE {1000 * um_per_px * np.sqrt(np.mean(ex ** 2)):.1f} nm, "
          f"within 1σ / 2σ {np.mean(np.abs(ex) < s):.0%} / {np.mean(np.abs(ex) < 2 * s):.0%}\n")
    print("| subset | points | robust error (px) | median σ (px) | within 1σ | within 2σ |")
    print("|---|---|---|---|---|---|")
    for side in np.unique(side_px):
        w = side_px == side
        if w.sum() >= 20:
            print(f"| {side} px | {w.sum()} | {robust_sd(ex[w]):.4f} | {np.median(s[w]):.4f} | "
                  f"{np.mean(np.abs(ex[w]) < s[w]):.0%} | {np.mean(np.abs(ex[w]) < 2 * s[w]):.0%} |",
                  flush=True)


def sized_terms(cell):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    orig_me, orig_ap = matching.parallax_model_error, matching.aposteriori_sigma
    with tempfile.TemporaryDirectory() as tmp:
        exp = am.make_cell(Path(tmp), regime, noise, tilts)
        v = exp.views()[:2]
        # height per pixel of view-1 x (parallax), the same linear model as the matrix
        um_per_px = abs(heightmap.height_model_from_tilts(*tilts, exp.pixel_size_um).coef[0])
        try:
            for name in VARIANTS:
                no_me = name in ("no model error", "neither")
                no_ap = name in ("no a posteriori factor", "neither")
                matching.parallax_model_error = ((lambda *a, **k: np.zeros(len(a[0])))
                                                 if no_me else orig_me)
                matching.aposteriori_sigma = ((lambda s, rr: np.asarray(s, float))
                                              if no_ap else orig_ap)
                m = matching.auto_match(v, target_sigma_px=0.05, progress=False)
                ok = m.valid
                p = m.pts[ok]
                z = reconstruct.heights_from_tilts(p, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
                zt = validation.true_height_at(exp.truth_dir, p[:, 0])
                ex = validation.height_errors(z, zt, p[:, 0])["err_um"] / um_per_px
                s = m.sigma_px[ok]
                _table(f"{cell} [{name}]", ex, s, m.subset_px[ok], um_per_px)
                if name == "no model error":
                    # alternatives computed on the accepted points alone (auto_match computes
                    # its model error before the later outlier stages, on all points alive
                    # then): the same plane-fit model error; the noise σ with the centre bias
                    # of the mean curvature; that bias with the quadric fits' own model error
                    # (the non-quadratic part: steps)
                    pa = p[:, 1, 0] - p[:, 0, 0]
                    h = (m.subset_px[ok] - 1) / 2
                    side = m.subset_px[ok]
                    me_plane = orig_me(p[:, 0], pa, s, h, spacing_px=m.params.spacing_px)
                    _table(f"{cell} [noise σ ⊕ plane-fit model error, accepted points only]",
                           ex, np.hypot(s, me_plane), side, um_per_px)
                    me_quad = orig_me(p[:, 0], pa, s, h, quadratic=True,
                                      spacing_px=m.params.spacing_px)
                    for k in (12, 24, 48):
                        b = np.abs(curvature_bias(p[:, 0], pa, h, k=k))
                        _table(f"{cell} [noise σ ⊕ |curvature_bias|, k = {k}]", ex,
                               np.hypot(s, b), side, um_per_px)
                        if k == 12:
                            _table(f"{cell} [noise σ ⊕ |curvature_bias| k = 12 ⊕ quadric-fit "
                                   "model error, accepted points only]", ex,
                                   np.sqrt(s ** 2 + b ** 2 + me_quad ** 2), side, um_per_px)
        finally:
            matching.parallax_model_error, matching.aposteriori_sigma = orig_me, orig_ap


def monte_carlo(n_draw=12, smooth_px=1.0):
    shape = (384, 512)
    scene = synth.make_scene(seed=0, size=shape, texture="polished")
    a = synth.render(scene, shape, tilt_deg=-5.0, noise=0.0)[0]
    b = synth.render(scene, shape, tilt_deg=5.0, noise=0.0)[0]
    rng = np.random.default_rng(1)

    def draw(im):
        return detect(im, "realistic", rng, gain=1.0, offset=0.0).astype(float)

    m = matching.auto_match([draw(a), draw(b)], target_sigma_px=None, progress=False,
                            spacing_px=16)
    p0, p1 = m.pts[m.valid, 0], m.pts[m.valid, 1]
    draws = [(draw(a), draw(b)) for _ in range(n_draw)]
    print(f"\nMonte Carlo, polished −5/+5°, realistic detector, {len(p0)} points, {n_draw} draws, "
          f"{smooth_px} px pre-smoothing\n")
    print("| h | points | median spread / predicted σ_x | RMS spread (px) | RMS predicted (px) |")
    print("|---|---|---|---|---|")
    for h in (10, 14, 20, 28):
        rs = [icgn_refine(A, B, p0, p1, half_window=h, warp="affine", smooth_sigma_px=smooth_px)
              for A, B in draws]
        xs = np.array([r.pts[:, 0] for r in rs])
        ss = np.array([r.sigma_px[:, 0] for r in rs])
        good = np.all([r.converged for r in rs], axis=0) & np.isfinite(ss).all(0)
        emp = xs[:, good].std(0, ddof=1)
        pred = np.sqrt(np.mean(ss[:, good] ** 2, 0))
        print(f"| {h} | {good.sum()} | {np.median(emp / pred):.2f} | "
              f"{np.sqrt(np.mean(emp ** 2)):.4f} | {np.sqrt(np.mean(pred ** 2)):.4f} |", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", nargs="*", default=None, help="cells regime/noise/t0/t1")
    ap.add_argument("--monte-carlo", action="store_true")
    args = ap.parse_args(argv)
    both = args.cells is None and not args.monte_carlo
    for cell in (CELLS if both or args.cells == [] else args.cells or ()):
        sized_terms(cell)
    if both or args.monte_carlo:
        monte_carlo()


if __name__ == "__main__":
    main()
