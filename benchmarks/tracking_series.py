"""The series chain of ``semlab run`` (tracking, then strain) on low-texture and real-texture series.

Run:  python benchmarks/tracking_series.py [--cases polished,real:fei,real:quartz]
      [--configs "default;lk;default, corners only"] [--drift]

Each case is an 8-frame 384×512 frontal series with the deformation growing over the cycles
(:mod:`semlab.synth`'s schedule: slip bands plus a uniform strain of 1 % / −0.5 % / 0.4 %),
realistic detector noise (shot noise, gain/offset, 8 bit):

- ``polished``: :mod:`semlab.synth`'s polished-metal texture, frame 0 at 30 % texture contrast
  (the early frames of a fatigue test are nearly featureless);
- ``real:fei`` / ``real:quartz``: a real SEM image carried by the same displacement field
  (:mod:`semlab.realtex`), the real texture throughout.

``--drift``: every frame but the last also shifted by up to 20 px, rotated by up to 0.5° and
re-magnified by up to 0.2 % (stage drift).

The chain is what :class:`semlab.Analysis` runs (``series.run_tracking`` with the
configuration's ``track_method`` / ``track_target``, then ``series.run_strain``) on a
series-only experiment (Shi–Tomasi seeds in the last frame). ``default`` is
:class:`semlab.AnalysisConfig`'s default (since 2026-12-02: subsets sized by their
information, ``track_target_sigma_px=0.02``, with which ``run_tracking`` also seeds a grid
where the texture allows valid steps and the steps' σ count the model error, see
``track_reverse``'s ``max_sigma_px`` and ``model_neighbours``), ``lk`` the former default
(pyramidal Lucas–Kanade on the corners), ``default, corners only`` the default without the
grid, ``default, up to 57 px`` / ``up to 81 px`` the default with larger sized subsets
(``track_reverse(max_half_window=28 / 40)``; the default stops at 41 px). The truth of every track comes from the scene's own
displacement field at the seed (end-state) position; the strain's truth is the Green–Lagrange
strain from the reference frame the run chose to the end, ``F = (I − (1 − f_r) ∂U/∂x)⁻¹``.

Printed per case and configuration: tracks, valid fraction per frame (F-2 = one step back
from the end), RMS / max error of the valid steps of frames 0..F-2, how many valid steps are
more than 0.5 px off, the RMS of |error| / (√2 σ) over those steps (1 where the steps' per-axis 1σ holds; σ is the larger of x and y), the strain's reference frame, and the strain error (median of the
measured component against the median of the truth at the same points, the RMS of the
point-wise error, and the RMS error against the same estimator, gauge and window applied to
the true motion: what a perfect tracker would give, for the sparse local least squares and
the dense grid).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from semlab import AnalysisConfig, experiment, realtex, series, synth
from semlab.errors import SemlabError

STRAIN = (0.01, -0.005, 0.004)
#: name -> (AnalysisConfig fields, extra keywords of series.run_tracking)
CONFIGS = {"default": ({}, {}),
           "lk": ({"track_method": "lk"}, {}),
           "default, corners only": ({}, {"grid_kw": None}),
           "default, up to 57 px": ({}, {"track_kw": {"max_half_window": 28}}),
           "default, up to 81 px": ({}, {"track_kw": {"max_half_window": 40}})}


def make_case(case, out, seed=0, drift=False, n_frames=8):
    """Write the case's experiment folder; returns (experiment.toml, scene)."""
    kw = dict(seed=seed, tilts_deg=(), n_frames=n_frames, detector="realistic", progress=False)
    if drift:
        kw.update(drift_shift_px=20.0, drift_rotation_deg=0.5, drift_scale=0.002)
    if case.startswith("real:"):
        src = case[5:]
        toml = realtex.make_experiment(out, source=src, uniform_strain=STRAIN, **kw)
        scene, _ = realtex.make_real_scene(src, seed=seed, uniform_strain=STRAIN)
    else:
        scene = synth.make_scene(seed=seed, size=(384, 512), texture=case, uniform_strain=STRAIN)
        toml = synth.make_experiment(out, scene=scene, **kw)
    return toml, scene


def true_positions(scene, exp_dir, seeds_last_px, shape):
    """(F, N, 2) true positions (frame pixels, drift included) of last-frame points."""
    import json

    info = json.loads((Path(exp_dir) / "truth" / "scene.json").read_text())
    c = synth.image_center(shape)
    xy_um = (np.asarray(seeds_last_px, float) - c) * scene.pixel_size_um
    out = []
    drift_csv = Path(exp_dir) / "truth" / "drift.csv"
    drifts = None
    if drift_csv.is_file():
        import csv
        with open(drift_csv) as fh:
            drifts = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(fh)]
    for n, f in enumerate(info["f"]):
        p = synth.frame_positions(scene, xy_um, 1.0 - f, shape)
        if drifts is not None:
            p = synth.drifted_positions(drifts[n], p, shape)
        out.append(p)
    return np.stack(out)


def true_green_lagrange(scene, pts_last_px, frac_left, shape, h_um=1e-3):
    """(N, 2, 2) Green–Lagrange strain from a frame with ``frac_left`` of U still to come to the
    end, at last-frame pixels."""
    c = synth.image_center(shape)
    x, y = ((np.asarray(pts_last_px, float) - c) * scene.pixel_size_um).T
    G = np.zeros((len(x), 2, 2))
    for j, (dx, dy) in enumerate(((h_um, 0.0), (0.0, h_um))):
        up = np.stack(scene.displacement(x + dx, y + dy), -1)
        um = np.stack(scene.displacement(x - dx, y - dy), -1)
        G[:, :, j] = (up - um) / (2 * h_um)
    Fm = np.linalg.inv(np.eye(2) - frac_left * G)
    return 0.5 * (np.einsum("nki,nkj->nij", Fm, Fm) - np.eye(2))


def _components(E):
    return np.stack([E[..., 0, 0], E[..., 1, 1], E[..., 0, 1]], -1)


def strain_errors(S, scene, f_frac, shape, true_ref_px=None, true_end_px=None):
    """Per component: (truth median, measured median, RMS point-wise error, RMS error against
    the estimator on the true motion) for sparse and dense."""
    from semlab import strain as st

    frac = 1.0 - f_frac[S["ref_frame"]]
    s_um = scene.pixel_size_um
    out = {}
    pts = S["pts_px"]
    gx, gy = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    # the estimators on the true motion (same gauge / window): a perfect tracker's strain
    G = st.gradient_local_lsq(true_ref_px * s_um, (true_end_px - true_ref_px) * s_um,
                              S["gauge_length_um"])
    est_sparse = st.green_lagrange(G)
    cxy = (grid - synth.image_center(shape)) * s_um
    U = frac * np.stack(scene.displacement(cxy[:, 0], cxy[:, 1]), -1)
    Gd = st.gradient_from_field(U[:, 0].reshape(gx.shape), U[:, 1].reshape(gx.shape),
                                (S["grid_x_px"][1] - S["grid_x_px"][0]) * s_um,
                                window=st.DENSE_WINDOW)
    Fd = np.linalg.inv(np.eye(2) - Gd.reshape(-1, 2, 2))
    est_dense = 0.5 * (np.einsum("nki,nkj->nij", Fd, Fd) - np.eye(2))
    for name, E, p, e0 in (("sparse LSQ", S["E_lsq"], pts, est_sparse),
                           ("dense", S["E"].reshape(-1, 2, 2), grid, est_dense)):
        m = _components(E)
        t = _components(true_green_lagrange(scene, p, frac, shape))
        g = _components(e0)
        ok = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(g), axis=1)
        out[name] = [(float(np.median(t[ok, k])), float(np.median(m[ok, k])),
                      float(np.sqrt(np.mean((m[ok, k] - t[ok, k]) ** 2))),
                      float(np.sqrt(np.mean((m[ok, k] - g[ok, k]) ** 2)))) for k in range(3)]
        out[name + " n"] = int(ok.sum())
    return out


def nonaffine_px(scene, pts_last_px, side_px, frac_left, shape):
    """Largest departure (px) of the true displacement still to come from an affine map over
    each step's square subset (``side_px`` wide, centred on its last-frame point): how far
    the motion inside the subset is from what an affine subset can follow (slip bands)."""
    c = synth.image_center(shape)
    s_um = scene.pixel_size_um
    out = np.full(len(pts_last_px), np.nan)
    for i, (p, side, fr) in enumerate(zip(np.asarray(pts_last_px, float), side_px, frac_left)):
        g = np.arange(-(int(side) // 2), int(side) // 2 + 1, 2.0)
        X, Y = np.meshgrid(g, g)
        X, Y = X.ravel() + p[0], Y.ravel() + p[1]
        U = fr * np.stack(scene.displacement((X - c[0]) * s_um, (Y - c[1]) * s_um), 1) / s_um
        A = np.column_stack([np.ones_like(X), X - p[0], Y - p[1]])
        res = U - A @ np.linalg.lstsq(A, U, rcond=None)[0]
        out[i] = np.sqrt((res ** 2).sum(1)).max()
    return out


def run_case(case, config, seed=0, drift=False, nonaffine=False):
    fields, extra = CONFIGS[config]
    cfg = AnalysisConfig(**fields)
    with tempfile.TemporaryDirectory() as tmp:
        toml, scene = make_case(case, Path(tmp) / "e", seed=seed, drift=drift)
        exp = experiment.load(toml)
        kw = {} if cfg.track_target is None else {"target_sigma_px": float(cfg.track_target)}
        kw.update(extra.get("track_kw", {}))
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True):
                warnings.simplefilter("always")
                r = series.run_tracking(exp, method=cfg.track_method, track_kw=kw or None,
                                        grid_kw=extra.get("grid_kw", "auto"),
                                        progress=False)
        except SemlabError as exc:
            return {"case": case + (" +drift" if drift else ""), "config": config,
                    "error": f"tracking failed: {exc}", "t_track": time.perf_counter() - t0}
        t_track = time.perf_counter() - t0
        tr = r.tracks
        shape = exp.frames(progress=False)[-1].shape
        true = true_positions(scene, Path(tmp) / "e", tr.xy[-1], shape)
        err = np.linalg.norm(tr.xy - true, axis=2)
        v = tr.valid[:-1]
        e = err[:-1][v]
        res = {"case": case + (" +drift" if drift else ""), "config": config, "tracks": tr.n_tracks,
               "valid": np.round(tr.valid.mean(1), 2).tolist(), "f2": float(tr.valid[-2].mean()),
               "rms": float(np.sqrt(np.mean(e ** 2))) if len(e) else np.nan,
               "max": float(e.max()) if len(e) else np.nan, "n_bad": int((e > 0.5).sum()),
               "n_valid": int(v.sum()), "t_track": t_track,
               # honesty of the steps' 1σ (per axis, the larger of x and y): RMS of
               # |error| / (√2 σ) over the valid steps, 1 for a 2-D error with that σ per axis
               "z_rms": float(np.sqrt(np.mean((e / tr.sigma_px[:-1][v]) ** 2) / 2))
               if len(e) else np.nan}
        f_frac = np.asarray(synth._series_schedule(tr.n_frames)[1])
        if nonaffine and tr.subset_px is not None:
            kk, ii = np.nonzero(v)
            na = nonaffine_px(scene, tr.xy[-1][ii], tr.subset_px[kk, ii], 1.0 - f_frac[kk], shape)
            res["nonaffine"] = [(lo, hi, int(m.sum()), float(np.sqrt(np.mean(e[m] ** 2))),
                                 int((e[m] > 0.5).sum()))
                                for lo, hi in ((0, 0.1), (0.1, 0.3), (0.3, 1.0), (1.0, np.inf))
                                for m in [(na >= lo) & (na < hi)] if m.any()]
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings(record=True):
                warnings.simplefilter("always")
                S = series.run_strain(exp, r)
        except SemlabError as exc:
            res["strain"] = f"error: {exc}"
        else:
            res["ref_frame"] = S["ref_frame"]
            ok = (tr.valid[S["ref_frame"]] & tr.valid[-1]
                  & np.all(np.isfinite(tr.xy[S["ref_frame"]]), axis=1))
            res["strain"] = strain_errors(S, scene, f_frac, shape,
                                          true[S["ref_frame"]][ok], true[-1][ok])
        res["t_strain"] = time.perf_counter() - t0
        return res


def _fmt_strain(s):
    if isinstance(s, str):
        return s.replace("|", "/")
    parts = []
    for name in ("sparse LSQ", "dense"):
        c = " ".join(f"{lab} {t:+.4f}/{m:+.4f} (rms {r:.4f}; {g:.4f})"
                     for lab, (t, m, r, g) in zip(("Exx", "Eyy", "Exy"), s[name]))
        parts.append(f"{name} [{s[name + ' n']}]: {c}")
    return "; ".join(parts)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--cases", default="polished,real:fei,real:quartz")
    ap.add_argument("--configs", default=";".join(CONFIGS), help="separated by ';'")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--drift", action="store_true")
    ap.add_argument("--nonaffine", action="store_true",
                    help="also print the valid steps binned by how far the true motion inside "
                         "their subset departs from affine (px): count, RMS error, > 0.5 px")
    args = ap.parse_args()
    print("| case | config | tracks | valid per frame 0..F-1 | valid at F-2 | RMS / max error of "
          "valid steps 0..F-2 (px), RMS |error| / (√2 σ) | valid steps > 0.5 px | strain ref frame | strain: truth / "
          "measured median (RMS error against the point-wise truth; against the same estimator "
          "on the true motion) | s (track + strain) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        for config in args.configs.split(";"):
            r = run_case(case, config, seed=args.seed, drift=args.drift, nonaffine=args.nonaffine)
            if "error" in r:
                print(f"| {r['case']} | {config} | - | {r['error']} | 0 | - | - | - | no strain |"
                      f" {r['t_track']:.0f} |", flush=True)
                continue
            print(f"| {r['case']} | {config} | {r['tracks']} | {r['valid']} | {r['f2']:.2f} | "
                  f"{r['rms']:.3f} / {r['max']:.3f} ({r['n_valid']} steps), {r['z_rms']:.2f} | {r['n_bad']} | "
                  f"{r.get('ref_frame', '-')} | {_fmt_strain(r['strain'])} | "
                  f"{r['t_track']:.0f} + {r['t_strain']:.0f} |", flush=True)
            for lo, hi, n, rms, nb in r.get("nonaffine", []):
                print(f"|  | non-affine motion in the subset {lo:g}–{hi:g} px | {n} steps | "
                      f"RMS {rms:.3f} px | {nb} > 0.5 px |", flush=True)


if __name__ == "__main__":
    main()
