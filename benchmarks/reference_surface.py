"""Reference surface and tilt checks: a synthetic tall object, and the real pollen_pot1 and
brassica series.

Run:  python benchmarks/reference_surface.py [--figure] [--only=synthetic|pollen|brassica]
                                            [--backward-sigma-p=P] [--total-error] [--fixed]
      (a few minutes; --figure writes docs/reference_surface_pollen.png, the figure of
      docs/accuracy.md;
      --backward-sigma-p passes ``backward_sigma_p`` to auto_match on pollen_pot1;
      --total-error sizes its grid by the total error: ``target_sigma_px=0,
      curvature_neighbours=1``; --fixed: fixed subsets, ``target_sigma_px=None``;
      --stage9-off: brassica without stage 9, ``variational_fusion=False``)

1. Synthetic: a textured bump 6 µm tall, ``6 (1 - r²/R²)²`` with R = 14 µm, off the
   centre of a flat substrate, seen at ±9° at 0.03 µm/px, 1024×768 px (the texture and
   rendering of tests/test_matching.py, DomeScene), matched with
   semlab.matching.auto_match; heights at the known tilts. The substrate (exactly flat
   beyond R) is the rest of the view. Reported: the 5–95 % spread of its heights above the
   default reference (the dominant flat surface) and above a robust fit through all points,
   in units of the points' own height σ (from the matching σ); for Gaussian errors the floor
   is 3.29 σ.
2. Real: ../shared/data/real_sem/pollen_pot1 (4 views, tilts and pixel size unknown, a grain
   on a grooved substrate; heights in pixels), matched by semlab.matching.auto_match alone
   (defaults; the grooved substrate through its epipolar stage). Reported: the accepted
   fraction of the grid points on the grain (inside its ellipse) and on the substrate
   (outside 1.06 times it); tilts estimated (semlab.reconstruct.estimate_tilts) and levelled
   on the default reference (the dominant flat surface, RANSAC); how many of its inliers lie
   on the substrate; the error bars checked without truth: heights from view pairs (0,1),
   (2,3) and (1,2) alone, their differences over the predicted σ; the plane left across the
   substrate (weighted least squares, its change over the substrate's extent ±1σ) through
   all substrate points and through the lands only (upper envelope: the grooves, more than
   2σ below, dropped); the x-scale tilt check (semlab.tiltcheck.check_tilts); the groove
   relief: RMS height difference of substrate points 6–12 px apart across the grooves
   (along x) against along them (along y, noise only).
   Then the points valid in the reference and at least one other view
   (``MatchResult.seen_in(2)``; heights from their own views at the same levelled tilts,
   ``heights_from_tilts(..., view_valid=...)``): coverage with 2, 3 and 4 views, and their
   error bars without truth: for points valid in three views ``(r, a, b)`` the heights from
   ``(r, a)`` and ``(r, b)`` alone (independent errors: the reference positions are the
   exact grid) against their predicted σ, the same check on the all-view points for
   comparison, and, for every group (two-view points included, which no pair can check),
   the substrate heights above the reference in units of their σ, and each point's height
   against a local quadric through its 3- and 4-view neighbours (the neighbour check).
3. Real: ../shared/data/real_sem/brassica (4 views of the 3DSEM dataset, a reticulate pollen
   grain filling the views, tilts and pixel size unknown): the same checks over the whole
   view (no flat substrate): coverage, estimated tilts, the pair differences of the all-view
   points, the (r, a) − (r, b) check and the neighbour check.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from semlab.io import read_image  # noqa: E402
from semlab.matching import auto_match  # noqa: E402
from semlab.plane import fit_reference_plane, heights_above_plane  # noqa: E402
from semlab.stats import robust_sd  # noqa: E402
from semlab.reconstruct import estimate_tilts, heights_from_tilts  # noqa: E402
from semlab.surface import height_sigma, reference_surface  # noqa: E402
from semlab.tiltcheck import check_tilts, level_tilts  # noqa: E402
from test_matching import S_UM, DomeScene  # noqa: E402

POLLEN = ROOT.parent / "shared" / "data" / "real_sem" / "pollen_pot1"
#: The grain's outline in view 0 of pollen_pot1: an ellipse (centre, semi-axes x, y in px).
GRAIN_CENTRE, GRAIN_AXES = np.array([395.0, 352.0]), np.array([310.0, 340.0])
#: Substrate: outside the ellipse scaled by this (the rim and the shadow are neither).
SUBSTRATE_R = 1.06
#: The figure of docs/accuracy.md, written with --figure.
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


def _ellipse_r(xy):
    """Normalised radius of (x, y) view-0 pixels in the grain's ellipse (1 on its outline)."""
    return np.hypot((xy[:, 0] - GRAIN_CENTRE[0]) / GRAIN_AXES[0],
                    (xy[:, 1] - GRAIN_CENTRE[1]) / GRAIN_AXES[1])


def _pair_heights(P, tilt, pairs, sig_px, ref_view):
    """Heights (N, len(pairs)) of every point from each view pair alone (pixels), and their
    predicted 1σ from the matching σ (the reference view's coordinate is exact; a non-
    reference view's x error is the point's ``sigma_px``)."""
    z, zs = [], []
    for a, b in pairs:
        th = np.asarray(tilt)[[a, b]]
        z.append(heights_from_tilts(P[:, [a, b]], th, 1.0).xyz_um[:, 2])
        sa, sb = (np.where(k == ref_view, 0.0, sig_px) for k in (a, b))
        ca, cb = np.cos(np.deg2rad(th))          # two views: semlab.surface.height_sigma
        zs.append(np.sqrt(sa ** 2 * cb ** 2 + sb ** 2 * ca ** 2)
                  / abs(np.sin(np.deg2rad(th[1] - th[0]))))
    return np.column_stack(z), np.column_stack(zs)


def _neighbour_check(xy, z, zs, nv, radius=24.0, min_nb=8):
    """Each point's height against a local quadric through its neighbours valid in 3 or more
    views (itself left out), within ``radius`` pixels, weighted by their σ:
    ``u = (z − ẑ) / √(σ² + var ẑ)``. A check without truth that also reaches the points valid
    in two views: a 2-view point whose ``u`` behaves like those of the 3- and 4-view points
    (which the pair check verifies) is as trustworthy; a wrong match stands out from its
    neighbours' surface. Neighbours' subsets overlap the point's, so their errors are
    correlated and ``u`` comes out below 1 for honest σ: compare the groups, not 1.
    Returns (N,) ``u`` (NaN where fewer than ``min_nb`` neighbours)."""
    from scipy.spatial import cKDTree

    good = (nv >= 3) & np.isfinite(z) & np.isfinite(zs) & (zs > 0)
    gi = np.flatnonzero(good)
    tree = cKDTree(xy[gi])
    u = np.full(len(z), np.nan)
    for i, nb in enumerate(tree.query_ball_point(xy, radius)):
        j = gi[np.asarray(nb, int)]
        j = j[j != i]
        if len(j) < min_nb or not np.isfinite(z[i]) or not zs[i] > 0:
            continue
        d = (xy[j] - xy[i]) / radius
        A = np.column_stack([np.ones(len(j)), d, d[:, 0] ** 2, d[:, 0] * d[:, 1], d[:, 1] ** 2])
        w = 1.0 / zs[j]
        cf, *_ = np.linalg.lstsq(A * w[:, None], z[j] * w, rcond=None)
        cov = np.linalg.pinv((A * w[:, None]).T @ (A * w[:, None]))
        u[i] = (z[i] - cf[0]) / np.sqrt(zs[i] ** 2 + cov[0, 0])
    return u


def _triple_check(P, vv, rows, sigma_px, tilt, ref_view):
    """``(r, a) − (r, b)``: for the ``rows`` valid in views ``a`` and ``b`` besides the
    reference, the heights from the two pairs alone differ by their independent noise (the
    reference positions are exact grid points); after the median and a plane of the
    difference are removed, each difference over its predicted σ, pooled over the view pairs
    with at least 10 such rows (None without one)."""
    others = [j for j in range(P.shape[1]) if j != ref_view]
    us = []
    for ia, a in enumerate(others):
        for b in others[ia + 1:]:
            sel = rows & vv[:, a] & vv[:, b]
            if sel.sum() < 10:
                continue
            zab, zsab = _pair_heights(P[sel], tilt, ((ref_view, a), (ref_view, b)),
                                      sigma_px[sel], ref_view)
            dd = zab[:, 0] - zab[:, 1]
            xy1 = np.column_stack([P[sel, ref_view], np.ones(sel.sum())])
            dd = dd - np.median(dd)
            dd = dd - xy1 @ np.linalg.lstsq(xy1, dd, rcond=None)[0]
            us.append(dd / np.hypot(zsab[:, 0], zsab[:, 1]))
    return np.concatenate(us) if us else None


def _fewer_views(m, tilt, ref, ref_view, ref_index):
    """Points valid in the reference and at least one other view (``MatchResult.seen_in``):
    coverage, and their error bars checked without truth. Pairs sharing only the reference
    view (exact grid positions) have independent errors: for points valid in three views
    ``(r, a, b)`` the heights from ``(r, a)`` and ``(r, b)`` alone differ by their noise
    (after the median and a plane of the difference, per region, are removed). Points valid
    in two views cannot be checked so; for them, and the others, the substrate's heights
    above the reference plane in units of their σ (grooves included, so above 1 for all)
    compare the groups. ``ref_index``: grid indices (``source_index``) of the points the
    reference was chosen among, in the order of ``ref.inliers``. Returns the view-0 pixels,
    heights above the reference and reference-inlier flags of all these points (the
    figure)."""
    s = m.seen_in(2)
    s = s.select(np.isfinite(s.sigma_px) & (s.sigma_px > 0))   # as above: a finite σ
    vv = s.views_valid()
    nv = vv.sum(1)
    r_all = _ellipse_r(m.pts[:, ref_view])
    seen_all = m.views_valid()[:, ref_view] & (m.views_valid().sum(1) >= 2)
    nv_all = np.where(seen_all, m.views_valid().sum(1), 0)
    print("\n#### Points valid in fewer views (`MatchResult.seen_in(2)`: the reference and at "
          "least one other view)\n")
    print("| region | grid points | valid in ≥ 2 views | ≥ 3 views | all 4 views |")
    print("|---|---|---|---|---|")
    for name, sel in (("grain", r_all < 1.0), ("substrate", r_all > SUBSTRATE_R)):
        c = [int(np.sum(sel & (nv_all >= k))) for k in (2, 3, 4)]
        print(f"| {name} | {sel.sum()} | " + " | ".join(
            f"{k} ({k / sel.sum():.1%})" for k in c) + " |")
    sig = np.where(vv, np.clip(s.sigma_px, 1e-3, None)[:, None], np.inf)
    P = s.pts
    xyz = heights_from_tilts(P, tilt, 1.0, view_valid=vv).xyz_um
    zs = height_sigma(sig, tilt, 1.0)
    z = ref.heights(xyz)
    rr = _ellipse_r(P[:, ref_view])
    print("\n| check | region | points | robust SD / predicted σ | within 1σ | within 2σ |")
    print("|---|---|---|---|---|---|")
    for k_views, label in ((3, "valid in 3 views"), (4, "valid in all 4 (same check)")):
        for name, reg in (("grain", rr < 1.0), ("substrate", rr > SUBSTRATE_R)):
            u = _triple_check(P, vv, reg & (nv == k_views), s.sigma_px, tilt, ref_view)
            if u is None:
                continue
            print(f"| (r, a) − (r, b), {label} | {name} | {len(u)} | {robust_sd(u):.2f} | "
                  f"{np.mean(np.abs(u) <= 1):.0%} | {np.mean(np.abs(u) <= 2):.0%} |")
    for k_views in (2, 3, 4):
        sel = (rr > SUBSTRATE_R) & (nv == k_views)
        if sel.sum() < 10:
            continue
        u = (z[sel] - np.median(z[sel])) / zs[sel]
        print(f"| substrate height above the reference / σ, valid in {k_views} views | "
              f"substrate | {sel.sum()} | {robust_sd(u):.2f} | {np.mean(np.abs(u) <= 1):.0%} | "
              f"{np.mean(np.abs(u) <= 2):.0%} |")
    un = _neighbour_check(P[:, ref_view], z, zs, nv)
    print("\n| neighbour check: height − local quadric of the 3/4-view neighbours (24 px), / σ "
          "| region | points | robust SD | within 1σ | within 2σ | beyond 4σ |")
    print("|---|---|---|---|---|---|---|")
    for k_views in (2, 3, 4):
        for name, reg in (("grain", rr < 1.0), ("substrate", rr > SUBSTRATE_R)):
            sel = reg & (nv == k_views) & np.isfinite(un)
            if sel.sum() < 10:
                continue
            a = un[sel]
            print(f"| valid in {k_views} views | {name} | {sel.sum()} | {robust_sd(a):.2f} | "
                  f"{np.mean(np.abs(a) <= 1):.0%} | {np.mean(np.abs(a) <= 2):.0%} | "
                  f"{np.mean(np.abs(a) > 4):.1%} |")
    return P[:, ref_view], z, np.isin(s.source_index, np.asarray(ref_index)[ref.inliers])


def _plane_left(q, sig):
    """Weighted least-squares plane through (x, y, z) points: its height change across
    their x and y extent and that change's 1σ (from the residual scatter)."""
    a = np.column_stack([q[:, 0] - q[:, 0].mean(), q[:, 1] - q[:, 1].mean(), np.ones(len(q))])
    w = 1.0 / np.asarray(sig, float) ** 2 * np.ones(len(q))
    aw = a * np.sqrt(w)[:, None]
    coef, *_ = np.linalg.lstsq(aw, q[:, 2] * np.sqrt(w), rcond=None)
    r = q[:, 2] - a @ coef
    chi2 = float(np.sum(w * r ** 2) / (len(r) - 3))
    cov = np.linalg.inv(aw.T @ aw) * max(chi2, 1.0)
    ext = np.ptp(q[:, :2], axis=0)
    return [coef[k] * ext[k] for k in (0, 1)], [np.sqrt(cov[k, k]) * ext[k] for k in (0, 1)]


def _lands(q, zsig, n_iter=5):
    """The upper envelope of a grooved surface: a plane refitted through the points not more
    than 2σ below it (the grooves are cut into the lands, so they lie on one side)."""
    keep = np.ones(len(q), bool)
    for _ in range(n_iter):
        a = np.column_stack([q[keep, 0], q[keep, 1], np.ones(keep.sum())])
        coef, *_ = np.linalg.lstsq(a, q[keep, 2], rcond=None)
        r = q[:, 2] - np.column_stack([q[:, 0], q[:, 1], np.ones(len(q))]) @ coef
        keep = r > -2 * zsig
    return keep


def pollen():
    if not POLLEN.is_dir():
        print(f"(skipped: {POLLEN} not present)")
        return
    ims = [read_image(POLLEN / f"pot1_0{i}.jpg").data for i in range(4)]
    ref_view = 0
    t = time.perf_counter()
    bsp = [float(a.split("=", 1)[1]) for a in sys.argv if a.startswith("--backward-sigma-p=")]
    sized = (dict(target_sigma_px=0.0, curvature_neighbours=1) if "--total-error" in sys.argv
             else dict(target_sigma_px=None) if "--fixed" in sys.argv else {})
    m = auto_match(ims, ref_view=ref_view, progress=False,
                   backward_sigma_p=bsp[0] if bsp else None, **sized)
    dt = time.perf_counter() - t
    r_all = _ellipse_r(m.pts[:, ref_view])
    on_grain, on_sub = r_all < 1.0, r_all > SUBSTRATE_R
    # grid points whose subset stays inside every view (a match can exist at all)
    hw = m.params.half_window + m.params.search_px
    h, w = ims[0].shape
    shift = [np.median(m.pts[m.valid, j] - m.pts[m.valid, ref_view], axis=0) for j in range(4)]
    inside = np.all([(m.pts[:, ref_view, 0] + d[0] >= hw) & (m.pts[:, ref_view, 0] + d[0] < w - hw)
                     for d in shift], axis=0)
    print(f"\n### pollen_pot1 (real, 4 views, heights in pixels)\n\nsemlab.matching.auto_match "
          f"(defaults, backward_sigma_p={m.params.backward_sigma_p}, target_sigma_px="
          f"{m.params.target_sigma_px}, curvature_neighbours={m.params.curvature_neighbours}, "
          f"reference view {ref_view}, "
          f"{dt:.0f} s): {m.valid.sum()} of {len(m.valid)} "
          f"grid points matched in all 4 views\n")
    print("| region | grid points | accepted | coverage | of those inside every view |")
    print("|---|---|---|---|---|")
    for name, sel in (("grain", on_grain), ("substrate", on_sub)):
        print(f"| {name} | {sel.sum()} | {(sel & m.valid).sum()} | "
              f"{(sel & m.valid).sum() / sel.sum():.1%} | "
              f"{(sel & m.valid).sum() / (sel & inside).sum():.1%} |")
    v = m.only_valid()
    bad_sig = ~(np.isfinite(v.sigma_px) & (v.sigma_px > 0))
    if bad_sig.any():
        print(f"({bad_sig.sum()} accepted points without a finite σ left out)")
        v = v.select(~bad_sig)
    P = v.pts
    is_sub = _ellipse_r(P[:, ref_view]) > SUBSTRATE_R
    is_grain = _ellipse_r(P[:, ref_view]) < 1.0
    sig_px = v.sigma_px
    est = estimate_tilts(P, n_boot=200, progress=False)
    d = np.diff(est.tilt_deg)
    print(f"\n- tilts estimated (semlab.reconstruct.estimate_tilts, all accepted points): "
          f"differences {np.round(d, 3).tolist()}°, σ of the tilts "
          f"{np.round(est.tilt_sigma_deg, 3).tolist()}°")
    print(f"- matching σ (auto_match sigma_px, median): substrate {np.median(sig_px[is_sub]):.3f}"
          f" px, grain {np.median(sig_px[is_grain]):.3f} px")
    # reference surface (default: the dominant flat surface), tilts levelled on it
    tilt = est.tilt_deg
    zsig = height_sigma(np.clip(sig_px, 1e-3, None), tilt, 1.0)
    for _ in range(3):
        xyz = heights_from_tilts(P, tilt, 1.0).xyz_um
        ref = reference_surface(xyz, zsig, xy_px=P[:, ref_view])
        tilt = level_tilts(tilt, ref.plane)
    xyz = heights_from_tilts(P, tilt, 1.0).xyz_um
    zsig = height_sigma(np.clip(sig_px, 1e-3, None), tilt, 1.0)
    ref = reference_surface(xyz, zsig, xy_px=P[:, ref_view])
    z = ref.heights(xyz)
    n_in_sub = int(np.sum(ref.inliers & is_sub))
    print(f"- reference (default, dominant flat surface by RANSAC): {ref.n_inliers} inliers, "
          f"{n_in_sub} of them on the substrate ({n_in_sub / max(ref.n_inliers, 1):.0%}; "
          f"{is_sub.sum()} substrate points); levelled tilts {np.round(tilt, 2).tolist()}°; "
          f"grain median {np.median(z[is_grain]):+.0f} px")
    # pair-to-pair agreement, without truth
    pairs = ((0, 1), (2, 3), (1, 2))
    zp, zps = _pair_heights(P, tilt, pairs, sig_px, ref_view)
    print("\n| pair difference | points | robust SD of difference / predicted σ | within 1σ "
          "| within 2σ | median predicted σ (px) |")
    print("|---|---|---|---|---|---|")
    for (i, k), in (((0, 1),), ((0, 2),), ((1, 2),)):
        dz = zp[:, i] - zp[:, k]
        sd = np.hypot(zps[:, i], zps[:, k])
        for name, sel in (("grain", is_grain), ("substrate", is_sub)):
            dd = dz[sel] - np.median(dz[sel])
            dd = dd - np.column_stack([P[sel, ref_view], np.ones(sel.sum())]) @ np.linalg.lstsq(
                np.column_stack([P[sel, ref_view], np.ones(sel.sum())]), dd, rcond=None)[0]
            u = dd / sd[sel]
            rsd = robust_sd(u)
            print(f"| {pairs[i]} − {pairs[k]}, {name} | {sel.sum()} | {rsd:.2f} | "
                  f"{np.mean(np.abs(u) <= 1):.0%} | {np.mean(np.abs(u) <= 2):.0%} | "
                  f"{np.median(sd[sel]):.2f} |")
    # the plane left across the substrate: all points, and the lands only
    q = np.column_stack([xyz[is_sub, :2], z[is_sub]])
    zs_sub = zsig[is_sub]
    lands = _lands(q, zs_sub)
    ext = np.ptp(q[:, :2], axis=0)
    print(f"\nThe substrate points span {ext[0]:.0f} × {ext[1]:.0f} px (x × y).")
    print("\n| substrate points | n | plane left across the substrate: x, y (px over its extent, "
          "±1σ) | 5–95 % spread (px) |")
    print("|---|---|---|---|")
    for name, sel in (("all (lands and grooves)", np.ones(len(q), bool)),
                      ("lands only (upper envelope, grooves 2σ below dropped)", lands)):
        left, left_s = _plane_left(q[sel], zs_sub[sel])
        print(f"| {name} | {sel.sum()} | x {left[0]:+.2f} ± {left_s[0]:.2f}, y {left[1]:+.2f} ± "
              f"{left_s[1]:.2f} | {spread(q[sel, 2]):.2f} |")
    chk = check_tilts(P, tilt, float(np.median(sig_px[is_sub])), region=ref.inliers,
                      strict=False)
    print(f"\nTilt check on the reference inliers: "
          f"{'consistent' if chk.consistent else 'REFUSED'}, surface tilt {chk.pretilt_deg:+.1f}°")
    from scipy.spatial import cKDTree

    xyr, zr = P[is_sub, ref_view], z[is_sub]
    pr = cKDTree(xyr).query_pairs(13, output_type="ndarray")
    dxy = xyr[pr[:, 1]] - xyr[pr[:, 0]]
    dz = zr[pr[:, 1]] - zr[pr[:, 0]]
    along_y = (np.abs(dxy[:, 0]) < 1) & (np.abs(dxy[:, 1]) > 5)
    along_x = (np.abs(dxy[:, 1]) < 1) & (np.abs(dxy[:, 0]) > 5)
    ry, rx = (float(np.sqrt(np.mean(dz[s] ** 2))) for s in (along_y, along_x))
    relief = np.sqrt(max(rx ** 2 - ry ** 2, 0.0) / 2)
    print(f"\nGroove relief on the substrate: RMS height difference of points 6–12 px apart "
          f"along the grooves (y) {ry:.2f} px, across them (x) {rx:.2f} px, i.e. a groove "
          f"relief of {relief:.2f} px RMS beyond the noise ({along_y.sum()} / {along_x.sum()} "
          f"pairs); median height σ of the substrate points {np.median(zs_sub):.2f} px")
    xy_seen, z_seen, inl_seen = _fewer_views(m, tilt, ref, ref_view, v.source_index)
    if FIGURE:
        import matplotlib

        matplotlib.use("Agg")
        from semlab.plots import show_reference_surface

        ax = show_reference_surface(ims[ref_view], xy_seen, z_seen, inl_seen, unit="px",
                                    lim=8.0, title="pollen_pot1: heights above the "
                                    "dominant flat surface (points valid in 2+ views)")
        FIGURE.parent.mkdir(parents=True, exist_ok=True)
        ax.figure.savefig(FIGURE, dpi=80, bbox_inches="tight")
        print(f"\nfigure: {FIGURE.relative_to(ROOT)}")


def brassica(stage9_off=False):
    """The real four-view Brassica pollen series (3DSEM, Tafti et al. 2015): a tall,
    reticulate grain filling the views, tilts and pixel size unknown. Checked without truth
    as pollen_pot1 is, over the whole view (no flat substrate to level on): coverage, the
    estimated tilts, pair-to-pair agreement of the all-view points, the (r, a) − (r, b)
    check of the points valid in three and four views, and the neighbour check."""
    d = ROOT.parent / "shared" / "data" / "real_sem" / "brassica"
    if not d.is_dir():
        print(f"(skipped: {d} not present)")
        return
    ims = [read_image(d / f"Brassica0{i}.jpg").data for i in range(1, 5)]
    ref_view = 0
    t = time.perf_counter()
    m = auto_match(ims, ref_view=ref_view, progress=False, variational_fusion=not stage9_off)
    dt = time.perf_counter() - t
    nv_all = np.where(m.views_valid()[:, ref_view], m.views_valid().sum(1), 0)
    print(f"\n### brassica (real, 4 views, heights in pixels)\n\nsemlab.matching.auto_match "
          f"(defaults{', variational_fusion=False' if stage9_off else ''}, reference view "
          f"{ref_view}, {dt:.0f} s): of {len(nv_all)} grid points, valid in ≥ 2 views "
          + ", ≥ 3 ".join(f"{np.sum(nv_all >= k)} ({np.mean(nv_all >= k):.1%})" for k in (2, 3))
          + f", all 4 {np.sum(nv_all >= 4)} ({np.mean(nv_all >= 4):.1%})")
    v = m.only_valid()
    v = v.select(np.isfinite(v.sigma_px) & (v.sigma_px > 0))
    est = estimate_tilts(v.pts, n_boot=200, progress=False)
    tilt = est.tilt_deg
    print(f"\n- tilts estimated (all-view points): differences {np.round(np.diff(tilt), 3).tolist()}°, "
          f"σ {np.round(est.tilt_sigma_deg, 3).tolist()}°, rank-2 residual {est.residual_px:.3f} px; "
          f"matching σ median {np.median(v.sigma_px):.3f} px")
    pairs = ((0, 1), (2, 3), (1, 2))
    zp, zps = _pair_heights(v.pts, tilt, pairs, v.sigma_px, ref_view)
    print(f"- height range of pair (0, 1): {np.ptp(zp[:, 0]):.0f} px")
    print("\n| check | points | robust SD (px) | robust SD / predicted σ | within 1σ | within 2σ "
          "| median predicted σ (px) |")
    print("|---|---|---|---|---|---|---|")
    xy1 = np.column_stack([v.pts[:, ref_view], np.ones(len(v.pts))])
    for i, k in ((0, 1), (0, 2), (1, 2)):
        dd = zp[:, i] - zp[:, k]
        sd = np.hypot(zps[:, i], zps[:, k])
        dd = dd - np.median(dd)
        dd = dd - xy1 @ np.linalg.lstsq(xy1, dd, rcond=None)[0]
        u = dd / sd
        print(f"| {pairs[i]} − {pairs[k]}, all-view points | {len(u)} | {robust_sd(dd):.2f} | "
              f"{robust_sd(u):.2f} | {np.mean(np.abs(u) <= 1):.0%} | "
              f"{np.mean(np.abs(u) <= 2):.0%} | {np.median(sd):.2f} |")
    s = m.seen_in(2)
    s = s.select(np.isfinite(s.sigma_px) & (s.sigma_px > 0))
    vv = s.views_valid()
    nv = vv.sum(1)
    for k_views in (3, 4):
        u = _triple_check(s.pts, vv, nv == k_views, s.sigma_px, tilt, ref_view)
        if u is not None:
            print(f"| (r, a) − (r, b), valid in {k_views} views | {len(u)} | – | "
                  f"{robust_sd(u):.2f} | {np.mean(np.abs(u) <= 1):.0%} | "
                  f"{np.mean(np.abs(u) <= 2):.0%} | – |")
    sig = np.where(vv, np.clip(s.sigma_px, 1e-3, None)[:, None], np.inf)
    z = heights_from_tilts(s.pts, tilt, 1.0, view_valid=vv).xyz_um[:, 2]
    un = _neighbour_check(s.pts[:, ref_view], z, height_sigma(sig, tilt, 1.0), nv)
    for k_views in (2, 3, 4):
        sel = (nv == k_views) & np.isfinite(un)
        if sel.sum() >= 10:
            a = un[sel]
            print(f"| neighbour check (24 px quadric), valid in {k_views} views | {sel.sum()} | "
                  f"– | {robust_sd(a):.2f} | {np.mean(np.abs(a) <= 1):.0%} | "
                  f"{np.mean(np.abs(a) <= 2):.0%} | – |")


if __name__ == "__main__":
    only = [a.split("=", 1)[1] for a in sys.argv if a.startswith("--only=")]
    if not only or only[0] == "synthetic":
        synthetic()
    if not only or only[0] == "pollen":
        pollen()
    if not only or only[0] == "brassica":
        brassica(stage9_off="--stage9-off" in sys.argv)
