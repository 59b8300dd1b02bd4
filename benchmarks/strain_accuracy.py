"""Strain end to end: a synthetic series under a known uniform strain, through tracking.

Run:  python benchmarks/strain_accuracy.py

semlab.synth makes a frontal series whose displacement from the first to the last frame is a
uniform small strain (no slip bands); semlab.series.run_tracking tracks it backwards, semlab.series.run_strain and
derives the strain (dense IC-GN grid, Delaunay triangles, local least squares). The table
compares the median Green–Lagrange strain with the truth (truth/fields.npz), for several
seeds (scenes). The sparse methods use the Shi–Tomasi-seeded tracks valid from the reference
frame (the earliest frame with enough valid tracks) to the last; the dense grid uses every
converged subset (subsets with ZNCC >= 0.95 until 2026-12-07) and a 7×7-point strain window.

The last table checks the local least-squares strain's 1σ (``E_lsq_sigma``, propagated from
the tracks' ``sigma_px``): per component the median predicted σ, the RMS of the error
against the truth, the RMS of the normalised error (error / σ, 1 if σ is right) and the
fraction of points within 2σ (0.95 for Gaussian errors); and the same for the tracks' own
σ (``sigma_px`` in the reference frame, against the residual of the track displacements
about one affine fit to all of them, which the uniform strain makes exact).
"""

from __future__ import annotations

import argparse
import tempfile
import warnings
from pathlib import Path

import numpy as np

from semlab import experiment, series, synth, validation


def run(strain=(0.02, -0.01, 0.008), method="lk", seed=0):
    with tempfile.TemporaryDirectory() as tmp:
        toml = synth.make_experiment(Path(tmp) / "e", seed=seed, tilts_deg=(), n_frames=4,
                                     slip_um=0.0, uniform_strain=strain, early_contrast=1.0,
                                     progress=False)
        exp = experiment.load(toml)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # "sized": semlab run's default (subsets sized by their information, 0.02 px)
            kw = ({"method": "subset", "track_kw": {"target_sigma_px": 0.02}}
                  if method == "sized" else {"method": method})
            r = series.run_tracking(exp, progress=False, **kw)
            S = series.run_strain(exp, r)
        f = validation.load_fields(exp.root)
        # U(x) = E x (end-state coordinates); frame r holds x - (1 - f_r) E x, so the deformation
        # from the pipeline's reference frame r to the end is F = (I - (1 - f_r) E)^-1 exactly
        frac = 1.0 - f["f"][S["ref_frame"]]
        Em = np.array([[strain[0], strain[2]], [strain[2], strain[1]]])
        Fm = np.linalg.inv(np.eye(2) - frac * Em)
        GL = 0.5 * (Fm.T @ Fm - np.eye(2))
        true_part = np.array([GL[0, 0], GL[1, 1], GL[0, 1]])
        out = {}
        Ec = np.stack([S["E_lsq"][:, 0, 0], S["E_lsq"][:, 1, 1], S["E_lsq"][:, 0, 1]], -1)
        t, ref = r.tracks, S["ref_frame"]
        ok = t.valid[ref] & t.valid[-1]
        X, u = t.xy[ref][ok], t.xy[-1][ok] - t.xy[ref][ok]
        A = np.column_stack([np.ones(len(X)), X])
        res = (u - A @ np.linalg.lstsq(A, u, rcond=None)[0]) * np.sqrt(len(X) / (len(X) - 3))
        out["sigma"] = (Ec - true_part, S["E_lsq_sigma"], res, t.sigma_px[ref][ok])
        for name, E in (("dense", S["E"]), ("triangles", S["E_tri"]), ("local LSQ", S["E_lsq"])):
            axes = tuple(range(E.ndim - 2))
            m = np.nanmedian(E, axis=axes)
            out[name] = np.array([m[0, 0], m[1, 1], m[0, 1]])
        return true_part, out, S["ref_frame"], len(S["pts_px"])


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--methods", nargs="+", default=["lk", "subset"], choices=["lk", "subset", "sized"])
    args = ap.parse_args()
    print("| seed | method | tracks (ref frame) | strain | Exx truth / measured / error | "
          "Eyy truth / measured / error | Exy truth / measured / error |")
    print("|---|---|---|---|---|---|---|")
    calib = []
    for seed in range(args.seeds):
        for method in args.methods:
            true, out, ref, n = run(method=method, seed=seed)
            calib.append((seed, method, *out.pop("sigma")))
            for name, m in out.items():
                cells = [f"{true[k]:.5f} / {m[k]:.5f} / {abs(m[k] / true[k] - 1) * 100:.1f} %"
                         for k in range(3)]
                print(f"| {seed} | {method} | {n} ({ref}) | {name} | " + " | ".join(cells) + " |")
    print("\n| seed | method | points | component | median σ | RMS error | RMS error/σ | within 2σ |")
    print("|---|---|---|---|---|---|---|---|")
    for seed, method, err, sig, res, sig_px in calib:
        ok = np.isfinite(err).all(axis=1) & np.isfinite(sig).all(axis=1) & (sig > 0).all(axis=1)
        for k, comp in enumerate(("Exx", "Eyy", "Exy")):
            e, sg = err[ok, k], sig[ok, k]
            print(f"| {seed} | {method} | {int(ok.sum())} | {comp} | {np.median(sg):.2e} | "
                  f"{np.sqrt(np.mean(e ** 2)):.2e} | {np.sqrt(np.mean((e / sg) ** 2)):.2f} | "
                  f"{np.mean(np.abs(e) <= 2 * sg):.2f} |")
        for k, comp in enumerate(("track x (px)", "track y (px)")):
            e, sg = res[:, k], sig_px
            print(f"| {seed} | {method} | {len(e)} | {comp} | {np.median(sg):.4f} | "
                  f"{np.sqrt(np.mean(e ** 2)):.4f} | {np.sqrt(np.mean((e / sg) ** 2)):.2f} | "
                  f"{np.mean(np.abs(e) <= 2 * sg):.2f} |")


if __name__ == "__main__":
    main()
