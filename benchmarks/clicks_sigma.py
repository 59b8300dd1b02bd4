"""Refined clicks: their error bars, against noise-sized subsets, and a per-click breakdown
of the misses.

Run:  python benchmarks/clicks_sigma.py real:fei/low/0/8,real:quartz/realistic/0/8 0,1,2
      (cells as in ``accuracy_matrix.py --cells``; seeds comma-separated; ~10 s per cell)
      python benchmarks/clicks_sigma.py --diagnose real:fei/realistic/-5/5 0,1,2
      (per click: truth error and predicted σ with its parts, see :func:`diagnose`)

Default mode: for each cell and seed (the accuracy matrix's scenes, 384×512 px, 50 clicks)
the refined clicks with each of :data:`VARIANTS`, scored as ``accuracy_matrix.py`` scores
them: height RMSE (nm), points, fractions within 1σ / 2σ, and ECC 15 px at the same points,
under the least-squares plane of the error and in parentheses the robust (Huber) gauge plane
(``validation.height_errors(plane="robust")``, as the matrix's second tables). Prints one line
per cell.

``--diagnose``: the default refined clicks (``target_sigma_px=0.05``), and per click the
height error against the truth (plane of the error removed, as the matrix scores it) in
units of the predicted σ, the σ's parts (noise σ, a posteriori factor, model error of the
coarse grid, the click's own curvature bias from the size ladder, the band subset's use),
the subset size, the residual ratio and ZNCC, the spread of the click's x match over the
size ladder (:func:`semlab.adaptive.adaptive_icgn`'s runs) in units of the smallest size's
noise σ, the distance to the nearest steep truth slope (slip-band flanks), and the truth's
model error (``m/σ``: the information-weighted affine fit of the true height over the
chosen subset minus the true height at the click, :func:`_truth_model_error`). Prints a
table of the misses (``|error| > 2σ``) and the pooled fractions per class.
Results: ``benchmarks/results/clicks_sigma_diagnosis.md``.

(:data:`VARIANTS`: subsets sized by the noise alone, ``curvature_neighbours=None``, whose
σ carries no curvature bias, and the default, sized by the total error with the expected
squared ladder bias in σ. The before / after of 2026-12-02, ``bias_in_sigma="estimate"``
against the default, needs a semlab from before that option was removed: docs/accuracy.md
and ``benchmarks/results/clicks_sigma_diagnosis.md``.)
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

VARIANTS = {"noise-sized": {"target_sigma_px": 0.05, "curvature_neighbours": None},
            "default": {"target_sigma_px": 0.05}}
STEEP = 0.25      # truth |∇z| (µm/µm) counted as a band flank


def _variants():
    """VARIANTS whose keywords this semlab's refine_correspondences accepts."""
    import inspect

    from semlab import refine

    names = set(inspect.signature(refine.refine_correspondences).parameters)
    return {k: {a: b for a, b in v.items() if a in names} for k, v in VARIANTS.items()}


def compare(cells, seeds):
    """Default mode: one line per cell and seed, every variant."""
    variants = _variants()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for regime, noise, tilts in cells:
                exp = am.make_cell(tmp, regime, noise, tilts, seed)
                v0, v1 = exp.views()[:2]
                flows, _ = am.dense_flows(v0, v1)
                line = f"{regime:12s} {noise:9s} {tilts[0]:+g}/{tilts[1]:+g} seed {seed}"
                for name, kw in variants.items():
                    sh = am.semlab_heights(exp, "refined", refine=kw)
                    r = am.score(exp, sh.pts, tilts, sh.z_err_um)
                    ecc = am.score(exp, am.reference_matches(v0, v1, sh.pts[:, 0], flows)
                                   ["ECC 15px"], tilts)
                    line += (f" | {name}: {r['rmse']:5.1f} nm N {r['n']} within 1σ/2σ "
                             f"{r['in1']:.2f}/{r['in2']:.2f} ECC {ecc['rmse']:5.1f}"
                             f" (robust gauge: {r['rmse_rob']:5.1f} nm, {r['in1_rob']:.2f}/"
                             f"{r['in2_rob']:.2f}, ECC {ecc['rmse_rob']:5.1f})")
                print(line, flush=True)


@contextlib.contextmanager
def _capture():
    """Record the internals of one refine_correspondences call (two views)."""
    from semlab import adaptive, refine

    rec = {"runs": []}
    saved = {k: getattr(refine, k) for k in ("_grid_icgn", "model_error_at", "match_sigma")}
    saved_icgn = adaptive.icgn_refine

    def grid(*a, **k):
        out = saved["_grid_icgn"](*a, **k)
        rec["hw"], rec["bias"] = out[1], out[2]
        rec["rr_sq"], rec["zn_sq"] = out[0].residual_ratio.copy(), out[0].zncc.copy()
        rec["sig_sq"] = out[0].sigma_px[:, 0].copy()
        return out

    def mod(*a, **k):
        out = saved["model_error_at"](*a, **k)
        rec["model_grid"] = out
        return out

    def msig(s, rr=None, m=None):
        rec["sig_noise"], rec["rr"], rec["model"] = np.array(s), np.array(rr), np.array(m)
        return saved["match_sigma"](s, rr, m)

    def icgn(*a, **k):
        r = saved_icgn(*a, **k)
        rec["runs"].append((k.get("half_window"), r.pts[:, 0].copy(), r.sigma_px[:, 0].copy(),
                            r.converged.copy()))
        return r

    try:
        refine._grid_icgn = grid
        refine.model_error_at, refine.match_sigma = mod, msig
        adaptive.icgn_refine = icgn
        yield rec
    finally:
        for k, v in saved.items():
            setattr(refine, k, v)
        adaptive.icgn_refine = saved_icgn


def _truth_height(exp):
    """(H, W) true view-0 height, µm."""
    d = Path(exp.truth_dir)
    return np.load(d / "height_view0.npy" if (d / "height_view0.npy").exists()
                   else d / "truth" / "height_view0.npy").astype(float)


def _truth_model_error(exp, p0, hw, smooth_px=0.8):
    """(N,) height error (µm) an affine subset makes on the true relief, noise-free.

    The affine shape function's centre is, to first order, the least-squares plane of the
    true height over the subset weighted by the x information ``gx²`` of the (smoothed)
    reference view, evaluated at the centre; minus the true height there.
    """
    z = _truth_height(exp)
    v0 = np.asarray(exp.views()[0], float)
    w = np.gradient(ndimage.gaussian_filter(v0, smooth_px), axis=1) ** 2
    out = np.full(len(p0), np.nan)
    for i, ((x, y), h) in enumerate(zip(p0, hw)):
        c, r = int(round(x)), int(round(y))
        if h <= 0 or r - h < 0 or c - h < 0 or r + h >= z.shape[0] or c + h >= z.shape[1]:
            continue
        yy, xx = np.mgrid[-h:h + 1, -h:h + 1]
        ww = w[r - h:r + h + 1, c - h:c + h + 1].ravel()
        A = np.column_stack([np.ones(ww.size), xx.ravel() + c - x, yy.ravel() + r - y])
        zz = z[r - h:r + h + 1, c - h:c + h + 1].ravel()
        coef = np.linalg.lstsq(A * np.sqrt(ww)[:, None], zz * np.sqrt(ww), rcond=None)[0]
        zc = ndimage.map_coordinates(z, [[y], [x]], order=3)[0]
        out[i] = coef[0] - zc
    return out


def _band_distance(exp, p0, pixel_um):
    """(N,) distance (px) from each view-0 point to the nearest truth slope > STEEP."""
    z = _truth_height(exp)
    gy, gx = np.gradient(z, pixel_um)
    dist = ndimage.distance_transform_edt(np.hypot(gx, gy) <= STEEP)
    return ndimage.map_coordinates(dist, [p0[:, 1], p0[:, 0]], order=0, mode="nearest")


def diagnose_cell(tmp, regime, noise, tilts, seed, refine_kw=None):
    """Per-click breakdown of one cell: a dict of (N,) arrays (see the module docstring)."""
    exp = am.make_cell(tmp, regime, noise, tilts, seed)
    with _capture() as rec:
        sh = am.semlab_heights(exp, "refined", refine=dict(target_sigma_px=0.05,
                                                           **(refine_kw or {})))
    r = am.score(exp, sh.pts, tilts, sh.z_err_um)
    ok = r["ok"]
    p = sh.pts[ok]
    z = am.reconstruct.heights_from_tilts(p, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
    zt = am.validation.true_height_at(exp.truth_dir, p[:, 0])
    err = am.validation.height_errors(z, zt, p[:, 0])["err_um"]
    # which clicks of refine_correspondences's input are the scored ones
    clicks = exp.correspondences().pts[:, 0]
    idx = np.array([int(np.argmin(np.hypot(*(clicks - q).T))) for q in p[:, 0]])
    tot = np.sqrt(rec["sig_noise"] ** 2 * np.maximum(1, np.nan_to_num(rec["rr"], nan=1.0))
                  + np.nan_to_num(rec["model"]) ** 2)[idx]
    nm_per_px = np.where(np.isfinite(tot) & (tot > 0), 1000 * sh.z_err_um[ok] / tot, np.nan)
    # the click's x match over the size ladder of adaptive_icgn (total-error sizing)
    runs = [x for x in rec["runs"] if x[0] is not None]
    X = np.stack([x[1] for x in runs])[:, idx]
    S = np.stack([x[2] for x in runs])[:, idx]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        X = np.where(np.isfinite(X), X, np.nanmedian(X, 0) if np.isfinite(X).any() else 0)
        spread = (X.max(0) - X.min(0)) / S[0]
    return {"cell": f"{regime}/{noise}/{tilts[0]:+g}/{tilts[1]:+g}/s{seed}",
            "err_sig": err / sh.z_err_um[ok], "err_px": 1000 * err / nm_per_px,
            "sig_px": tot, "noise_px": rec["sig_noise"][idx],
            "apost": np.sqrt(np.maximum(1, np.nan_to_num(rec["rr"], nan=1.0)))[idx],
            "model_px": np.nan_to_num(rec["model"])[idx],
            "grid_px": np.nan_to_num(rec["model_grid"])[idx],
            "bias_px": np.nan_to_num(rec["bias"])[idx], "hw": rec["hw"][idx],
            "band": ~np.isclose(rec["sig_noise"], rec["sig_sq"], rtol=1e-12, atol=0)[idx],
            "rr": rec["rr"][idx], "zncc": rec["zn_sq"][idx], "spread": spread,
            "dist": _band_distance(exp, p[:, 0], exp.pixel_size_um),
            "ladder_h": np.broadcast_to(np.array([x[0] for x in runs])[:, None],
                                        X.shape).T.copy(),
            "ladder_x": X.T.copy(), "ladder_sig": S.T.copy(),
            "true_model_sig": _truth_model_error(exp, p[:, 0], rec["hw"][idx]) / sh.z_err_um[ok]}


def diagnose(cells, seeds, refine_kw=None):
    """--diagnose mode: per-cell fractions, the misses, and pooled fractions per class."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            for regime, noise, tilts in cells:
                d = diagnose_cell(tmp, regime, noise, tilts, seed, refine_kw)
                a = np.abs(d["err_sig"])
                print(f"{d['cell']:32s} N {len(a):2d} within 1σ/2σ {np.mean(a < 1):.2f}/"
                      f"{np.mean(a < 2):.2f}  RMSE {np.sqrt(np.nanmean(d['err_px'] ** 2)):.3f} px "
                      f"median σ {np.median(d['sig_px']):.3f} px", flush=True)
                rows.append(d)
    keys = [k for k in rows[0] if k != "cell"]
    pool = {k: np.concatenate([r[k] for r in rows]) for k in keys}
    cell = np.concatenate([[r["cell"]] * len(r["hw"]) for r in rows])
    a = np.abs(pool["err_sig"])
    miss = a > 2
    print(f"\npooled: N {len(a)}, within 1σ {np.mean(a < 1):.3f}, within 2σ "
          f"{np.mean(a < 2):.3f}, misses {miss.sum()}")
    print("\nmisses (|error| > 2σ):\n"
          f"{'cell':32s} {'err/σ':>6s} {'err px':>7s} {'σ px':>6s} {'noise':>6s} "
          f"{'apost':>5s} {'grid':>6s} {'bias':>6s} {'h':>3s} {'band':>4s} {'rr':>5s} "
          f"{'zncc':>5s} {'spread':>6s} {'dist':>5s} {'m/σ':>5s}")
    for i in np.flatnonzero(miss)[np.argsort(-a[miss])]:
        print(f"{cell[i]:32s} {pool['err_sig'][i]:6.2f} {pool['err_px'][i]:7.3f} "
              f"{pool['sig_px'][i]:6.3f} {pool['noise_px'][i]:6.3f} {pool['apost'][i]:5.2f} "
              f"{pool['grid_px'][i]:6.3f} {pool['bias_px'][i]:6.3f} {pool['hw'][i]:3d} "
              f"{int(pool['band'][i]):4d} {pool['rr'][i]:5.2f} {pool['zncc'][i]:5.3f} "
              f"{pool['spread'][i]:6.2f} {pool['dist'][i]:5.1f} {pool['true_model_sig'][i]:5.2f}")
    classes = {"near a band flank (dist <= h)": pool["dist"] <= pool["hw"],
               "far from flanks (dist > h)": pool["dist"] > pool["hw"],
               "small subset (h <= 10)": pool["hw"] <= 10,
               "large subset (h >= 14)": pool["hw"] >= 14,
               "band subset used": pool["band"].astype(bool),
               "model error > noise σ": pool["model_px"] > pool["noise_px"],
               "model error = 0": pool["model_px"] == 0,
               "residual ratio > 1.2": pool["rr"] > 1.2,
               "ladder spread > 2 noise σ": pool["spread"] > 2}
    print(f"\n{'class':34s} {'N':>4s} {'1σ':>5s} {'2σ':>5s} {'misses':>6s} "
          f"{'RMS err/σ':>9s}")
    for name, m in classes.items():
        if m.sum():
            print(f"{name:34s} {m.sum():4d} {np.mean(a[m] < 1):5.2f} {np.mean(a[m] < 2):5.2f} "
                  f"{miss[m].sum():6d} {np.sqrt(np.mean(a[m] ** 2)):9.2f}")
    return rows


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    diag = "--diagnose" in argv
    argv = [a for a in argv if a != "--diagnose"]
    cells = [am._parse_cell(c) for c in argv[0].split(",")]
    seeds = [int(s) for s in (argv[1] if len(argv) > 1 else "0").split(",")]
    (diagnose if diag else compare)(cells, seeds)


if __name__ == "__main__":
    main()
