"""Spatial resolution of subset matching: a 0.1 px sinusoidal displacement on a real texture.

DIC Challenge 2.0 style (Reu et al. 2018, "DIC Challenge: developing images and guidelines
for evaluating accuracy and resolution of 2D analyses", Exp. Mech. 58, sample 14): the
current image shows the reference texture displaced by ``u(x) = A sin(2π x / T)`` in x
(``A = 0.1`` px), with the period ``T`` falling from 300 px to 10 px. The error of the
matched displacement against the true one at each point, RMS over a grid, is plotted
against ``T``: it is small while the subset is much shorter than the period and grows to
the full amplitude when it is not. semlab's fixed subsets (21×21 and 41×41, affine),
the information-sized subsets (:func:`semlab.adaptive.adaptive_icgn`, affine, h = 7 to 28,
target 0.01 px, noise measured from the matched residuals: ``noise_sigma="calibrated"``)
sized by the noise alone and by the noise and the displacement's curvature
(``curvature_neighbours=9``), and OpenCV's DeepFlow (defaults, sampled at the same
points) are measured on the same images.

Texture: the FEI BSE image of ``../shared/data/real_sem`` (data bar removed), a 256×512 px
crop; the current image is the reference's cubic-spline interpolant (quintic, mirror) at
``x - u(x)``, both with Gaussian noise of 0.5 % of the crop's grey range.

Target (issue #13): RMS <= 0.015 px wherever ``T >= 5`` subset widths.

Run: ``python benchmarks/resolution_sinusoid.py`` (about 3 minutes); prints a markdown table.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from scipy import ndimage

from semlab.adaptive import adaptive_icgn
from semlab.realtex import load_source
from semlab.subset import icgn_refine

PERIODS = (300, 200, 150, 100, 75, 50, 30, 20, 10)
AMP_PX = 0.1
NOISE_FRAC = 0.005


def images(period, seed=0, shape=(256, 512)):
    src = load_source("fei")
    r0 = (src.shape[0] - shape[0]) // 2
    c0 = (src.shape[1] - shape[1]) // 2
    ref = src[r0:r0 + shape[0], c0:c0 + shape[1]].astype(float)
    coef = ndimage.spline_filter(ref, order=5, mode="mirror")
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    u = AMP_PX * np.sin(2 * np.pi * xx / period)
    # pixel x of the current image shows the material point X with X + u(X) = x; one
    # fixed-point step is exact to A² (2π/T) ~ 6e-4 px at T = 10
    X = xx - AMP_PX * np.sin(2 * np.pi * (xx - u) / period)
    cur = ndimage.map_coordinates(coef, [yy, X], order=5, prefilter=False, mode="mirror")
    rng = np.random.default_rng(seed)
    s = NOISE_FRAC * np.ptp(ref)
    return ref + rng.normal(0, s, shape), cur + rng.normal(0, s, shape)


def truth(pts, period):
    return AMP_PX * np.sin(2 * np.pi * pts[:, 0] / period)


def _u8(a):
    a = (a - a.min()) / (np.ptp(a) + 1e-12) * 255
    return np.clip(np.round(a), 0, 255).astype(np.uint8)


def main():
    t0 = time.perf_counter()
    shape = (256, 512)
    step = 4
    ys, xs = np.mgrid[40:shape[0] - 40:step, 40:shape[1] - 40:step]
    pts = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    rows = []
    for T in PERIODS:
        ref, cur = images(T, shape=shape)
        ut = truth(pts, T)
        res = {}
        for h in (10, 20):
            r = icgn_refine(ref, cur, pts, pts, half_window=h, smooth_sigma_px=0.8)
            ok = r.converged
            res[f"fixed {2 * h + 1}²"] = (r.pts[ok, 0] - pts[ok, 0] - ut[ok], 2 * h + 1)
        for name, k_nb in (("adaptive, noise", None), ("adaptive, noise + curvature", 9)):
            a = adaptive_icgn(ref, cur, pts, pts, target_sigma_px=0.01, warp="affine",
                              half_windows=(7, 10, 14, 20, 28), smooth_sigma_px=0.8,
                              noise_sigma="calibrated", curvature_neighbours=k_nb)
            ok = a.subset.converged
            res[name] = (a.subset.pts[ok, 0] - pts[ok, 0] - ut[ok],
                         float(np.median(2 * a.half_window[ok] + 1)))
        flow = cv2.optflow.createOptFlow_DeepFlow().calc(_u8(ref), _u8(cur), None)
        fu = ndimage.map_coordinates(flow[..., 0], [pts[:, 1], pts[:, 0]], order=1)
        res["DeepFlow"] = (fu - ut, np.nan)
        rows.append((T, {k: (float(np.sqrt(np.mean(e ** 2))), w, len(e))
                         for k, (e, w) in res.items()}))
    names = list(rows[0][1])
    print(f"# Resolution: 0.1 px sinusoid on the FEI texture ({time.strftime('%Y-%m-%d')}, "
          f"{time.perf_counter() - t0:.0f} s)\n")
    print("RMS error of u (px) against the period; in brackets the subset side (median for "
          "adaptive); * where the period is at least 5 subset widths and RMS > 0.015 px.\n")
    print("| period (px) | " + " | ".join(names) + " |")
    print("|---" * (len(names) + 1) + "|")
    for T, d in rows:
        cells = []
        for k in names:
            rms, w, n = d[k]
            flag = "*" if (np.isfinite(w) and T >= 5 * w and rms > 0.015) else ""
            side = "" if not np.isfinite(w) else f" ({w:.0f})"
            cells.append(f"{rms:.4f}{side}{flag}")
        print(f"| {T} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
