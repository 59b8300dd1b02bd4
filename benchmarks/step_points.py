"""Where the automatic heights are worst, whether a step of the parallax is visible there,
and what shiftable windows would gain (issue #13; the opt-in ``auto_match(step_windows=True)``
that applied them was measured negative and removed, docs/accuracy.md, "Points beside
slip-band steps").

Run:  python benchmarks/step_points.py                       # the 5 cells below (~3 min)
      python benchmarks/step_points.py --cells polished/realistic/-5/5

Per accuracy-matrix cell (``benchmarks/accuracy_matrix.py``'s scenes, seed 0, 384×512 px),
at the points semlab's automatic matching accepts with total-error sizing
(``target_sigma_px=0, curvature_neighbours=1``, the matrix's ``auto total``):

1. **where**: semlab's and DeepFlow's height RMSE (nm, plane of the error removed) on the
   worst 5 % of semlab's points (their share of semlab's squared error), on the points
   with a steep true height (max |∇z| > 5 nm/px within 10 px: beside a slip band) and on
   the rest;
2. **visible**: the residual ratio (residual variance over the noise's) of a centred 21×21
   IC-GN subset at those points, median and fraction above 1.5 (the removed step windows'
   trigger);
3. **gain**: the same subset displaced by ``h`` (and ``h/2``) in 8 directions: the error of
   the oracle choice among the 9 windows (the truth picks; an upper bound, which also picks
   the luckiest noise), of the smallest residual ratio, and of the removed step windows'
   rule (a displaced window only where the centred ratio > 1.5 and the displaced one is
   below 0.7× it).

Heights of the 21×21 windows (step 2-3) are scored with the median error removed (no plane),
so their RMSE is comparable between windows, not to step 1's.
Writes ``benchmarks/results/step_points.md`` and prints it.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

from semlab import reconstruct, validation  # noqa: E402
from semlab.subset import icgn_refine, prefilter_image  # noqa: E402

CELLS = ("polished/realistic/-5/5", "polished/realistic/0/8", "real:fei/realistic/-5/5",
         "real:quartz/low/-5/5", "speckle/low/-5/5")


def _rms(a):
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a ** 2))) if len(a) else np.nan


def _heights(exp, tilts, p0, p1):
    """(N,) heights (µm) of matches p0 -> p1, NaN where unmatched."""
    pts = np.stack([p0, p1], 1)
    ok = np.all(np.isfinite(pts.reshape(len(pts), -1)), 1)
    z = np.full(len(pts), np.nan)
    z[ok] = reconstruct.heights_from_tilts(pts[ok], list(tilts), exp.pixel_size_um).xyz_um[:, 2]
    return z


def _plane_errors(exp, tilts, pts):
    z = _heights(exp, tilts, pts[:, 0], pts[:, 1])
    zt = validation.true_height_at(exp.truth_dir, pts[:, 0])
    return 1000 * validation.height_errors(z, zt, pts[:, 0])["err_um"]


def shifted_offsets(half_window, shift_px, angle_deg):
    """(P, 2) int ``(dx, dy)`` offsets, ``P = (2h+1)²``, of a square subset whose centre is
    ``shift_px`` from the point in the direction ``angle_deg`` (from +x toward +y), for
    ``icgn_refine(subset_offsets=...)``."""
    h = int(half_window)
    a = np.deg2rad(angle_deg)
    c = np.rint([shift_px * np.cos(a), shift_px * np.sin(a)]).astype(int)
    oy, ox = np.mgrid[-h:h + 1, -h:h + 1]
    return np.stack([ox.ravel() + c[0], oy.ravel() + c[1]], 1)


def windows(v0, v1, p0, guess, h=10, shift_frac=1.0, smooth_sigma_px=0.8):
    """Centred and 8 displaced (2h+1)² windows at ``p0``: (9, N) matched x-y positions,
    residual ratios (inf where not converged) and x σ; the noise of the centred run for all."""
    rc, cc = prefilter_image(v0, smooth_sigma_px), prefilter_image(v1, smooth_sigma_px)
    kw = dict(half_window=h, smooth_sigma_px=smooth_sigma_px, ref_prefiltered=rc,
              cur_prefiltered=cc)
    r0 = icgn_refine(v0, v1, p0, guess, **kw)
    out = [r0]
    for ang in range(0, 360, 45):
        out.append(icgn_refine(v0, v1, p0, r0.pts, init_warp=r0.warp,
                               subset_offsets=shifted_offsets(h, shift_frac * h, ang),
                               noise_sigma=tuple(r0.noise_sigma), **kw))
    pts = np.array([r.pts for r in out])
    rr = np.array([np.where(r.converged, r.residual_ratio, np.inf) for r in out])
    sig = np.array([r.sigma_px[:, 0] for r in out])
    return pts, rr, sig


def run_cell(tmp, cell):
    regime, noise, t0, t1 = cell.split("/")
    tilts = (float(t0), float(t1))
    exp = am.make_cell(tmp, regime, noise, tilts, 0, (384, 512), 50)
    v0, v1 = (np.asarray(v, float) for v in exp.views()[:2])
    flows, _ = am.dense_flows(v0, v1)
    sh = am.semlab_heights(exp, "auto", auto={"target_sigma_px": 0.0, "curvature_neighbours": 1})
    p0 = sh.pts[:, 0]
    es = _plane_errors(exp, tilts, sh.pts)
    df = np.stack([p0, p0 + am._sample_flow(flows["DeepFlow"], p0)], 1)
    ed = _plane_errors(exp, tilts, df)
    zt_map = np.load(Path(exp.truth_dir) / "height_view0.npy").astype(float)
    steep_map = ndimage.maximum_filter(1000 * np.hypot(*np.gradient(zt_map)), 21)
    steep = ndimage.map_coordinates(steep_map, [p0[:, 1], p0[:, 0]], order=0) > 5
    n = len(es)
    worst = np.zeros(n, bool)
    worst[np.argsort(-es ** 2)[: max(1, n // 20)]] = True
    zs = 1000 * np.asarray(sh.z_err_um, float)
    row = dict(cell=cell, n=n, rmse=_rms(es), df=_rms(ed), share=np.sum(es[worst] ** 2) / np.sum(es ** 2),
               w_s=_rms(es[worst]), w_df=_rms(ed[worst]), w_steep=steep[worst].mean(),
               w_in2=np.mean(np.abs(es[worst]) < 2 * zs[worst]),
               st_frac=steep.mean(), st_s=_rms(es[steep]), st_df=_rms(ed[steep]),
               fl_s=_rms(es[~steep]), fl_df=_rms(ed[~steep]))
    zt = validation.true_height_at(exp.truth_dir, p0)
    for frac in (1.0, 0.5):
        pts, rr, sig = windows(v0, v1, p0, sh.pts[:, 1], shift_frac=frac)
        e = np.array([1000 * (_heights(exp, tilts, p0, q) - zt) for q in pts])
        e -= np.nanmedian(e[0])
        k = np.arange(n)
        best_rr = np.argmin(rr, 0)
        rule_rr = rr.copy()
        rule_rr[0] = np.where(rr[0] > 1.5, 0.7 * rr[0], -np.inf)
        rule = np.argmin(rule_rr, 0)
        tag = f"_{frac:g}"
        best = np.min(np.where(np.isfinite(e), np.abs(e), np.inf), 0)  # the truth's choice
        best[~np.isfinite(best)] = np.nan
        row.update({
            "rr_w": float(np.nanmedian(rr[0][worst])), "rr_w15": float(np.mean(rr[0][worst] > 1.5)),
            "rr_rest": float(np.nanmedian(rr[0][~worst])),
            "rr_rest15": float(np.mean(rr[0][~worst] > 1.5)),
            "c_w": _rms(e[0][worst]), "c_all": _rms(e[0]),
            "or_w" + tag: _rms(best[worst]),
            "or_all" + tag: _rms(best),
            "mr_w" + tag: _rms(e[best_rr, k][worst]), "mr_all" + tag: _rms(e[best_rr, k]),
            "ru_w" + tag: _rms(e[rule, k][worst]), "ru_all" + tag: _rms(e[rule, k]),
            "ru_n" + tag: float(np.mean(rule > 0)),
            "sig" + tag: float(np.nanmedian(sig[1:][:, rule > 0] / sig[0][rule > 0]))
            if np.any(rule > 0) else np.nan})
    return row


def _f(v, fmt=".1f"):
    return "–" if v is None or not np.isfinite(v) else format(v, fmt)


def tables(rows):
    a = ["| cell | N | semlab / DeepFlow RMSE (nm) | worst 5 %: share of SSE | worst 5 %: semlab / DeepFlow | "
         "worst 5 % beside a band | worst 5 % within 2σ | beside a band: N share, semlab / DeepFlow | "
         "rest: semlab / DeepFlow |", "|" + "---|" * 9]
    for r in rows:
        a.append(f"| {r['cell']} | {r['n']} | {_f(r['rmse'])} / {_f(r['df'])} | {r['share']:.0%} | "
                 f"{_f(r['w_s'])} / {_f(r['w_df'])} | {r['w_steep']:.0%} | {r['w_in2']:.0%} | "
                 f"{r['st_frac']:.0%}, {_f(r['st_s'])} / {_f(r['st_df'])} | "
                 f"{_f(r['fl_s'])} / {_f(r['fl_df'])} |")
    b = ["| cell | residual ratio (21²) worst 5 %: median, > 1.5 | rest: median, > 1.5 | "
         "centred 21²: worst 5 % / all | shift | oracle of 9: worst / all | smallest residual: "
         "worst / all | rule (ratio > 1.5, gain 0.7): worst / all, shifted, σ ×|", "|" + "---|" * 8]
    for r in rows:
        for frac in (1.0, 0.5):
            t = f"_{frac:g}"
            b.append(f"| {r['cell']} | {r['rr_w']:.2f}, {r['rr_w15']:.0%} | {r['rr_rest']:.2f}, "
                     f"{r['rr_rest15']:.0%} | {_f(r['c_w'])} / {_f(r['c_all'])} | {frac:g} h | "
                     f"{_f(r['or_w' + t])} / {_f(r['or_all' + t])} | {_f(r['mr_w' + t])} / "
                     f"{_f(r['mr_all' + t])} | {_f(r['ru_w' + t])} / {_f(r['ru_all' + t])}, "
                     f"{r['ru_n' + t]:.0%}, {_f(r['sig' + t], '.2f')} |")
    return "\n".join(a), "\n".join(b)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cells", default=",".join(CELLS))
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parent / "results" / "step_points.md")
    args = ap.parse_args(argv)
    t0 = time.time()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for cell in args.cells.split(","):
            rows.append(run_cell(tmp, cell))
            print(f"{cell}: {time.time() - t0:.0f} s", file=sys.stderr)
    a, b = tables(rows)
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    text = (f"# Points beside slip-band steps\n\n`python benchmarks/step_points.py --cells "
            f"{args.cells}` on {now}, {time.time() - t0:.0f} s (see the script's docstring).\n\n"
            f"## Where the automatic heights (total-error sizing) are worst\n\n{a}\n\n"
            f"## Is the step visible in the residual; what displaced windows would gain\n\n{b}\n")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
