"""Accuracy and speed of semlab.tracking (reverse-time tracking) on data with known answers.

(a) DIC Challenge 1.0 sample 5: uniform shift of 0.10 px in x and y between
    ``Sample5 Reference.tif`` and ``Sample5-001 X0.10 Y0.10 N2 C100 R20.tif`` (raw files,
    different contrast), frames = [reference, shifted] so the series is tracked from the
    shifted image back to the reference;
(b) DIC Challenge rotation set: CG_000 .. CG_360 every 20° about the image centre, tracked
    from CG_000 through increasing angles (the largest angle is the reference);
(c) speed of LK and IC-GN subset tracking, points per second per frame step;
(d) the synthetic series of semlab.synth (true material-point positions per frame).

In-script references (``reference_trackers.py``): OpenCV DeepFlow, DIS medium and DIS fine
at the same seeds in (a) and (d), flow from the last frame to each frame directly; in (d)
the RMS error of semlab's valid steps is set against the references' at the same steps.

Run: ``.venv/bin/python benchmarks/tracking_accuracy.py`` from the project root. Prints
markdown tables. Data are looked up in ../shared/data next to the project root.
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from semlab.tracking import TrackingWarning, shi_tomasi_seeds, track_reverse

from reference_trackers import reference_tracks, rms

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "dic_challenge"

warnings.simplefilter("ignore", TrackingWarning)


def _read(p):
    import tifffile
    return tifffile.imread(str(p)).astype(np.float64)


def sample5(rows, speed):
    d = DATA / "sample5"
    ref_p, cur_p = d / "Sample5 Reference.tif", d / "Sample5-001 X0.10 Y0.10 N2 C100 R20.tif"
    if not (ref_p.exists() and cur_p.exists()):
        print(f"(a) skipped: {d} not found")
        return
    ref, cur = _read(ref_p), _read(cur_p)
    seeds = shi_tomasi_seeds(cur, border_px=25)
    true = np.array([0.10, 0.10])                 # material displacement reference -> 001
    for method, kw in (("lk", {}), ("subset", {}), ("subset", {"subset_half_window": 15}),
                       ("subset", {"target_sigma_px": 0.005})):
        t0 = time.perf_counter()
        tr = track_reverse([ref, cur], seeds, method=method, progress=False, **kw)
        dt = time.perf_counter() - t0
        v = tr.valid[0]
        d_ = tr.xy[1, v] - tr.xy[0, v]
        e = d_ - true
        label = method + (f" (target σ {kw['target_sigma_px']} px, h 10-20, 0.8 px smoothing)"
                          if "target_sigma_px" in kw else
                          f" (h={kw['subset_half_window']})" if kw else
                          (" (h=10)" if method == "subset" else " (win 21)"))
        rows.append((f"(a) sample 5, {label}", len(seeds), f"{v.mean():.3f}",
                     f"{np.sqrt(np.mean(e[:, 0] ** 2)):.4f} / {np.sqrt(np.mean(e[:, 1] ** 2)):.4f}",
                     f"{np.sqrt(np.mean(np.sum(e ** 2, 1))):.4f}",
                     f"mean bias ({e[:, 0].mean():+.4f}, {e[:, 1].mean():+.4f}) px"))
        speed.append((f"sample 5 512x512, {label}", len(seeds), 1, dt, len(seeds) / dt))
    # in-script references at the same seeds (dense flow, no validity: every seed)
    ref_tracks = reference_tracks([ref, cur], seeds)
    for name, q in ref_tracks.items():
        e = (seeds - q[0]) - true
        rows.append((f"(a) sample 5, {name} (reference)", len(seeds), "-",
                     f"{np.sqrt(np.mean(e[:, 0] ** 2)):.4f} / {np.sqrt(np.mean(e[:, 1] ** 2)):.4f}",
                     f"{np.sqrt(np.mean(np.sum(e ** 2, 1))):.4f}",
                     f"mean bias ({e[:, 0].mean():+.4f}, {e[:, 1].mean():+.4f}) px; all seeds"))


def _rot(pts, c, deg):
    t = np.deg2rad(deg)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    return (pts - c) @ R.T + c


def rotation(rows):
    from semlab.tracking import _sample_patches, normalize_frame

    d = DATA / "rotation"
    files = sorted(d.glob("CG_*.tif"))
    if len(files) < 3:
        print(f"(b) skipped: {d} not found")
        return
    angles = [int(f.stem.split("_")[1]) for f in files]
    imgs = [_read(f) for f in files]
    h, w = imgs[0].shape
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    seeds = shi_tomasi_seeds(imgs[0], quality=0.05, border_px=15)
    # Sense of the rotation in (x right, y down) pixels: the one whose prediction matches.
    a0, _ = normalize_frame(imgs[0])
    a1, _ = normalize_frame(imgs[angles.index(20)])
    p0 = _sample_patches(a0, seeds, 2).reshape(len(seeds), -1)
    score = {}
    for sgn in (1, -1):
        p1 = _sample_patches(a1, _rot(seeds, c, sgn * 20), 2).reshape(len(seeds), -1)
        with np.errstate(invalid="ignore", divide="ignore"):
            score[sgn] = np.nanmedian([np.corrcoef(u, v)[0, 1] for u, v in zip(p0, p1)])
    sgn = max(score, key=score.get)
    # The reference (last frame) is CG_000 and time runs from the largest angle to 0°, so
    # the tracker meets 20°, 40°, ... in turn. The image holds three near-copies of one
    # speckled patch about 120° apart (CG_120 correlates with CG_000 at 0.69), so a track
    # re-acquired after a long gap may lock onto a look-alike.
    for max_angle in (20, 40, 60, 340):
        sel = [i for i, a in enumerate(angles) if a <= max_angle][::-1]
        frames = [imgs[i] for i in sel]
        ang = [angles[i] for i in sel]
        for method in ("lk", "subset"):
            name = f"(b) rotation 0..{max_angle}° (20°/step), {method}"
            try:
                # up to 45 px motion per 20° step here: allow it (default bound is win_size)
                tr = track_reverse(frames, seeds, method=method, progress=False, max_jump_px=150)
            except Exception as exc:          # TrackingError when nothing survives
                rows.append((name, len(seeds), "0.000", "-", "-",
                             f"{type(exc).__name__}: every track lost at the first step "
                             "(flagged, none valid)"))
                continue
            err = np.array([np.linalg.norm(tr.xy[k] - _rot(seeds, c, sgn * a), axis=1)
                            for k, a in enumerate(ang)])
            v = tr.valid.copy()
            v[-1] = False
            bad = v & (err > 0.5)
            starts = ""
            if bad.any():
                # first wrong valid step of each wrong track, in processing (reverse) order
                first_gap = [tr.gap_frames[np.flatnonzero(bad[:, j]).max(), j]
                             for j in np.flatnonzero(bad.any(axis=0))]
                starts = (f" on {len(first_gap)} tracks, each starting with a re-acquisition "
                          f"after a gap of >= {min(first_gap)} frames" if min(first_gap) > 0
                          else f" on {len(first_gap)} tracks (some without a gap)")
            frac = ", ".join(f"{a}°: {tr.valid[k].mean():.2f}" for k, a in enumerate(ang)
                             if a > 0 and (tr.valid[k].any() or a <= 60))
            rows.append((name, len(seeds), f"{v[:-1].mean():.3f}", "-",
                         f"{np.sqrt(np.mean(err[v] ** 2)):.3f}" if v.any() else "-",
                         f"valid fraction by angle {frac}; valid steps with error > 0.5 px: "
                         f"{int(bad.sum())}{starts}"))


def synthetic(rows, speed):
    try:
        from semlab.experiment import load
        from semlab.synth import make_experiment
    except ImportError as exc:
        print(f"(d) skipped: {exc}")
        return
    import csv
    for scene_seed in (0, 1, 2):
        _synthetic_scene(rows, speed, scene_seed, load, make_experiment, csv)


def _synthetic_scene(rows, speed, scene_seed, load, make_experiment, csv):
    with tempfile.TemporaryDirectory() as tmp:
        toml = make_experiment(Path(tmp) / "exp", seed=scene_seed, tilts_deg=(), n_frames=6,
                               progress=False)
        exp = load(toml)
        frames = exp.frames()
        with open(Path(tmp) / "exp" / "truth" / "points.csv") as fh:
            pts = list(csv.DictReader(fh))
        F = len(frames)
        true = np.array([[[float(p[f"f{k}_x_px"]), float(p[f"f{k}_y_px"])] for p in pts]
                         for k in range(F)])
        h, w = frames[0].shape
        m = 15
        inside = np.all((true[..., 0] > m) & (true[..., 0] < w - 1 - m) & (true[..., 1] > m)
                        & (true[..., 1] < h - 1 - m), axis=0)
        true = true[:, inside]
        seeds = true[-1]
        st = shi_tomasi_seeds(frames[-1])
        ref_err = {name: np.linalg.norm(q - true, axis=2)
                   for name, q in reference_tracks(frames, seeds).items()}
        for method, kw in (("lk", {}), ("subset", {}), ("subset", {"target_sigma_px": 0.02})):
            t0 = time.perf_counter()
            tr = track_reverse(frames, seeds, method=method, progress=False, **kw)
            dt = time.perf_counter() - t0
            err = np.linalg.norm(tr.xy - true, axis=2)
            v0 = tr.valid[0]
            label = method + (f" (target σ {kw['target_sigma_px']} px, h 10-20, 0.8 px "
                              "smoothing)" if kw else "")
            rows.append((f"(d) synth series seed {scene_seed} ({F} frames {w}x{h}), {label}",
                         len(seeds),
                         f"{tr.valid[:-1].mean():.3f} (frame 0: {v0.mean():.3f})", "-",
                         f"{np.sqrt(np.mean(err[0][v0] ** 2)):.3f}" if v0.any() else "-",
                         f"valid steps with error > 0.5 px: {int((tr.valid & (err > 0.5)).sum())}; "
                         f"valid fraction per frame {np.round(tr.valid.mean(1), 2).tolist()}; "
                         "RMS error of valid steps per frame "
                         f"{[round(float(np.sqrt(np.mean(err[k][tr.valid[k]] ** 2))), 3) if tr.valid[k].any() else None for k in range(F)]}; "
                         "RMS error of all tracks (valid or not) per frame "
                         f"{[round(float(np.sqrt(np.nanmean(err[k] ** 2))), 3) for k in range(F)]}; "
                         "on the valid steps of frames 0..F-2, semlab "
                         f"{rms(err[:-1], tr.valid[:-1]):.3f} px vs "
                         + ", ".join(f"{name} {rms(e[:-1], tr.valid[:-1]):.3f}"
                                     for name, e in ref_err.items())
                         + " (ratio to the best "
                         f"{rms(err[:-1], tr.valid[:-1]) / min(rms(e[:-1], tr.valid[:-1]) for e in ref_err.values()):.2f})"))
            t0 = time.perf_counter()
            track_reverse(frames, st, method=method, progress=False, **kw)
            dt = time.perf_counter() - t0
            speed.append((f"synth seed {scene_seed} {w}x{h}, Shi-Tomasi seeds, {label}",
                          len(st), F - 1, dt,
                          len(st) * (F - 1) / dt))
        for name, e in ref_err.items():
            rows.append((f"(d) synth series seed {scene_seed}, {name} (reference)", len(seeds),
                         "-", "-", f"{rms(e[0]):.3f}",
                         "every point (no validity flag), last frame -> frame directly; RMS "
                         f"per frame {[round(rms(e[k]), 3) for k in range(F)]}"))


def main():
    rows, speed = [], []
    sample5(rows, speed)
    rotation(rows)
    synthetic(rows, speed)
    print("## Tracking accuracy\n")
    print("| case | points | valid fraction | RMS error x / y px | RMS error px (valid) | notes |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(x) for x in r) + " |")
    print("\n## Speed (2 shared cores; one step = chained LK + fb + direct match + checks)\n")
    print("| case | points | steps | seconds | points·steps / s |")
    print("|---|---|---|---|---|")
    for s in speed:
        print(f"| {s[0]} | {s[1]} | {s[2]} | {s[3]:.2f} | {s[4]:.0f} |")


if __name__ == "__main__":
    main()
