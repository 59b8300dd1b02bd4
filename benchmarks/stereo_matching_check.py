"""Stereo matching accuracy against the ground truth of semlab.synth experiments.

For each seed, makes a stereo experiment (±5°, 0.03 µm/px, 384×512) with semlab.synth, then

- refines the hand-click-like correspondences (``annotations/correspondences.csv``) with
  :func:`semlab.matching.refine_correspondences`;
- runs :func:`semlab.matching.auto_match`;

and compares the heights from two views,
``z = s((u1 − c) cos θ0 − (u0 − c) cos θ1) / sin(θ1 − θ0)``, with the true height of the
material seen at the reference-view position (``truth/view0_material.npz``, interpolated),
after removing a least-squares plane from the difference (the true tilt-axis offsets are
unknown to the matcher). Prints markdown tables.

Run: ``python benchmarks/stereo_matching_check.py [n_seeds]``
"""

import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from semlab.io import read_image
from semlab.matching import auto_match, refine_correspondences
from semlab.synth import make_experiment


def heights(pts, tilts_deg, s, c):
    t0, t1 = np.deg2rad(tilts_deg[:2])
    u0, u1 = pts[:, 0, 0], pts[:, 1, 0]
    return s * ((u1 - c) * np.cos(t0) - (u0 - c) * np.cos(t1)) / np.sin(t1 - t0)


def plane_removed_rms(xy, dz):
    ok = np.isfinite(dz)
    X = np.column_stack([np.ones(ok.sum()), xy[ok]])
    coef, *_ = np.linalg.lstsq(X, dz[ok], rcond=None)
    r = dz[ok] - X @ coef
    return np.sqrt(np.mean(r ** 2)), r


def true_height_at(zmap, xy):
    return ndimage.map_coordinates(zmap.astype(float), [xy[:, 1], xy[:, 0]], order=1)


def run(seed, tmp, **kw):
    root = Path(tmp) / f"exp{seed}"
    make_experiment(root, seed=seed, n_frames=0, write_block=False, progress=False)
    ims = [read_image(root / "end_state" / f"view_{i}.tif").data for i in range(2)]
    s, tilts = 0.03, (-5.0, 5.0)
    c = (ims[0].shape[1] - 1) / 2
    zmap = np.load(root / "truth" / "height_view0.npy")
    cc = np.genfromtxt(root / "annotations" / "correspondences.csv", delimiter=",", names=True)
    clicks = np.stack([np.column_stack([cc["x0_px"], cc["y0_px"]]),
                       np.column_stack([cc["x1_px"], cc["y1_px"]])], axis=1)
    rows = []
    z_raw = heights(clicks, tilts, s, c)
    zt = true_height_at(zmap, clicks[:, 0])
    rms_raw, _ = plane_removed_rms(clicks[:, 0], z_raw - zt)
    t = time.perf_counter()
    r = refine_correspondences(ims, clicks, **kw)
    dt = time.perf_counter() - t
    z = heights(r.pts, tilts, s, c)
    ok = r.valid
    rms, res = plane_removed_rms(clicks[ok, 0], (z - zt)[ok])
    pred = np.sqrt(np.mean((r.sigma_px[ok] * s / np.sin(np.deg2rad(10))) ** 2))
    rows.append((seed, "clicks raw", len(clicks), len(clicks), rms_raw * 1e3, np.nan, np.nan, 0))
    rows.append((seed, "clicks refined", len(clicks), ok.sum(), rms * 1e3,
                 np.percentile(np.abs(res), 95) * 1e3, pred * 1e3, dt))
    t = time.perf_counter()
    a = auto_match(ims, progress=False, **kw)
    dt = time.perf_counter() - t
    av = a.only_valid()
    za = heights(av.pts, tilts, s, c)
    zta = true_height_at(zmap, av.pts[:, 0])
    rms_a, res_a = plane_removed_rms(av.pts[:, 0], za - zta)
    pred = np.sqrt(np.mean((av.sigma_px * s / np.sin(np.deg2rad(10))) ** 2))
    rows.append((seed, "auto", len(a), len(av), rms_a * 1e3, np.percentile(np.abs(res_a), 95) * 1e3,
                 pred * 1e3, dt))
    return rows


def main():
    """Print the table for n_seeds seeds (argv[1], default 3)."""
    n_seeds = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    kw = {}
    print("| seed | points | tried | valid | height RMS (nm) | 95% abs (nm) | predicted σ (nm) | time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(n_seeds):
            for row in run(seed, tmp, **kw):
                print("| {} | {} | {} | {} | {:.1f} | {:.1f} | {:.1f} | {:.1f} |".format(*row))


if __name__ == "__main__":
    main()
