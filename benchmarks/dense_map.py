"""Dense height map against the truth and against OpenCV DeepFlow, in the same run.

For each scene: a synthetic experiment (semlab.synth / semlab.realtex) is written, the
normal run computes the sparse stereo result (automatic matching + clicks), then

- semlab's dense map (:func:`semlab.heightmap.heightmap_from_stereo`), and
- OpenCV DeepFlow (Weinzaepfel et al. 2013) on the same contrast-normalised views, its
  x-flow turned into heights by the *same* height model (same reference plane),

are compared with ``truth/height_view0.npy`` over the interior (a 20 px border removed),
after removing the best-fit plane of each error map (the plane is the reference-surface
choice, not an error of the matching). Reported: measured fraction of the interior, RMSE of
semlab on its measured pixels, DeepFlow's RMSE on the same pixels, their ratio (target
<= 0.8), and the share of pixels within 1σ / 2σ of the truth (target 60-75 % within 1σ).

The variational map (:mod:`semlab.variational`, ``heightmap_from_stereo(params=
VariationalParams())``) is computed in the same run and compared with DeepFlow on *its*
measured pixels (columns "variational", "DeepFlow (same pixels)", their ratio, 1σ / 2σ).

Run:  python benchmarks/dense_map.py [--quick]     (about 2 minutes per scene on 2 cores)
      python benchmarks/dense_map.py --low-texture   (polished / real texture, larger subsets
                                                     and the smoothing prior; ~7 min per scene)
      python benchmarks/dense_map.py --no-subset     (variational and DeepFlow only; ~1 min
                                                     per scene)
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

from semlab import experiment, fusion, heightmap, pipeline, synth, validation, variational
from semlab.matching import _norm8

from bench_args import variational_params

BORDER = 20


def scenes(quick):
    out = [("speckle ±5° seed 0", dict(seed=0)),
           ("speckle ±5° seed 1", dict(seed=1)),
           ("speckle ±5° seed 2", dict(seed=2)),
           ("speckle 0/+8° seed 0", dict(seed=0, tilts_deg=(0.0, 8.0))),
           ("polished ±5° seed 0, realistic noise", dict(seed=0, texture="polished",
                                                        detector="realistic")),
           ("polished 0/+8° seed 0, realistic noise", dict(seed=0, texture="polished",
                                                          detector="realistic",
                                                          tilts_deg=(0.0, 8.0)))]
    real = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real_sem"
    if real.exists():
        out.append(("real FEI texture ±5° seed 0", dict(seed=0, source="fei")))
        out.append(("real quartz texture ±5° seed 0", dict(seed=0, source="quartz")))
    return out[:1] if quick else out


def make(folder, kw):
    kw = dict(kw)
    common = dict(n_frames=0, n_clicks=30, progress=False)
    if "source" in kw:
        from semlab import realtex

        realtex.make_experiment(folder, **common, **kw)
    else:
        synth.make_experiment(folder, write_block=False, **common, **kw)


def deepflow_heights(views, model):
    import cv2

    a, b = np.asarray(views[0], float), np.asarray(views[1], float)
    flow = cv2.optflow.createOptFlow_DeepFlow().calc(_norm8(a, 14, 2.0), _norm8(b, 14, 2.0), None)
    yy, xx = np.mgrid[0:a.shape[0], 0:a.shape[1]].astype(float)
    return model.height(xx + flow[..., 0], yy + flow[..., 1], xx, yy)


def walls(truth, interior):
    """Band walls: pixels within 3 px of the steepest 15 % of the interior (truth slope after
    a 1 px Gaussian); the rest of the interior is "flat"."""
    gy, gx = np.gradient(ndimage.gaussian_filter(truth, 1.0))
    slope = np.hypot(gx, gy)
    return ndimage.binary_dilation(slope > np.percentile(slope[interior], 85), iterations=3)


def _compare(z, sigma, valid, zd, folder, truth, interior):
    """RMSE of a map and of DeepFlow on the map's measured interior pixels
    (:func:`semlab.validation.heightmap_errors`, the plane of each error removed), σ coverage,
    and the same split into band walls (:func:`walls`) and flat parts."""
    r = validation.heightmap_errors(z, sigma, valid, folder, border_px=BORDER)
    m = r["mask"]
    e = r["err_um"]
    e_deep = validation.heightmap_errors(zd, np.ones(zd.shape), m, folder,
                                         border_px=BORDER)["err_um"]
    if len(e_deep) != len(e):   # the wall split below indexes both by the map's mask
        raise SystemExit("DeepFlow's heights are not finite on every pixel the map measured")
    sig = sigma[m].astype(float)
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    out = dict(measured=r["measured"], ours_nm=1e3 * rms(e),
               deep_nm=1e3 * rms(e_deep), ratio=rms(e) / rms(e_deep),
               in1=r["within_1sigma"], in2=r["within_2sigma"],
               median_sigma_nm=1e3 * float(np.median(sig)))
    w = walls(truth, interior)[m]
    for part, sel in (("wall", w), ("flat", ~w)):
        out[part] = dict(share=float(sel.mean()), ours_nm=1e3 * rms(e[sel]),
                         deep_nm=1e3 * rms(e_deep[sel]),
                         median_sigma_nm=1e3 * float(np.median(sig[sel])),
                         in1=float(np.mean(np.abs(e[sel]) < sig[sel])),
                         in2=float(np.mean(np.abs(e[sel]) < 2 * sig[sel])))
    return out


def run_scene(name, kw, tmp, params=None, subset=True, vparams=None):
    folder = Path(tmp) / name.split()[0] / str(abs(hash(name)))
    make(folder, kw)
    exp = experiment.load(folder)
    truth = np.load(folder / "truth" / "height_view0.npy").astype(float)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # clicks that fail refinement are reported there
        st = pipeline.run_stereo(exp, n_boot=0, progress=False)
    t_sparse = time.perf_counter() - t0
    interior = np.zeros(truth.shape, bool)
    interior[BORDER:-BORDER, BORDER:-BORDER] = True
    out = dict(scene=name, n_sparse=len(st.pts), t_sparse=t_sparse)
    t0 = time.perf_counter()
    hv = heightmap.heightmap_from_stereo(exp, st, params=vparams or variational.VariationalParams())
    out["t_var"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    zd = deepflow_heights(exp.views(), hv.model)
    out["t_deep"] = time.perf_counter() - t0
    out["deep_all_nm"] = 1e3 * validation.heightmap_errors(
        zd, np.ones(zd.shape), np.isfinite(zd), folder, border_px=BORDER)["rmse_um"]
    out["var"] = _compare(hv.z_um, hv.sigma_um, hv.valid, zd, folder, truth, interior)
    from semlab.noise import image_noise_sigma

    out["noise"] = [float(v) for v in hv.parallax.calibration.get("noise_sigma", (np.nan,) * 2)]
    out["noise_immerkaer"] = [image_noise_sigma(v) for v in exp.views()[:2]]
    out["prior_scale_px"] = float(hv.parallax.calibration.get("prior_scale_px", np.nan))
    # the flat parts' information limit: the prior scale is the median data-only 1σ of the
    # parallax of a prior_window_px² window; a w² window's is (window / w) times it
    cy, cx = (n // 2 for n in truth.shape)
    nm_per_px = 1e3 * abs(float(hv.model.height(cx + 1.0, cy, cx, cy)
                                - hv.model.height(cx + 0.0, cy, cx, cy)))
    win = (vparams or variational.VariationalParams()).prior_window_px
    out["crb_nm"] = [nm_per_px * out["prior_scale_px"] * win / w for w in (15, 25, 41)]
    if subset:
        t0 = time.perf_counter()
        hm = heightmap.heightmap_from_stereo(exp, st, params=params)
        out["t_dense"] = time.perf_counter() - t0
        out.update(_compare(hm.z_um, hm.sigma_um, hm.valid, zd, folder, truth, interior))
        out["sigma_scale"] = hm.parallax.sigma_scale
        hf = fusion.fuse_heightmaps(hm, hv)
        out["fused"] = _compare(hf.z_um, hf.sigma_um, hf.valid, zd, folder, truth, interior)
        out["fused"]["from_var"] = float(np.mean(hf.valid & (hf.sigma_um == hv.sigma_um)
                                                 & ~np.isnan(hv.sigma_um)) / hf.valid.mean())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="first scene only")
    ap.add_argument("--low-texture", action="store_true",
                    help="only the low-texture scenes (polished, real FEI), with 25x25 subsets, "
                         "min_zncc 0.3 and the smoothing prior (radius 12 px)")
    ap.add_argument("--no-subset", action="store_true",
                    help="skip the subset map (variational and DeepFlow only)")
    ap.add_argument("--scenes", type=int, nargs="+", help="indices of the scenes to run")
    ap.add_argument("--var", action="append", default=[], metavar="KEY=VALUE",
                    help="a VariationalParams field of the variational map, e.g. "
                         "--var smooth_huber=0.2 --var solver=direct (repeatable)")
    args = ap.parse_args(argv)
    vparams = variational_params(args.var)
    print(f"variational params: {vparams}")
    rows = []
    sc = scenes(args.quick)
    if args.scenes:
        sc = [sc[i] for i in args.scenes]
    params = None
    if args.low_texture:
        sc = [s for s in sc if "speckle" not in s[0]]
        params = heightmap.DenseParams(half_window=12, min_zncc=0.3, smooth_radius_px=12)
        print(f"params: {params}")
    subset = not args.no_subset
    with tempfile.TemporaryDirectory() as tmp:
        for name, kw in sc:
            r = run_scene(name, kw, tmp, params, subset, vparams)
            rows.append(r)
            v = r["var"]
            msg = (f"{name}: variational {v['ours_nm']:.1f} nm vs DeepFlow {v['deep_nm']:.1f} nm "
                   f"(ratio {v['ratio']:.2f}, measured {100 * v['measured']:.1f} %, 1σ/2σ "
                   f"{100 * v['in1']:.0f}/{100 * v['in2']:.0f} %, {r['t_var']:.0f} s; noise "
                   f"{r['noise'][0]:.4g}/{r['noise'][1]:.4g} (Immerkær "
                   f"{r['noise_immerkaer'][0]:.4g}/{r['noise_immerkaer'][1]:.4g}), prior scale "
                   f"{r['prior_scale_px']:.4g} px)")
            if subset:
                msg += (f"; subset: measured {100 * r['measured']:.1f} %, {r['ours_nm']:.1f} nm, "
                        f"DeepFlow {r['deep_nm']:.1f} nm (ratio {r['ratio']:.2f}), within 1σ "
                        f"{100 * r['in1']:.0f} %, 2σ {100 * r['in2']:.0f} %, σ scale "
                        f"{r['sigma_scale']:.2f}, times {r['t_sparse']:.0f}/{r['t_dense']:.0f}/"
                        f"{r['t_deep']:.0f} s")
                f = r["fused"]
                msg += (f"; min-σ fusion: measured {100 * f['measured']:.1f} %, "
                        f"{f['ours_nm']:.1f} nm vs DeepFlow {f['deep_nm']:.1f} nm (ratio "
                        f"{f['ratio']:.2f}), 1σ/2σ {100 * f['in1']:.0f}/{100 * f['in2']:.0f} %, "
                        f"{100 * f['from_var']:.0f} % from variational")
            print(msg, flush=True)
    if subset:
        _table(rows, "semlab", lambda r: r, "dense time", lambda r, m: f"{r['t_dense']:.0f} s")
        _table(rows, "min-σ fusion", lambda r: r["fused"], "from variational",
               lambda r, m: f"{100 * m['from_var']:.0f} %")
    _table(rows, "variational", lambda r: r["var"], "time", lambda r, m: f"{r['t_var']:.0f} s")
    _split_table(rows, "variational", lambda r: r["var"])
    print("\n| scene | flat RMSE | flat median 1σ | data-only 1σ of a 15² / 25² / 41² window |")
    print("|---|---|---|---|")
    for r in rows:
        f, c = r["var"]["flat"], r["crb_nm"]
        print(f"| {r['scene']} | {f['ours_nm']:.1f} nm | {f['median_sigma_nm']:.1f} nm | "
              f"{c[0]:.1f} / {c[1]:.1f} / {c[2]:.1f} nm |")
    if subset:
        _split_table(rows, "semlab", lambda r: r)
    return rows


def _split_table(rows, label, metrics):
    """Print one markdown table of the band-wall / flat split of ``metrics(row)``."""
    print(f"\n| scene | {label}: walls (share) RMSE vs DeepFlow, 1σ / 2σ | flat RMSE vs "
          "DeepFlow, 1σ / 2σ |")
    print("|---|---|---|")
    for r in rows:
        m = metrics(r)
        w, f = m["wall"], m["flat"]
        print(f"| {r['scene']} | ({100 * w['share']:.0f} %) {w['ours_nm']:.1f} vs "
              f"{w['deep_nm']:.1f} nm, {100 * w['in1']:.0f} / {100 * w['in2']:.0f} % | "
              f"{f['ours_nm']:.1f} vs {f['deep_nm']:.1f} nm, {100 * f['in1']:.0f} / "
              f"{100 * f['in2']:.0f} % |")


def _table(rows, label, metrics, last, last_cell):
    """Print one markdown table: each scene's ``metrics(row)`` against DeepFlow on the same
    pixels, with a last column ``last`` filled by ``last_cell(row, metrics(row))``."""
    print(f"\n| scene | measured interior | {label} RMSE | DeepFlow RMSE (same pixels) | ratio "
          f"| within 1σ / 2σ | {last} |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        m = metrics(r)
        print(f"| {r['scene']} | {100 * m['measured']:.1f} % | {m['ours_nm']:.1f} nm | "
              f"{m['deep_nm']:.1f} nm | {m['ratio']:.2f} | {100 * m['in1']:.0f} / "
              f"{100 * m['in2']:.0f} % | {last_cell(r, m)} |")


if __name__ == "__main__":
    main()
