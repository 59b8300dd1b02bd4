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
- drift recovery: the largest distance over the image between the estimated transform and
  (a) the true stage drift, on a scene without material motion (``slip_um=0``), and
  (b) the least-squares affine of the true point motion (stage drift, scan drift and the
  material's own mean motion, which no image registration can tell apart), on the default
  scene. Target: within 0.1 px.

Run: ``.venv/bin/python benchmarks/drift_accuracy.py`` (about 3 minutes on 2 cores).
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
from semlab.registration import Transform2D, fit_transform, read_drift_csv, register_frames
from semlab.synth import _stage_matrix, make_experiment
from semlab.tracking import TrackingWarning, track_reverse

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


def drift_recovery(seed, F, drift_kw):
    """Largest error over the image of the recovered transforms (px), per frame."""
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        frames, _, folder = _series(tmp, "pure", seed, F, slip_um=0.0, **drift_kw)
        truth = read_drift_csv(folder / "truth" / "drift.csv")
        shape = frames[0].shape
        reg = register_frames(frames, model="affine")
        cols = ("dx_px", "dy_px", "rotation_deg", "scale", "scan_dx_px", "scan_dy_px")
        errs = []
        for k in range(F - 1):
            d = {c: truth[c][k] for c in cols}
            T_true = Transform2D(_stage_matrix(d, shape))
            if not drift_kw.get("scan_drift_px"):
                errs.append(reg.transforms[k].distance(T_true, shape))
        out["pure"] = errs
        frames, true, _ = _series(tmp, "slip", seed, F, **drift_kw)
        reg = register_frames(frames, model="affine")
        ok = _inside(true, shape, 0)
        out["motion"] = [reg.transforms[k].distance(fit_transform(true[-1][ok], true[k][ok], "affine"),
                                                    shape) for k in range(F - 1)]
        out["methods"] = list(reg.method)
    return out


def tracking_case(seed, F, drift_kw, method="subset"):
    with tempfile.TemporaryDirectory() as tmp:
        f_u, t_u, _ = _series(tmp, "undrifted", seed, F)
        f_d, t_d, _ = _series(tmp, "drifted", seed, F, **drift_kw)
    keep = _inside(t_u, f_u[0].shape) & _inside(t_d, f_d[0].shape)
    t_u, t_d = t_u[:, keep], t_d[:, keep]
    rows = {}
    for label, frames, true, reg in (("undrifted, raw", f_u, t_u, None),
                                     ("undrifted, registered", f_u, t_u, "affine"),
                                     ("drifted, raw", f_d, t_d, None),
                                     ("drifted, registered", f_d, t_d, "affine")):
        t0 = time.perf_counter()
        try:
            tr = track_reverse(frames, true[-1], method=method, progress=False, register=reg)
            rows[label] = (*_frame0(tr, true), time.perf_counter() - t0)
        except Exception as exc:            # TrackingError: every track lost
            rows[label] = (0.0, np.nan, 0, time.perf_counter() - t0, type(exc).__name__)
    return int(keep.sum()), rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--shift", type=float, default=30.0)
    ap.add_argument("--rot", type=float, default=1.2)
    ap.add_argument("--scale", type=float, default=0.003)
    ap.add_argument("--scan", type=float, default=0.0)
    ap.add_argument("--method", default="subset")
    a = ap.parse_args()
    drift_kw = dict(drift_shift_px=a.shift, drift_rotation_deg=a.rot, drift_scale=a.scale,
                    scan_drift_px=a.scan)
    print(f"drift: shift up to {a.shift} px, rotation up to {a.rot}°, scale up to {a.scale:.2%}, "
          f"scan drift up to {a.scan} px; {a.frames} frames 512x384; method {a.method}\n")
    print("| seed | points | run | valid at frame 0 | RMS error at frame 0 (px) | valid steps > 0.5 px off | s |")
    print("|---|---|---|---|---|---|---|")
    for seed in (int(s) for s in a.seeds.split(",")):
        n, rows = tracking_case(seed, a.frames, drift_kw, a.method)
        base = rows["undrifted, raw"]
        for label, r in rows.items():
            rel = f" ({r[0] / base[0]:.2f}x)" if base[0] > 0 and label != "undrifted, raw" else ""
            d = f" ({r[1] - base[1]:+.3f})" if label != "undrifted, raw" and np.isfinite(r[1]) else ""
            print(f"| {seed} | {n} | {label} | {r[0]:.3f}{rel} | {r[1]:.3f}{d} | {r[2]} | {r[3]:.1f} |")
    print("\n| seed | recovered drift, largest error over the image (px), frames 0..F-2 | against |")
    print("|---|---|---|")
    for seed in (int(s) for s in a.seeds.split(",")):
        r = drift_recovery(seed, a.frames, drift_kw)
        if r["pure"]:
            print(f"| {seed} | {np.round(r['pure'], 3).tolist()} (max {max(r['pure']):.3f}) | true "
                  "stage drift, scene without material motion |")
        print(f"| {seed} | {np.round(r['motion'], 3).tolist()} (max {max(r['motion']):.3f}) | affine "
              f"fit of the true point motion, default scene; methods {r['methods']} |")


if __name__ == "__main__":
    main()
