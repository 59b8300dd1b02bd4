"""Accuracy matrix: heights over texture regime × noise × tilt pair × method, one table.

Run:  python benchmarks/accuracy_matrix.py            # full matrix (394 s on an idle 2-core machine, 2026-12-03)
      python benchmarks/accuracy_matrix.py --quick    # 3 small cells (< 3 min)
      python benchmarks/accuracy_matrix.py --sets clicks \
          --cells polished/realistic/-5/5,real:fei/realistic/0/8   # some cells, clicks only
      python benchmarks/accuracy_matrix.py --sets auto \
          --cells polished/realistic/-5/0/5    # a three-view cell (not in the full matrix)
      python benchmarks/accuracy_matrix.py --headline benchmarks/results/accuracy_matrix.md
                                                      # the README's compact table, no matching

Writes ``benchmarks/results/accuracy_matrix.md`` (``--quick``: ``accuracy_matrix_quick.md``; with
``--cells`` or ``--sets``: ``accuracy_matrix_subset.md``;
``--out`` to change) and prints it.

Cells
-----
- regimes: ``speckle``, ``polished``, ``featureless`` (:mod:`semlab.synth`) and the real
  textures ``real:fei`` and ``real:quartz`` (:mod:`semlab.realtex`: the real image is view 0,
  the other view is rendered by a known surface), all with the same surface per seed;
- noise: the :data:`semlab.synth.NOISE_LEVELS` presets ``low`` and ``realistic`` (Poisson shot
  noise, per-image gain/offset, 8-bit);
- tilt pairs: −5°/+5° and 0°/+8°; 384×512 px, 0.03 µm/px, 50 hand-click-like points with
  0.5 px click noise.
- multi-view cells, on request (``--cells REGIME/NOISE/T0/T1/T2``): three or more tilts.
  semlab matches from its reference view (``AutoMatchParams.ref_view``, view 0) and so do
  the references (each run from that view to every other one); every method's heights come from all views
  at the points semlab's automatic matching accepted in all of them (points it kept in fewer
  views are not scored). The Cramér–Rao column is for pairs only.

Methods, all scored at the same points
--------------------------------------
Point sets per cell: the **clicks** semlab refined (``pipeline.run_stereo(...,
method="refined")``) and the points semlab's **automatic** matching accepted (``"auto"``),
each with fixed subsets and, where semlab has them, with information-sized subsets
(``target_sigma_px=0.05``: ``clicks adaptive``, ``auto adaptive``), and the automatic
points sized by their predicted total error, noise and curvature bias (``auto total``:
``target_sigma_px=0, curvature_neighbours=1``, each point at its smallest). At each
set's view-0 positions the references are computed in the same run on the same images:

Where semlab's automatic matching finds no point (``featureless``), the references are scored
on the whole 8-px grid inside a 16 px border instead (points ``grid``).

- ``DeepFlow``: ``cv2.optflow.createOptFlow_DeepFlow()`` with its default settings, view 0 →
  view 1, sampled bilinearly at the points;
- ``ECC 15px``: ``cv2.findTransformECC`` with ``MOTION_TRANSLATION`` per point, a 15×15 px
  template around the point's pixel, started from the DeepFlow displacement (ECC is a local
  method); points where it fails to converge are dropped from its row (see its points);
- ``DIS medium``: ``cv2.DISOpticalFlow_create(DISOPTICAL_FLOW_PRESET_MEDIUM)``; ``DIS fine``:
  the same down to the full resolution (``setFinestScale(0)``; OpenCV has no FINE preset,
  only ULTRAFAST, FAST and MEDIUM).

Heights of every method come from the same affine reconstruction
(``reconstruct.heights_from_tilts`` with the known tilts); semlab's predicted 1σ is its
``z_err_um`` (``pipeline.run_stereo``, matching σ, no bootstrap). Errors are measured after
removing the best-fit plane of the error (``validation.height_errors``). The same run also
scores every method with a robust gauge plane (``plane="robust"``: Huber IRLS, which one
large-σ error cannot tilt; the same for every method, at the same points; the matching is
not repeated): the second pair of tables of the output, same columns.

Columns: height RMSE and robust σ (1.4826·MAD of the plane-removed error) in nm; the number
of points; coverage (clicks: fraction refined; automatic: fraction of the 8-px grid cells of
the view inside a 16 px border that hold an accepted point); semlab's median predicted 1σ
(nm), the fractions of points within 1σ and 2σ of the truth, and efficiency (median predicted
σ / robust σ of the actual error: 1 for error bars of the right size); the RMSE ratio to
DeepFlow at the same points; the median Cramér–Rao bound of the height for a 21×21
translation subset at the set's points (:func:`crb_height_nm`, from the noise-free view and
the detector's known noise: the information limit of that support, whatever the method).

semlab is called only through :func:`semlab_heights` (a thin adapter): an API rename is a
one-line change there.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import inspect
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from semlab import experiment, pipeline, realtex, reconstruct, synth, validation
from semlab.stats import robust_sd

from bench_args import variational_params

REGIMES = ("speckle", "polished", "featureless", "real:fei", "real:quartz")
NOISES = ("low", "realistic")
PAIRS = ((-5.0, 5.0), (0.0, 8.0))
REFERENCES = ("DeepFlow", "ECC 15px", "DIS medium", "DIS fine")
RESULTS = Path(__file__).resolve().parent / "results" / "accuracy_matrix.md"


# ------------------------------------------------------------------------------ scenes
def make_cell(tmp, regime, noise, tilts, seed=0, size=(384, 512), n_clicks=50):
    """An experiment for one cell: synth regime or real texture, stereo only."""
    out = Path(tmp) / (f"{regime.replace(':', '_')}_{noise}_"
                       + "_".join(f"{t:+g}" for t in tilts) + f"_{seed}")
    kw = dict(seed=seed, size=size, tilts_deg=tilts, n_frames=0, n_clicks=n_clicks,
              detector=noise, write_block=False, progress=False)
    if regime.startswith("real:"):
        toml = realtex.make_experiment(out, regime[5:], **kw)
    else:
        toml = synth.make_experiment(out, texture=regime, **kw)
    return experiment.load(toml)


def clean_view0(exp, regime, seed, size):
    """The noise-free view 0 of a cell (relative signal), re-rendered from its known scene."""
    tilt = float(exp.stereo.tilt_deg[0])
    if regime.startswith("real:"):
        scene, _ = realtex.make_real_scene(regime[5:], seed=seed, size=size,
                                           source_tilt_deg=tilt, n_landmarks=0)
        img, _, _ = synth.render(scene, size, tilt, blur_px=0, noise=0, shading=False)
    else:
        scene = synth.make_scene(seed=seed, size=size, texture=regime)
        img, _, _ = synth.render(scene, size, tilt, noise=0)
    return img


def crb_height_nm(clean, detector, p0, tilts, pixel_size_um, half=10):
    """Cramér–Rao bound of the height at view-0 points for a (2·half+1)² translation subset.

    From the noise-free view's gradients (counts) and the detector's per-pixel noise
    (Poisson: variance ∝ signal, plus 8-bit quantisation), both views noisy: the Fisher matrix
    of the 2D shift is ``Σ g gᵀ / (2 σ_i²)`` over the subset; the height follows from the x
    shift by ``s cos θ0 / sin(θ1 − θ0)``. The information limit of a 21×21 subset, whatever
    the method.
    """
    det = synth.as_detector(detector)
    scale = (2 ** det.bits - 1) / det.full_scale
    img = clean * scale
    var = scale ** 2 * np.clip(clean, 1e-6, None) / det.dose_e_per_px + 1.0 / 12
    gy, gx = np.gradient(img)
    n = (2 * half + 1) ** 2
    f = {k: ndimage.uniform_filter(v / (2 * var), 2 * half + 1, mode="nearest") * n
         for k, v in (("xx", gx * gx), ("xy", gx * gy), ("yy", gy * gy))}
    fs = {k: ndimage.map_coordinates(v, [p0[:, 1], p0[:, 0]], order=1, mode="nearest")
          for k, v in f.items()}
    det_f = fs["xx"] * fs["yy"] - fs["xy"] ** 2
    ok = (det_f > 0) & (fs["yy"] > 0)  # no texture: rounding can leave tiny negative sums
    var_dx = np.where(ok, fs["yy"] / np.where(ok, det_f, 1), np.inf)
    t0, t1 = np.deg2rad(tilts)
    return 1000 * np.sqrt(var_dx) * pixel_size_um * np.cos(t0) / abs(np.sin(t1 - t0))


# ------------------------------------------------------------------------------ semlab adapter
@dataclass
class Heights:
    pts: np.ndarray        # (N, V, 2) (x, y) px in every view
    z_err_um: np.ndarray   # (N,) predicted 1σ (NaN when the method gives none)
    n_tried: int           # points the method was asked for (clicks) or grid cells (auto)
    seconds: float


def semlab_variants(vparams=None, stage9=True):
    """(point set, method, matching keywords) of the semlab rows: fixed subsets, and the
    information-sized (adaptive) subsets where this semlab has them; ``vparams``: the
    automatic sets' stage-9 ``variational_params`` (``--var``); ``stage9=False``: the
    automatic sets without stage 9 (``variational_fusion=False``, ``--stage9-off``)."""
    from semlab import matching

    params = getattr(matching, "AutoMatchParams", None)
    names = set(inspect.signature(matching.auto_match).parameters)
    if params is not None:
        names |= {f.name for f in dataclasses.fields(params)}
    if "target_sigma_px" not in names:
        return [("clicks", "refined", {}), ("auto", "auto", {})]
    fixed = {"target_sigma_px": None}  # refine_correspondences may size subsets by default
    out = [("clicks", "refined", {"refine": fixed}), ("auto", "auto", {"auto": fixed}),
           ("clicks adaptive", "refined", {"refine": {"target_sigma_px": 0.05}}),
           ("auto adaptive", "auto", {"auto": {"target_sigma_px": 0.05}})]
    if "curvature_neighbours" in names:
        # noise-only sizing stays noise-only; "auto total": total-error sizing, each point
        # at its smallest predicted total error (noise and curvature bias)
        out[3] = ("auto adaptive", "auto", {"auto": {"target_sigma_px": 0.05,
                                                     "curvature_neighbours": None}})
        out.append(("auto total", "auto", {"auto": {"target_sigma_px": 0.0,
                                                    "curvature_neighbours": 1}}))
    if vparams is not None:
        out = [(n, m, {**kw, "auto": {**kw["auto"], "variational_params": vparams}})
               if "auto" in kw else (n, m, kw) for n, m, kw in out]
    if not stage9:
        out = [(n, m, {**kw, "auto": {**kw["auto"], "variational_fusion": False}})
               if "auto" in kw else (n, m, kw) for n, m, kw in out]
    return out


def semlab_heights(exp, method, **match_kw):
    """semlab's matches and predicted height σ (the one place semlab's API is called)."""
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        if "refine_kw" in inspect.signature(pipeline.run_stereo).parameters:
            kw = {"refine_kw": match_kw.get("refine"), "auto_kw": match_kw.get("auto")}
        else:  # before 2026-12-01 18:00: run_stereo(..., refine={...}, auto={...})
            kw = match_kw
        res = pipeline.run_stereo(exp, method=method, n_boot=0, progress=False, **kw)
    corr = exp.correspondences()
    n = len(corr.pts) if (method == "refined" and corr is not None) else 0
    return Heights(res.pts, np.asarray(res.z_err_um, float), n,
                   time.perf_counter() - t0)


# ------------------------------------------------------------------------------ references
def _u8(img):
    img = np.asarray(img, float)
    if img.max() > 255 or img.min() < 0:
        img = (img - img.min()) / (np.ptp(img) + 1e-12) * 255
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _sample_flow(flow, p):
    return np.column_stack([ndimage.map_coordinates(flow[..., k], [p[:, 1], p[:, 0]], order=1,
                                                    mode="nearest") for k in (0, 1)])


def dense_flows(v0, v1):
    """Dense view-0 → view-1 flows of the dense references, (H, W, 2) each, and their times."""
    a, b = _u8(v0), _u8(v1)
    out, secs = {}, {}
    t0 = time.perf_counter()
    out["DeepFlow"] = cv2.optflow.createOptFlow_DeepFlow().calc(a, b, None)
    secs["DeepFlow"] = time.perf_counter() - t0
    for name, finest in (("DIS medium", None), ("DIS fine", 0)):
        t0 = time.perf_counter()
        dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
        if finest is not None:  # OpenCV has no FINE preset: MEDIUM down to full resolution
            dis.setFinestScale(finest)
        out[name] = dis.calc(a, b, None)
        secs[name] = time.perf_counter() - t0
    return out, secs


def ecc_points(v0, v1, p0, init_disp, half=7):
    """ECC translation per point (15×15 template), from an initial displacement.

    Returns (N, 2) displacements (NaN where ECC fails or leaves the image).
    """
    a = np.asarray(v0, np.float32)
    b = np.asarray(v1, np.float32)
    h, w = a.shape
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    out = np.full((len(p0), 2), np.nan)
    for i, ((x, y), (dx, dy)) in enumerate(zip(p0, init_disp)):
        c, r = int(round(x)), int(round(y))
        if not (half <= c < w - half and half <= r < h - half):
            continue
        tpl = a[r - half:r + half + 1, c - half:c + half + 1]
        if tpl.std() < 1e-6:
            continue
        warp = np.array([[1, 0, c - half + dx], [0, 1, r - half + dy]], np.float32)
        try:
            _, warp = cv2.findTransformECC(tpl, b, warp, cv2.MOTION_TRANSLATION, crit, None, 1)
        except cv2.error:
            continue
        d = np.array([warp[0, 2] - (c - half), warp[1, 2] - (r - half)])
        if np.all(np.isfinite(d)) and np.hypot(*(d - (dx, dy))) < 2 * half:
            out[i] = d
    return out


def reference_matches(v0, v1, p0, flows):
    """(N, 2, 2) matches of every reference method at view-0 points ``p0``."""
    out = {}
    for name in ("DeepFlow", "DIS medium", "DIS fine"):
        out[name] = np.stack([p0, p0 + _sample_flow(flows[name], p0)], 1)
    d = ecc_points(v0, v1, p0, _sample_flow(flows["DeepFlow"], p0))
    out["ECC 15px"] = np.stack([p0, p0 + d], 1)
    return out


def reference_view():
    """The view semlab's automatic matching takes as its reference
    (``AutoMatchParams.ref_view``, view 0 by default, which ``pipeline.run_stereo`` keeps);
    the references are run from the same view."""
    from semlab import matching

    params = getattr(matching, "AutoMatchParams", None)
    return int(params().ref_view) if params is not None else 0


def multiview_reference_matches(views, p_ref, ref, flows):
    """(N, V, 2) matches of every reference method at points ``p_ref`` of view ``ref``: each
    method run from the reference view to every other view, as semlab matches (two views:
    :func:`reference_matches` from view 0); ``flows``: ``{j: dense_flows(views[ref],
    views[j])[0]}`` for every other view ``j``."""
    out = {}
    for j in range(len(views)):
        if j == ref:
            continue
        for name, m in reference_matches(views[ref], views[j], p_ref, flows[j]).items():
            out.setdefault(name, np.repeat(p_ref[:, None, :], len(views), axis=1).astype(float))
            out[name][:, j] = m[:, 1]
    return out


def tilts_label(tilts):
    """``-5/+0/+5°`` for the tables."""
    return "/".join(f"{t:+g}" for t in tilts) + "°"


# ------------------------------------------------------------------------------ scoring
def coverage_auto(p0, shape, cell=8, border=16):
    """Fraction of the cell×cell grid cells inside ``border`` that hold an accepted point."""
    h, w = shape
    nx, ny = (w - 2 * border) // cell, (h - 2 * border) // cell
    cx = np.floor((p0[:, 0] - border) / cell).astype(int)
    cy = np.floor((p0[:, 1] - border) / cell).astype(int)
    ok = (cx >= 0) & (cx < nx) & (cy >= 0) & (cy < ny)
    return len(set(zip(cx[ok], cy[ok]))) / float(nx * ny)


GAUGES = {"": "lsq", "_rob": "robust"}  # row-key suffix -> validation.height_errors plane


def score(exp, pts, tilts, z_err_um=None):
    """Height errors of matches ``pts`` (N, 2, 2) against the truth (nm), under each gauge
    plane of :data:`GAUGES` (keys ``rmse``, ``rsig``, ``in1``, ``in2`` with the lsq plane;
    the same with suffix ``_rob`` with the robust plane)."""
    ok = np.all(np.isfinite(pts.reshape(len(pts), -1)), axis=1)
    row = {"n": int(ok.sum()), "ok": ok, "pred": np.nan}
    for sfx in GAUGES:
        row.update({f"{k}{sfx}": np.nan for k in ("rmse", "rsig", "in1", "in2")})
    if ok.sum() < 4:
        return row
    p = pts[ok]
    z = reconstruct.heights_from_tilts(p, list(tilts), exp.pixel_size_um).xyz_um[:, 2]
    zt = validation.true_height_at(exp.truth_dir, p[:, 0])
    zs = None if z_err_um is None else np.asarray(z_err_um, float)[ok]
    if zs is not None:
        row["pred"] = 1000 * float(np.median(zs))
    for sfx, plane in GAUGES.items():
        e = validation.height_errors(z, zt, p[:, 0], plane=plane)
        err = e["err_um"]
        row.update({f"rmse{sfx}": 1000 * e["rmse_um"], f"rsig{sfx}": 1000 * robust_sd(err)})
        if zs is not None:
            row.update({f"in1{sfx}": float(np.mean(np.abs(err) < zs)),
                        f"in2{sfx}": float(np.mean(np.abs(err) < 2 * zs))})
    return row


def with_gauge(cells, sfx):
    """``cells`` with the scores of gauge ``sfx`` (a key of :data:`GAUGES`) in the plain keys
    (``rmse``, ``rsig``, ``in1``, ``in2``, ``df_ratio``), for :func:`table` and :func:`summary`."""
    out = []
    for key, rows in cells:
        new = []
        for r in rows:
            if "fail" not in r:
                r = {**r, **{k: r[f"{k}{sfx}"] for k in ("rmse", "rsig", "in1", "in2",
                                                         "df_ratio")}}
            new.append(r)
        out.append((key, new))
    return out


def run_cell(tmp, regime, noise, tilts, seed, size, n_clicks, sets=None, vparams=None,
             stage9=True):
    """Rows of one cell; ``sets``: only the semlab point sets whose name starts with one of
    these (e.g. ``("clicks",)``), default all; ``vparams``, ``stage9``: see
    :func:`semlab_variants`."""
    exp = make_cell(tmp, regime, noise, tilts, seed, size, n_clicks)
    views = exp.views()[:len(tilts)]
    v0, ref = views[0], reference_view()
    flows = {j: dense_flows(views[ref], views[j])[0] for j in range(len(views)) if j != ref}
    clean = clean_view0(exp, regime, seed, size)
    rows = []
    variants = [v for v in semlab_variants(vparams, stage9)
                if sets is None or any(v[0] == k[1:] if k.startswith("=") else
                                       v[0].startswith(k) for k in sets)]
    for set_name, method, match_kw in variants:
        try:
            sh = semlab_heights(exp, method, **match_kw)
        except Exception as exc:  # a failing method is a result, not a crash of the table
            rows.append({"set": set_name, "method": f"semlab {method}", "fail": str(exc)[:80]})
            if set_name.startswith(("clicks", "auto adaptive", "auto total")):
                continue
            # the references are still scored, on the whole 8-px grid
            sh, set_name = None, "grid (semlab found none)"
        if sh is None:
            g = np.mgrid[16:v0.shape[0] - 16:8, 16:v0.shape[1] - 16:8].reshape(2, -1).T[:, ::-1]
            p0 = g.astype(float)
            cov = 1.0
            sem = None
        else:
            # points seen in every view (with three or more, semlab also gives heights of
            # points seen in fewer: not scored here, as the references could not be)
            full = np.all(np.isfinite(sh.pts.reshape(len(sh.pts), -1)), axis=1)
            sh = Heights(sh.pts[full], sh.z_err_um[full], sh.n_tried, sh.seconds)
            p0 = sh.pts[:, ref]
            cov = (len(p0) / sh.n_tried if sh.n_tried else np.nan) \
                if set_name.startswith("clicks") else coverage_auto(sh.pts[:, 0], v0.shape)
            sem = score(exp, sh.pts, tilts, sh.z_err_um)
        crb = (float(np.median(crb_height_nm(clean, noise, p0, tilts, exp.pixel_size_um)))
               if len(tilts) == 2 else np.nan)   # the bound of a pair only
        refs = {k: score(exp, v, tilts)
                for k, v in multiview_reference_matches(views, p0, ref, flows).items()}
        df = {sfx: refs["DeepFlow"][f"rmse{sfx}"] for sfx in GAUGES}
        label = f"semlab {method}" + (" adaptive" if "adaptive" in set_name else
                                       " total" if "total" in set_name else "")
        own = [] if sem is None else [(label, sem)]
        for name, r in own + list(refs.items()):
            rows.append({"set": set_name, "method": name, "cov": cov, "crb": crb,
                         **{f"df_ratio{sfx}": r[f"rmse{sfx}"] / df[sfx] for sfx in GAUGES},
                         "seconds": sh.seconds if name.startswith("semlab") else np.nan, **r})
    return rows


# ------------------------------------------------------------------------------ table
def _f(v, fmt):
    return "–" if v is None or not np.isfinite(v) else format(v, fmt)


def table(cells):
    head = ("| regime | noise | tilts | points | method | RMSE (nm) | robust σ (nm) | N | coverage "
            "| median predicted σ (nm) | within 1σ / 2σ | efficiency | ÷ DeepFlow | CRB 21² (nm) |")
    lines = [head, "|" + "---|" * 14]
    for (regime, noise, tilts), rows in cells:
        for r in rows:
            lead = f"| {regime} | {noise} | {tilts_label(tilts)} | {r['set']} | {r['method']} "
            if "fail" in r:
                lines.append(lead + f"| failed: {r['fail']} |" + " |" * 8)
                continue
            eff = r["pred"] / r["rsig"] if np.isfinite(r["pred"]) else np.nan
            within = (f"{r['in1']:.0%} / {r['in2']:.0%}" if np.isfinite(r["in1"]) else "–")
            lines.append(lead + f"| {_f(r['rmse'], '.1f')} | {_f(r['rsig'], '.1f')} | {r['n']} | "
                         f"{_f(r['cov'], '.0%')} | {_f(r['pred'], '.1f')} | {within} | "
                         f"{_f(eff, '.2f')} | {_f(r['df_ratio'], '.2f')} | {_f(r['crb'], '.1f')} |")
    return "\n".join(lines)


def summary(cells):
    """One line per cell: height RMSE (nm) of every method at the same points (the results
    file's first table; the README's is :func:`headline`)."""
    lines = ["| regime | noise | tilts | automatic: semlab (N, coverage) | DeepFlow | ECC 15px "
             "| DIS fine | CRB 21² | adaptive automatic: semlab (N) | DeepFlow "
             "| refined clicks: semlab | ECC 15px | DeepFlow | adaptive refined: semlab | ECC 15px "
             "| total-error automatic: semlab (N) | DeepFlow |",
             "|" + "---|" * 18]
    for (regime, noise, tilts), rows in cells:
        by = {(r["set"].replace("grid (semlab found none)", "auto"), r["method"]): r for r in rows}

        def rm(key):
            r = by.get(key)
            if r is None and not any(k[0] == key[0] for k in by):
                return "–"      # that point set was not run (--sets)
            return "failed" if r is None or "fail" in r else _f(r["rmse"], ".1f")

        a = by.get(("auto", "semlab auto"), {})
        auto = (f"{rm(('auto', 'semlab auto'))} ({a['n']}, {a['cov']:.0%})"
                if a and "fail" not in a else "none found (refs on the 8-px grid)")
        if not any(k[0] == "auto" for k in by):
            auto = "not run"
        crb = _f(by.get(("auto", "DeepFlow"), {}).get("crb", np.nan), ".1f")
        aa = by.get(("auto adaptive", "semlab auto adaptive"), {})
        adaptive = (f"{rm(('auto adaptive', 'semlab auto adaptive'))} ({aa['n']})"
                    if aa and "fail" not in aa else rm(("auto adaptive", "semlab auto adaptive")))
        at = by.get(("auto total", "semlab auto total"), {})
        total = (f"{rm(('auto total', 'semlab auto total'))} ({at['n']})"
                 if at and "fail" not in at else rm(("auto total", "semlab auto total")))
        lines.append(f"| {regime} | {noise} | {tilts_label(tilts)} | {auto} | "
                     f"{rm(('auto', 'DeepFlow'))} | {rm(('auto', 'ECC 15px'))} | "
                     f"{rm(('auto', 'DIS fine'))} | {crb} | {adaptive} | "
                     f"{rm(('auto adaptive', 'DeepFlow'))} | {rm(('clicks', 'semlab refined'))} | "
                     f"{rm(('clicks', 'ECC 15px'))} | {rm(('clicks', 'DeepFlow'))} | "
                     f"{rm(('clicks adaptive', 'semlab refined adaptive'))} | "
                     f"{rm(('clicks adaptive', 'ECC 15px'))} | {total} | "
                     f"{rm(('auto total', 'DeepFlow'))} |")
    return "\n".join(lines)


def headline(markdown):
    """The README's compact table, from a results file written by this script.

    One row per cell of the first "Every method and column" table (least-squares gauge): the
    automatic points with ``auto_match``'s defaults (fixed 21×21 subsets and stage 9: semlab's
    RMSE with its points and coverage, DeepFlow's at the same points, their ratio, the fraction
    of errors within semlab's 1σ / 2σ and the efficiency) and the refined clicks with
    ``semlab run``'s default (information-sized subsets, ``clicks adaptive``: semlab's RMSE,
    within 1σ / 2σ, and ECC 15 px's at the same points).

    Parameters
    ----------
    markdown : str
        The text of a results file (``--out`` of a full or subset run).

    Returns
    -------
    str, a markdown table.
    """
    lines = markdown.split("\n")
    try:
        start = lines.index("## Every method and column")
    except ValueError:
        raise SystemExit("--headline: no '## Every method and column' table in that file; give "
                         "a results file of this script") from None
    rows = {}
    for ln in lines[start + 1:]:
        if ln.startswith("## "):
            break
        c = [x.strip() for x in ln.strip().strip("|").split("|")]
        if len(c) < 14 or c[0] in ("regime", "---"):
            continue
        rows.setdefault(tuple(c[:3]), {})[(c[3], c[4])] = c[5:]
    out = ["| regime | noise | tilts | automatic: semlab RMSE (N, coverage) | DeepFlow "
           "| ÷ DeepFlow | within 1σ / 2σ | efficiency | refined clicks (sized): semlab "
           "| within 1σ / 2σ | ECC 15px |", "|" + "---|" * 11]
    for (regime, noise, tilts), by in rows.items():
        # each row's columns from RMSE on: RMSE, robust σ, N, coverage, predicted σ,
        # within 1σ / 2σ, efficiency, ÷ DeepFlow, CRB
        a = by.get(("auto", "semlab auto"))
        if a is None or a[0].startswith("failed"):
            df = by.get(("grid (semlab found none)", "DeepFlow"), ["–"])[0]
            auto = ["none found", f"{df} (8-px grid)", "–", "–", "–"]
        else:
            auto = [f"{a[0]} ({a[2]}, {a[3]})", by.get(("auto", "DeepFlow"), ["–"])[0], a[7],
                    a[5], a[6]]
        k = by.get(("clicks adaptive", "semlab refined adaptive"), ["–"] * 9)
        ecc = by.get(("clicks adaptive", "ECC 15px"), ["–"])[0]
        out.append(f"| {regime} | {noise} | {tilts} | " + " | ".join(auto)
                   + f" | {k[0]} | {k[5]} | {ecc} |")
    return "\n".join(out)


def _parse_cell(text):
    """(regime, noise, (t0, t1, ...)) from ``REGIME/NOISE/T0/T1[/T2...]`` (three or more
    tilts: a multi-view cell, matched from view 0 as semlab does)."""
    parts = text.strip().split("/")
    try:
        tilts = tuple(float(t) for t in parts[2:])
    except ValueError:
        tilts = ()
    if len(tilts) < 2 or parts[0] not in REGIMES or parts[1] not in NOISES:
        raise SystemExit(f"--cells: {text!r} is not REGIME/NOISE/T0/T1[/T2...] with REGIME in "
                         f"{REGIMES} and NOISE in {NOISES}")
    return parts[0], parts[1], tilts


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="3 cells (speckle, polished, real:fei; realistic noise; ±5°) at 192×256")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None,
                    help=f"markdown file (default {RESULTS.name}, or accuracy_matrix_quick.md; "
                    "with --cells or --sets: accuracy_matrix_subset.md)")
    ap.add_argument("--cells", default=None,
                    help="only these cells of the full matrix, comma-separated "
                    "REGIME/NOISE/T0/T1, e.g. polished/realistic/-5/5,real:fei/realistic/0/8")
    ap.add_argument("--sets", default=None,
                    help="only these semlab point sets (and the references at their points), "
                    "comma-separated prefixes: clicks, auto (=NAME: that set only, e.g. "
                    "=auto for the default automatic points alone)")
    ap.add_argument("--var", action="append", default=[], metavar="KEY=VALUE",
                    help="a semlab.variational.VariationalParams field of the automatic sets' "
                    "stage 9, e.g. --var norm_sigma_px=5 (repeatable)")
    ap.add_argument("--stage9-off", action="store_true",
                    help="the automatic sets without stage 9 (variational_fusion=False)")
    ap.add_argument("--headline", type=Path, default=None, metavar="RESULTS_MD",
                    help="print the README's compact table from a results file of this "
                    "script and stop (no matching)")
    args = ap.parse_args(argv)
    if args.headline is not None:
        try:
            text = args.headline.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise SystemExit(f"--headline: cannot read {args.headline}: {exc}") from None
        print(headline(text))
        return None
    vparams = variational_params(args.var) if args.var else None
    subset = args.cells is not None or args.sets is not None
    if args.out is None:
        args.out = RESULTS.with_name("accuracy_matrix_quick.md") if args.quick else (
            RESULTS.with_name("accuracy_matrix_subset.md") if subset else RESULTS)
    sets = None if args.sets is None else tuple(args.sets.split(","))
    if args.quick:
        grid = [(r, "realistic", PAIRS[0]) for r in ("speckle", "polished", "real:fei")]
        size, n_clicks = (192, 256), 20
    else:
        grid = [(r, n, t) for r in REGIMES for n in NOISES for t in PAIRS]
        size, n_clicks = (384, 512), 50
    if args.cells is not None:
        grid = [_parse_cell(c) for c in args.cells.split(",")]
    t0 = time.perf_counter()
    cells = []
    with tempfile.TemporaryDirectory() as tmp:
        for regime, noise, tilts in grid:
            tc = time.perf_counter()
            cells.append(((regime, noise, tilts),
                          run_cell(tmp, regime, noise, tilts, args.seed, size, n_clicks,
                                   sets, vparams, not args.stage9_off)))
            print(f"{regime} {noise} {tilts}: {time.perf_counter() - tc:.0f} s", flush=True)
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    cmd = " ".join(["python benchmarks/accuracy_matrix.py"] + (argv if argv is not None
                                                                  else sys.argv[1:]))
    kind = "quick" if args.quick else ("subset" if subset else "full")
    text = (f"# Accuracy matrix ({kind})\n\n"
            f"`{cmd}` on {when}, "
            f"{size[0]}×{size[1]} px, 0.03 µm/px, seed {args.seed}, "
            f"{time.perf_counter() - t0:.0f} s. Heights after removing the plane of the error; "
            "all methods at the same points (see the script's docstring).\n\n"
            "## Height RMSE (nm) per cell\n\n" + summary(cells) + "\n\n## Every method and column\n\n"
            + table(cells) + "\n\n"
            "## With a robust gauge plane: height RMSE (nm) per cell\n\n"
            "The same matches, scored after removing a robust plane of the error instead "
            "(`validation.height_errors(..., plane=\"robust\")`: Huber IRLS on the residual "
            "scaled by its MAD), identically for every method at the same points.\n\n"
            + summary(with_gauge(cells, "_rob")) + "\n\n"
            "## With a robust gauge plane: every method and column\n\n"
            + table(with_gauge(cells, "_rob")) + "\n")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text)
    return cells


if __name__ == "__main__":
    main()
