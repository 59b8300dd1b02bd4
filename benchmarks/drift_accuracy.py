"""Tracking through stage drift (issue #14 section 1), on synthetic series with known drift.

For each scene seed, the same series (same scene, same noise) is rendered twice by
``semlab.synth.make_experiment``: without drift, and with every frame but the last shifted by
up to ``--shift`` px, rotated by up to ``--rot`` degrees, re-magnified by up to ``--scale``
and, optionally, scan-drifted (a row-dependent shift up to ``--scan`` px over a frame).
The truth material points (``truth/points.csv``, each frame's own pixels) are tracked from
the last frame backwards (subset method) in four ways: undrifted raw, undrifted registered,
drifted raw, drifted registered. Reported:

- valid fraction at frame 0 and the RMS error of the valid steps there, against the
  undrifted raw run (target: fraction >= 0.8x, RMS within 0.02 px);
- drift recovery: the largest distance, over the part of the last frame every drifted frame
  still sees (35 px margin), between the estimated transform and
  (a) the true stage drift, on a scene without material motion (``slip_um=0``);
  (b) the true map of stage drift plus a 3 px scan drift (not affine: 30 % quadratic), with
  the affine model;
  (c) on the default slip-band scene, the true drift composed with the undrifted series'
  own registration (the material's own motion, which no image registration can tell
  apart from drift); (d) on the same scene, the true drift composed with the motion of the
  largest rigidly moving region (the strip between slip bands covering most of the image,
  from ``truth/fields.npz``), over the image and over that strip. Target: within 0.1 px.

In-script references: DeepFlow, DIS medium and DIS fine (``reference_trackers.py``) at the
same points on the undrifted raw and the drifted registered runs (``--no-reference``: skip).

Run: ``.venv/bin/python benchmarks/drift_accuracy.py`` (about 6 minutes on 2 cores).
"""

from __future__ import annotations

import argparse
import csv
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from semlab.experiment import load
from semlab.registration import Transform2D, read_drift_csv, register_frames
from semlab.synth import _stage_matrix, drifted_positions, make_experiment
from semlab.tracking import TrackingWarning, track_reverse

from reference_trackers import REFERENCE_TRACKERS, reference_tracks, rms

warnings.simplefilter("ignore", TrackingWarning)


def _truth(folder, F):
    with open(Path(folder) / "truth" / "points.csv") as fh:
        pts = list(csv.DictReader(fh))
    return np.array([[[float(p[f"f{k}_x_px"]), float(p[f"f{k}_y_px"])] for p in pts]
                     for k in range(F)])


def _series(tmp, name, seed, F, **kw):
    toml = make_experiment(Path(tmp) / name, seed=seed, tilts_deg=(), n_frames=F, progress=False,
                           **kw)
    return load(toml).frames(), _truth(Path(tmp) / name, F), Path(tmp) / name


def _inside(true, shape, m=15):
    h, w = shape
    return np.all((true[..., 0] > m) & (true[..., 0] < w - 1 - m) & (true[..., 1] > m)
                  & (true[..., 1] < h - 1 - m), axis=0)


def _frame0(tr, true):
    v0 = tr.valid[0]
    err = np.linalg.norm(tr.xy[0] - true[0], axis=1)
    rms = float(np.sqrt(np.mean(err[v0] ** 2))) if v0.any() else np.nan
    bad = int((tr.valid & (np.linalg.norm(tr.xy - true, axis=2) > 0.5)).sum())
    return float(v0.mean()), rms, bad


def _grid(shape, margin=35, n=9):
    h, w = shape
    return np.stack(np.meshgrid(np.linspace(margin, w - 1 - margin, n),
                                np.linspace(margin, h - 1 - margin, n)), -1).reshape(-1, 2)


def drift_recovery(seed, F, drift_kw):
    """Largest error (px) of the recovered transforms over the part of the last frame that
    every drifted frame still sees (35 px margin), per frame."""
    cols = ("dx_px", "dy_px", "rotation_deg", "scale", "scan_dx_px", "scan_dy_px")
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        # (a) stage drift alone, no material motion: against the true stage similarity
        frames, _, folder = _series(tmp, "pure", seed, F, slip_um=0.0,
                                    **{**drift_kw, "scan_drift_px": 0.0})
        truth = read_drift_csv(folder / "truth" / "drift.csv")
        shape = frames[0].shape
        g = _grid(shape)
        reg = register_frames(frames, model="similarity")
        out["stage"] = [float(np.linalg.norm(reg.transforms[k](g) - Transform2D(_stage_matrix(
            {c: truth[c][k] for c in cols}, shape))(g), axis=1).max()) for k in range(F - 1)]
        # (b) with scan drift (3 px over a frame, 30 % quadratic): affine model against the
        # true (non-affine) map of stage and scan drift
        frames, _, folder = _series(tmp, "scan", seed, F, slip_um=0.0,
                                    **{**drift_kw, "scan_drift_px": 3.0})
        truth = read_drift_csv(folder / "truth" / "drift.csv")
        reg = register_frames(frames, model="affine")
        out["scan"] = [float(np.linalg.norm(reg.transforms[k](g) - drifted_positions(
            {c: truth[c][k] for c in cols}, g, shape), axis=1).max()) for k in range(F - 1)]
        # (c) the default scene (slip bands): the drifted registration against the true drift
        # composed with the undrifted run's registration (the material's own mean motion)
        f_u, _, _ = _series(tmp, "still", seed, F)
        f_d, _, folder = _series(tmp, "slip", seed, F, **{**drift_kw, "scan_drift_px": 0.0})
        truth = read_drift_csv(folder / "truth" / "drift.csv")
        ru, rd = register_frames(f_u), register_frames(f_d)
        out["slip"] = [float(np.linalg.norm(rd.transforms[k](g) - (Transform2D(_stage_matrix(
            {c: truth[c][k] for c in cols}, shape)) @ ru.transforms[k])(g), axis=1).max())
            for k in range(F - 1)]
        out["methods"] = [str(m) for m in rd.method]
        # (d) the same against the true stage drift composed with the motion of the largest
        # rigidly moving region: the strip between slip bands covering most of the part of
        # the last frame every frame sees (the mode of the true displacement field there)
        fl = np.load(folder / "truth" / "fields.npz")
        xx, yy = np.meshgrid(fl["x_px"], fl["y_px"])
        h, w = shape
        seen = (xx >= 35) & (xx <= w - 36) & (yy >= 35) & (yy <= h - 36)
        key = np.round(np.column_stack([fl["ux_um"][seen], fl["uy_um"][seen]]) / 0.002).astype(int)
        vals, inv, cnt = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        u_px = vals[np.argmax(cnt)] * 0.002 / float(fl["pixel_size_um"])
        strip = np.column_stack([xx[seen], yy[seen]])[inv.ravel() == np.argmax(cnt)]
        out["strip_fraction"] = float(cnt.max() / cnt.sum())
        out["rigid"], out["rigid_in"] = [], []
        for k in range(F - 1):
            true = Transform2D(_stage_matrix({c: truth[c][k] for c in cols}, shape)) @ \
                Transform2D.from_params(*(-(1 - fl["f"][k]) * u_px))
            out["rigid"].append(float(np.linalg.norm(rd.transforms[k](g) - true(g), axis=1).max()))
            out["rigid_in"].append(float(np.linalg.norm(rd.transforms[k](strip) - true(strip),
                                                        axis=1).max()))
    return out


def tracking_case(seed, F, drift_kw, method="subset", reg_model="similarity", with_reference=True):
    with tempfile.TemporaryDirectory() as tmp:
        f_u, t_u, _ = _series(tmp, "undrifted", seed, F)
        f_d, t_d, _ = _series(tmp, "drifted", seed, F, **drift_kw)
    keep = _inside(t_u, f_u[0].shape) & _inside(t_d, f_d[0].shape)
    t_u, t_d = t_u[:, keep], t_d[:, keep]
    rows = {}
    for label, frames, true, reg in (("undrifted, raw", f_u, t_u, None),
                                     ("undrifted, registered", f_u, t_u, "similarity"),
                                     ("drifted, raw", f_d, t_d, None),
                                     ("drifted, registered", f_d, t_d, reg_model)):
        t0 = time.perf_counter()
        try:
            tr = track_reverse(frames, true[-1], method=method, progress=False, register=reg)
            rows[label] = (*_frame0(tr, true), time.perf_counter() - t0, tr.valid[:-1],
                           np.linalg.norm(tr.xy - true, axis=2)[:-1])
        except Exception as exc:            # TrackingError: every track lost
            tr = None
            rows[label] = (0.0, np.nan, 0, time.perf_counter() - t0,
                           np.zeros((F - 1, len(true[0])), bool), np.full((F - 1, len(true[0])), np.nan))
        if with_reference and label in ("undrifted, raw", "drifted, registered"):
            # the dense references at the same points; the drifted frames resampled with the
            # registration semlab tracked with
            ref = reference_tracks(frames, true[-1], None if tr is None else tr.registration)
            rows[label] += ({k: np.linalg.norm(v - true, axis=2)[:-1] for k, v in ref.items()},)
    return int(keep.sum()), rows


def reference_table(refs):
    """semlab's error against the dense references' at the same steps (ratios)."""
    names = " | ".join(REFERENCE_TRACKERS)
    print("\nIn-script reference trackers at the same points and steps (`reference_trackers.py`: "
          "dense flow from the last frame to each frame, drifted frames resampled with semlab's "
          "registration first). RMS error (px) on the steps semlab kept valid, frames 0..F-2, "
          "and semlab / reference; then every point at frame 0 (the references flag nothing)\n")
    print(f"| seed | run | valid steps | semlab | {names} | semlab / best reference | "
          f"frame 0, all points: {names} |")
    print("|---|---|---|---|" + "---|" * len(REFERENCE_TRACKERS) + "---|"
          + "---|" * len(REFERENCE_TRACKERS))
    for seed, rows in refs:
        for label, r in rows.items():
            if len(r) < 7:
                continue
            v, err, ref = r[4], r[5], r[6]
            own = rms(err, v)
            others = [rms(ref[k], v) for k in REFERENCE_TRACKERS]
            best = np.nanmin(others) if np.isfinite(others).any() else np.nan
            f0 = [rms(ref[k][0]) for k in REFERENCE_TRACKERS]
            print(f"| {seed} | {label} | {int(v.sum())} | {own:.3f} | "
                  + " | ".join(f"{x:.3f}" for x in others) + f" | {own / best:.2f} | "
                  + " | ".join(f"{x:.3f}" for x in f0) + " |")


def figure(path, F, drift_kw):
    """plot_drift of a registered synthetic series against its truth."""
    import matplotlib

    matplotlib.use("Agg")
    from semlab.plots import plot_drift

    with tempfile.TemporaryDirectory() as tmp:
        frames, _, folder = _series(tmp, "fig", 0, F, slip_um=0.0, **drift_kw)
        reg = register_frames(frames)
        fig = plot_drift(reg, truth=read_drift_csv(folder / "truth" / "drift.csv"))
    fig.savefig(path, dpi=90)
    print("wrote", path)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--shift", type=float, default=30.0)
    ap.add_argument("--rot", type=float, default=1.2)
    ap.add_argument("--scale", type=float, default=0.003)
    ap.add_argument("--scan", type=float, default=0.0, help="scan drift of the tracked series, px")
    ap.add_argument("--model", default="similarity")
    ap.add_argument("--method", default="subset")
    ap.add_argument("--figure", help="write the README drift figure (seed 0) to this PNG and stop")
    ap.add_argument("--tracking-only", action="store_true", help="skip the drift-recovery table")
    ap.add_argument("--no-reference", action="store_true",
                    help="skip the in-script reference trackers (DeepFlow, DIS)")
    a = ap.parse_args()
    if a.figure:
        return figure(a.figure, a.frames, dict(drift_shift_px=a.shift, drift_rotation_deg=a.rot,
                                               drift_scale=a.scale, scan_drift_px=a.scan))
    seeds = [int(s) for s in a.seeds.split(",")]
    drift_kw = dict(drift_shift_px=a.shift, drift_rotation_deg=a.rot, drift_scale=a.scale,
                    scan_drift_px=a.scan)
    print(f"drift: shift up to {a.shift} px, rotation up to {a.rot}°, scale up to {a.scale:.2%}, "
          f"scan drift up to {a.scan} px; {a.frames} frames 512x384; tracking {a.method}, "
          f"registration {a.model}\n")
    print("| seed | points | run | valid at frame 0 | RMS error at frame 0 (px) | valid per frame "
          "0..F-2 | RMS on the steps valid in this run and the undrifted raw one, frames 0..F-2 (px) "
          "| valid steps > 0.5 px off | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    refs = []
    for seed in seeds:
        n, rows = tracking_case(seed, a.frames, drift_kw, a.method, a.model,
                                not a.no_reference)
        refs.append((seed, rows))
        base = rows["undrifted, raw"]
        for label, r in rows.items():
            rel = f" ({r[0] / base[0]:.2f}x)" if base[0] > 0 and label != "undrifted, raw" else ""
            d = f" ({r[1] - base[1]:+.3f})" if label != "undrifted, raw" and np.isfinite(r[1]) else ""
            both = r[4] & base[4]
            if label != "undrifted, raw" and both[0].any():
                # frame 0 on the tracks valid there in both runs (the sets above differ)
                e1, e0 = (rms(x[0], both[0]) for x in (r[5], base[5]))
                d += f"; on the {both[0].sum()} common: {e1:.3f} vs {e0:.3f} ({e1 - e0:+.3f})"
            common = "-"
            if label != "undrifted, raw" and both.any():
                e1, e0 = (np.sqrt(np.mean(x[both] ** 2)) for x in (r[5], base[5]))
                common = f"{e1:.3f} vs {e0:.3f} ({e1 - e0:+.3f}, {both.sum()} steps)"
            per = np.round(r[4].mean(axis=1), 2).tolist()
            print(f"| {seed} | {n} | {label} | {r[0]:.3f}{rel} | {r[1]:.3f}{d} | {per} | {common} "
                  f"| {r[2]} | {r[3]:.1f} |")
    if not a.no_reference:
        reference_table(refs)
    if a.tracking_only:
        return
    print("\n| seed | case | largest error over the image (px), frames 0..F-2 | max |")
    print("|---|---|---|---|")
    for seed in seeds:
        r = drift_recovery(seed, a.frames, drift_kw)
        for key, name in (("stage", "stage drift alone (no material motion), similarity, vs the true drift"),
                          ("scan", "stage + 3 px scan drift, affine, vs the true non-affine map"),
                          ("slip", "slip-band scene: drifted registration vs true drift @ undrifted "
                                   f"registration; methods {r['methods']}"),
                          ("rigid", "slip-band scene: drifted registration vs true drift @ motion of "
                                    f"the largest rigid strip ({r['strip_fraction']:.0%} of the "
                                    "image), over the image"),
                          ("rigid_in", "same, over that strip only")):
            print(f"| {seed} | {name} | {np.round(r[key], 3).tolist()} | {max(r[key]):.3f} |")


if __name__ == "__main__":
    main()
