"""Is the noise of the real SEM series correlated, and would a correlated-noise covariance
change the subset σ?

Run:  python benchmarks/real_noise.py [--points 600]      (about 5 minutes on 2 cores)

The subset σ of :func:`semlab.subset.icgn_refine` is the Gauss–Newton covariance for white
noise, ``H⁻¹ (s² Jᵀ J) H⁻¹``. Noise correlated between neighbouring pixels (a detector's
bandwidth along the scan line, JPEG compression) reaches the estimate through
``Jᵀ C J`` instead (the "sandwich" covariance), which can be larger. This script measures,
on the real multi-view series in ``../shared/data/real_sem`` (quartz, pollen_pot1,
brassica), for the reference (middle) view against its two neighbours:

1. the correlation of the matched subsets' residuals at small lags ``(dx, dy)`` (the
   difference of the two images after the converged affine warp: both images' noise,
   plus any misfit), pooled as the median over subsets, next to the same statistic for
   white noise resampled through the same warps (the B-spline interpolation alone
   correlates neighbouring residuals a little);
2. the factor by which the x σ of a 21×21 affine subset would grow if ``C`` were the
   measured residual correlation instead of the white-noise one (median over subsets):
   ``sqrt(e H⁻¹ Jᵀ C_real J H⁻¹ e / e H⁻¹ Jᵀ C_white J H⁻¹ e)`` with lags up to 3 px;
3. the median ``noise_ratio`` of the subsets: residual variance over what the measured
   image noise predicts (above 1: misfit or noise the Immerkær estimate misses).

Raw images (no pre-smoothing), the matches of :func:`semlab.matching.auto_match` (defaults,
the middle view as reference) as the IC-GN start. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from semlab import matching
from semlab.io import read_image
from semlab.subset import icgn_refine

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real_sem"
SERIES = {"quartz": [f"quarz/Quarz_0{i}.png" for i in (1, 2, 3)],
          "pollen_pot1": [f"pollen_pot1/pot1_0{i}.jpg" for i in range(4)],
          "brassica": [f"brassica/Brassica0{i}.jpg" for i in range(1, 5)]}
HALF = 10
LAGS = [(dx, dy) for dy in range(4) for dx in range(-3, 4) if dy > 0 or dx > 0]
SHOWN = [(1, 0), (0, 1), (2, 0), (0, 2), (1, 1)]


def _shifted(a, dx, dy):
    """The overlapping parts ``a[i, j]`` and ``a[i + dy, j + dx]`` of the last two axes."""
    h, w = a.shape[-2:]
    x0, x1 = max(-dx, 0), w - max(dx, 0)
    return a[..., :h - dy, x0:x1], a[..., dy:, x0 + dx:x1 + dx]


def residual_patches(ref, cur_coef, pts_ref, res):
    """(n, 2h+1, 2h+1) ZNSSD residuals of the converged subsets of ``res`` (an
    ``icgn_refine`` result at ``pts_ref``); ``cur_coef``: the current image's B-spline
    coefficients."""
    ys, xs = np.mgrid[-HALF:HALF + 1, -HALF:HALF + 1]
    out = []
    for k in np.flatnonzero(res.converged):
        x0, y0 = np.round(pts_ref[k]).astype(int)
        f = ref[y0 + ys, x0 + xs]
        w = res.warp[k]
        dx, dy = x0 + xs - pts_ref[k, 0], y0 + ys - pts_ref[k, 1]
        cx = res.pts[k, 0] + (1 + w[1]) * dx + w[2] * dy
        cy = res.pts[k, 1] + w[4] * dx + (1 + w[5]) * dy
        g = ndimage.map_coordinates(cur_coef, [cy, cx], order=3, prefilter=False)
        fz, gz = f - f.mean(), g - g.mean()
        out.append(fz - np.sqrt((fz ** 2).sum() / max((gz ** 2).sum(), 1e-300)) * gz)
    return np.array(out)


def lag_correlations(patches):
    """Median over patches of each lag's correlation ``Σ r_i r_{i+d} / Σ r_i²`` (per pixel
    pair), a dict ``{(dx, dy): ρ}``."""
    p = patches - patches.mean(axis=(1, 2), keepdims=True)
    v = (p ** 2).mean(axis=(1, 2))
    return {d: float(np.median((np.prod(_shifted(p, *d), axis=0)).mean(axis=(1, 2)) / v))
            for d in LAGS}


def sigma_factor(ref, pts_ref, rho, rho_white, n=600):
    """Median over subsets of the x σ of a (2h+1)² affine subset with residual correlation
    ``rho`` over the one with ``rho_white`` (same gradients, sandwich covariance)."""
    gx = ndimage.sobel(ref, 1) / 8.0
    gy = ndimage.sobel(ref, 0) / 8.0
    ys, xs = np.mgrid[-HALF:HALF + 1, -HALF:HALF + 1].astype(float)
    basis = [np.ones_like(xs), xs, ys]
    out = []
    for p in pts_ref[:n]:
        x0, y0 = np.round(p).astype(int)
        sl = (slice(y0 - HALF, y0 + HALF + 1), slice(x0 - HALF, x0 + HALF + 1))
        J = np.stack([gx[sl] * b for b in basis] + [gy[sl] * b for b in basis])
        H = np.einsum("aij,bij->ab", J, J)
        Hi = np.linalg.inv(H)

        def middle(r):
            m = H.copy()
            for d in LAGS:
                a, b = _shifted(J, *d)
                S = np.einsum("aij,bij->ab", a, b)
                m += r[d] * (S + S.T)
            return (Hi @ m @ Hi)[0, 0]
        out.append(np.sqrt(middle(rho) / middle(rho_white)))
    return float(np.median(out))


def one_pair(ims, a, b, pts_a, pts_b, n_points, rng):
    idx = np.arange(len(pts_a))
    if len(idx) > n_points:
        idx = np.sort(rng.choice(idx, n_points, replace=False))
    pr, pg = pts_a[idx], pts_b[idx]
    res = icgn_refine(ims[a], ims[b], pr, pg, half_window=HALF)
    coef = ndimage.spline_filter(ims[b], order=3)
    real = residual_patches(ims[a], coef, pr, res)
    # white noise of the same level in both images, through the same warps
    white_ref = rng.normal(size=ims[a].shape)
    white_coef = ndimage.spline_filter(rng.normal(size=ims[b].shape), order=3)
    white = residual_patches(white_ref, white_coef, pr, res)
    rho, rho_w = lag_correlations(real), lag_correlations(white)
    conv = pr[res.converged]
    return {"n": int(res.converged.sum()), "rho": rho, "rho_white": rho_w,
            "factor": sigma_factor(ims[a], conv, rho, rho_w),
            "noise_ratio": float(np.nanmedian(res.noise_ratio))}


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=600, help="subsets per view pair")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    lines = ["| series | pair | subsets | " + " | ".join(f"ρ{d}" for d in SHOWN)
             + " | σ factor | noise ratio |", "|" + "---|" * (len(SHOWN) + 5)]
    for name, files in SERIES.items():
        if not (REAL / files[0]).exists():
            lines.append(f"| {name} | not found in {REAL}: skipped |" + " |" * (len(SHOWN) + 3))
            continue
        ims = [read_image(REAL / f).data.astype(float) for f in files]
        ref = (len(ims) - 1) // 2
        m = matching.auto_match(ims, ref_view=ref, band_aware=False, progress=False)
        for b in (ref - 1, ref + 1):
            ok = m.valid & np.all(np.isfinite(m.pts[:, b]), axis=1)
            r = one_pair(ims, ref, b, m.pts[ok, ref], m.pts[ok, b], args.points, rng)
            cells = [f"{r['rho'][d]:.2f} ({r['rho_white'][d]:.2f})" for d in SHOWN]
            lines.append(f"| {name} | {ref}→{b} | {r['n']} | " + " | ".join(cells)
                         + f" | {r['factor']:.2f} | {r['noise_ratio']:.2f} |")
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    print(f"`python benchmarks/real_noise.py --points {args.points}` on {when}, "
          f"{time.perf_counter() - t0:.0f} s. ρ(dx, dy): residual correlation at that lag, "
          "median over subsets (in brackets: white noise through the same warps); σ factor: "
          "the x σ of a 21×21 affine subset with the measured correlation over the one with "
          "the white-noise correlation (median); noise ratio: median residual variance over "
          "the noise-predicted one.\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
