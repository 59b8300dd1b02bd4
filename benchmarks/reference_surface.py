"""Reference surface and tilt checks: a synthetic tall object, and the real pollen_pot1 series.

Run:  python benchmarks/reference_surface.py [--figure] [--only=synthetic|pollen]
      (a few minutes; --figure writes docs/reference_surface_pollen.png, the README's figure)

1. Synthetic: a textured bump 6 µm tall, ``6 (1 - r²/R²)²`` with R = 14 µm, off the
   centre of a flat substrate, seen at ±9° at 0.03 µm/px, 1024×768 px (the texture and
   rendering of tests/test_matching.py, DomeScene), matched with
   semlab.matching.auto_match; heights at the known tilts. The substrate (exactly flat
   beyond R) is the rest of the view. Reported: the 5–95 % spread of its heights above the
   default reference (the dominant flat surface) and above a robust fit through all points,
   in units of the points' own height σ (from the matching σ); for Gaussian errors the floor
   is 3.29 σ.
2. Real: ../shared/data/real_sem/pollen_pot1 (4 views, tilts and pixel size unknown, a grain
   on a grooved substrate; heights in pixels). Matches: auto_match over the 4 views (the
   grain) plus a grid on the substrate (outside the grain's disc) matched by ZNCC into each
   view warped by the substrate's affine map (pairwise auto matches give the map; the
   grooves run along y, so IC-GN has no y texture there). Tilts estimated
   (semlab.reconstruct.estimate_tilts), levelled on the reference surface (the substrate
   mask as reference_region), checked against the x-scales (semlab.tiltcheck.check_tilts).
   Reported: tilt differences with σ, the plane left across the substrate (its height change
   over the substrate's extent and that change's σ), and the groove relief: RMS height
   difference of substrate points 6–12 px apart across the grooves (along x) against along
   them (along y, noise only).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from semlab.io import read_image  # noqa: E402
from semlab.matching import auto_match, fit_affine  # noqa: E402
from semlab.plane import fit_reference_plane, heights_above_plane  # noqa: E402
from semlab.reconstruct import estimate_tilts, heights_from_tilts  # noqa: E402
from semlab.subset import zncc_match  # noqa: E402
from semlab.surface import height_sigma, reference_surface  # noqa: E402
from semlab.tiltcheck import check_tilts, level_tilts  # noqa: E402
from test_matching import S_UM, DomeScene  # noqa: E402

POLLEN = ROOT.parent / "shared" / "data" / "real_sem" / "pollen_pot1"
#: The grain's disc in view 0 of pollen_pot1 (centre, radius px); outside = substrate.
GRAIN_CENTRE, GRAIN_RADIUS = np.array([395.0, 355.0]), 405.0
#: Substrate grid matches need this ZNCC in every view.
MIN_ZNCC = 0.8
#: The README figure, written with --figure.
FIGURE = ROOT / "docs" / "reference_surface_pollen.png" if "--figure" in sys.argv else None


class BumpScene(DomeScene):
    """DomeScene with a compact bump ``amp (1 - r²/R²)²`` off the centre: exactly flat beyond R."""

    centre_um = (4.0, 2.0)

    def z(self, x, y):
        r2 = (np.asarray(x) - self.centre_um[0]) ** 2 + (np.asarray(y) - self.centre_um[1]) ** 2
        return self.amp * np.clip(1 - r2 / self.rad ** 2, 0, None) ** 2


def spread(z):
    return float(np.ptp(np.percentile(z, [5, 95])))


def synthetic():
    tilts = (-9.0, 9.0)
    sc = BumpScene(amp_um=6.0, radius_um=14.0, shape=(768, 1024), margin_px=200, seed=5)
    ims = [sc.render(tilts[0], seed=1), sc.render(tilts[1], gain=0.8, offset=12, seed=2)]
    t = time.perf_counter()
    m = auto_match(ims, progress=False).only_valid()
    dt = time.perf_counter() - t
    x, y = sc.material(m.pts[:, 0, 0], m.pts[:, 0, 1], tilts[0])
    zt = sc.z(x, y)
    sub = zt == 0
    xyz = heights_from_tilts(m.pts, tilts, S_UM).xyz_um
    zsig = height_sigma(np.clip(m.sigma_px, 1e-3, None), tilts, S_UM)
    err_sd = float(np.std(xyz[sub, 2] - zt[sub] - np.median(xyz[sub, 2] - zt[sub])))
    print(f"### Synthetic tall object (6 µm bump on a flat substrate, ±9°)\n\n{len(m.pts)} "
          f"matches ({dt:.0f} s), {sub.mean():.0%} on the substrate; median height σ of the "
          f"substrate points {1000 * np.median(zsig[sub]):.2f} nm from the matching σ, "
          f"{1000 * err_sd:.2f} nm actual (SD of their height errors)\n")
    print("| reference | inliers | substrate spread 5–95 % (nm) | in matching σ | in actual SD "
          "| substrate median (nm) | bump top error (nm) |")
    print("|---|---|---|---|---|---|---|")
    top = zt > 0.9 * zt.max()
    for name, ref in (("dominant flat surface (default)", reference_surface(xyz, zsig)),
                      ("robust fit through all points", None)):
        plane = fit_reference_plane(xyz) if ref is None else ref.plane
        z = heights_above_plane(xyz, plane)
        n_in = "all" if ref is None else f"{ref.n_inliers}"
        s = spread(z[sub])
        print(f"| {name} | {n_in} | {1000 * s:.1f} | {s / np.median(zsig[sub]):.1f} | "
              f"{s / err_sd:.2f} | {1000 * np.median(z[sub]):.1f} | "
              f"{1000 * np.median(z[top] - zt[top]):.0f} |")


def _substrate_grid(ims, pair_matches, step=6, half_window=10):
    """Substrate points matched in every view (see the module docstring)."""
    h, w = ims[0].shape
    gy, gx = np.mgrid[16:h - 16:step, 16:w - 16:step]
    g = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    g = g[np.hypot(*(g - GRAIN_CENTRE).T) > GRAIN_RADIUS]
    maps = [np.eye(3)]
    for p in pair_matches:  # substrate map view i -> i+1 from its auto matches
        inv = np.linalg.inv(maps[-1])
        p0 = p[:, 0] @ inv[:2, :2].T + inv[:2, 2]
        s = np.hypot(*(p0 - GRAIN_CENTRE).T) > GRAIN_RADIUS
        maps.append(np.vstack([fit_affine(p[s, 0], p[s, 1]), [0, 0, 1]]) @ maps[-1])
    pts, zn = [g], []
    for j in range(1, len(ims)):
        M = maps[j][:2]
        warped = cv2.warpAffine(ims[j].astype(np.float32), M, (w, h),
                                flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
        q, z = zncc_match(ims[0], warped, g, g, half_window=half_window, search_px=5)
        q[z < MIN_ZNCC] = np.nan
        pts.append(q @ M[:, :2].T + M[:, 2])
    P = np.stack(pts, 1)
    return P[np.all(np.isfinite(P), axis=(1, 2))]


def pollen():
    if not POLLEN.is_dir():
        print(f"(skipped: {POLLEN} not present)")
        return
    ims = [read_image(POLLEN / f"pot1_0{i}.jpg").data for i in range(4)]
    t = time.perf_counter()
    grain = auto_match(ims, ref_view=1, progress=False).only_valid().pts
    pairs = [auto_match([ims[i], ims[i + 1]], progress=False).only_valid().pts
             for i in range(3)]
    sub = _substrate_grid(ims, pairs)
    dt = time.perf_counter() - t
    P = np.concatenate([grain, sub])
    is_sub = np.r_[np.zeros(len(grain), bool), np.ones(len(sub), bool)]
    print(f"\n### pollen_pot1 (real, 4 views, heights in pixels)\n\n{len(grain)} auto matches "
          f"in all 4 views (the grain), {len(sub)} substrate grid matches ({dt:.0f} s)\n")
    est = estimate_tilts(P, n_boot=200, progress=False)
    est_g = estimate_tilts(grain, n_boot=200, progress=False)
    for name, e in (("grain + substrate", est), ("grain only (auto matches)", est_g)):
        d = np.diff(e.tilt_deg)
        print(f"- tilts from {name}: differences {np.round(d, 3).tolist()}°, σ of the tilts "
              f"{np.round(e.tilt_sigma_deg, 3).tolist()}°")
    hr = heights_from_tilts(P, est.tilt_deg, 1.0)
    # matching σ of an x coordinate from the x residuals over the 4 views (2 unknowns per
    # point, so 2 degrees of freedom); y is weakly defined along the grooves and not used
    th = np.deg2rad(est.tilt_deg)
    u_hat = hr.offsets_px[:, 0] + np.outer(hr.xyz_um[:, 0], np.cos(th)) \
        + np.outer(hr.xyz_um[:, 2], np.sin(th))
    sig_pt = np.sqrt(np.sum((P[:, :, 0] - u_hat) ** 2, axis=1) / (P.shape[1] - 2))
    sig_px = float(np.median(sig_pt[is_sub]))
    zsig = float(height_sigma(sig_px, est.tilt_deg, 1.0))
    print(f"- matching σ (x, from the 4-view x residuals): substrate {sig_px:.3f} px, grain "
          f"{np.median(sig_pt[~is_sub]):.3f} px; height σ {zsig:.2f} px")
    region = np.hypot(*(P[:, 0] - GRAIN_CENTRE).T) > GRAIN_RADIUS
    mask = np.zeros(ims[0].shape, bool)
    yy, xx = np.mgrid[:mask.shape[0], :mask.shape[1]]
    mask[np.hypot(xx - GRAIN_CENTRE[0], yy - GRAIN_CENTRE[1]) > GRAIN_RADIUS] = True
    print("\n| reference | levelled tilts (°) | inliers | plane left across all substrate "
          "points, least squares (px over its extent, ±1σ) | substrate spread 5–95 % (px) | "
          "grain median (px) | tilt check |")
    print("|---|---|---|---|---|---|---|")
    for name, kw in (("substrate mask (reference_region)", {"region": mask}),
                     ("dominant flat surface (default)", {})):
        tilt = est.tilt_deg
        for _ in range(2):
            xyz = heights_from_tilts(P, tilt, 1.0).xyz_um
            ref = reference_surface(xyz, zsig, xy_px=P[:, 0], **kw)
            tilt = level_tilts(tilt, ref.plane)
        xyz = heights_from_tilts(P, tilt, 1.0).xyz_um
        ref = reference_surface(xyz, zsig, xy_px=P[:, 0], **kw)
        z = ref.heights(xyz)
        q = np.column_stack([xyz[is_sub, :2], z[is_sub]])
        a = np.column_stack([q[:, 0] - q[:, 0].mean(), q[:, 1] - q[:, 1].mean(), np.ones(len(q))])
        coef, *_ = np.linalg.lstsq(a, q[:, 2], rcond=None)
        r = q[:, 2] - a @ coef
        cov = np.linalg.inv(a.T @ a) * (r @ r) / (len(r) - 3)
        ext = np.ptp(q[:, :2], axis=0)
        left = [coef[k] * ext[k] for k in (0, 1)]
        left_sig = [np.sqrt(cov[k, k]) * ext[k] for k in (0, 1)]
        rob = fit_reference_plane(q)  # robust: less moved by the one-sided grooves
        left_r = [rob[k] * ext[k] for k in (0, 1)]
        chk = check_tilts(P, tilt, sig_px, region=ref.inliers, strict=False)
        n_sub_in = int(np.sum(ref.inliers & is_sub))
        print(f"| {name} | {np.round(tilt, 2).tolist()} | {ref.n_inliers} ({n_sub_in} of "
              f"{is_sub.sum()} substrate) | x {left[0]:+.2f} ± {left_sig[0]:.2f}, "
              f"y {left[1]:+.2f} ± {left_sig[1]:.2f} (robust: x {left_r[0]:+.2f}, y "
              f"{left_r[1]:+.2f}) | {spread(z[is_sub]):.1f} | "
              f"{np.median(z[~is_sub]):.0f} | {'consistent' if chk.consistent else 'REFUSED'},"
              f" surface tilt {chk.pretilt_deg:+.1f}° |")
        if kw:
            zr, xyr = z[is_sub], P[is_sub, 0]
            fig_args = (ims[0], P[:, 0], z, ref.inliers)
    from scipy.spatial import cKDTree

    pr = cKDTree(xyr).query_pairs(13, output_type="ndarray")
    d = xyr[pr[:, 1]] - xyr[pr[:, 0]]
    dz = zr[pr[:, 1]] - zr[pr[:, 0]]
    along_y = (np.abs(d[:, 0]) < 1) & (np.abs(d[:, 1]) > 5)
    along_x = (np.abs(d[:, 1]) < 1) & (np.abs(d[:, 0]) > 5)
    ry, rx = (float(np.sqrt(np.mean(dz[s] ** 2))) for s in (along_y, along_x))
    relief = np.sqrt(max(rx ** 2 - ry ** 2, 0.0) / 2)
    print(f"\nGroove relief on the substrate (reference = substrate mask): RMS height "
          f"difference of points 6–12 px apart along the grooves (y) {ry:.2f} px, across them "
          f"(x) {rx:.2f} px, i.e. a groove relief of {relief:.2f} px RMS beyond the noise "
          f"({along_y.sum()} / {along_x.sum()} pairs); height σ from the matching {zsig:.2f} px")
    if FIGURE:
        import matplotlib

        matplotlib.use("Agg")
        from semlab.plots import show_reference_surface

        ax = show_reference_surface(*fig_args, unit="px", lim=8.0, title="pollen_pot1: heights "
                                    "above the substrate")
        FIGURE.parent.mkdir(parents=True, exist_ok=True)
        ax.figure.savefig(FIGURE, dpi=80, bbox_inches="tight")
        print(f"\nfigure: {FIGURE.relative_to(ROOT)}")


if __name__ == "__main__":
    only = [a.split("=", 1)[1] for a in sys.argv if a.startswith("--only=")]
    if not only or only[0] == "synthetic":
        synthetic()
    if not only or only[0] == "pollen":
        pollen()
