"""What the refined clicks' information-offset rule leaves out, against the truth.

``refine_correspondences(max_info_offset=2/3)`` invalidates a click whose subset's x
information is centred more than 2/3 of its half size from the click ("texture-free around
the click"): such a match can give the parallax of texture elsewhere (the case it was made
for, a texture-free background beside a step's edge, is
``tests/test_matching.py::test_click_on_flat_background_beside_an_edge_is_flagged``). This
script refines the hand-click-like correspondences of synthetic and real-texture
experiments with the rule and without it, and reports, for the clicks the rule leaves out,
their parallax error against the truth and that error over their predicted σ with the rule
off: a rule that earns its place leaves out clicks whose error their σ does not cover.

Run:  python benchmarks/info_offset_clicks.py [SPEC ...]   (SPEC: TEXTURE@SEED@TILTS)
"""

from __future__ import annotations

import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy import ndimage

from semlab import experiment, realtex, synth
from semlab.refine import refine_correspondences

HERE = Path(__file__).resolve().parent
SPECS = ("polished@0@-5,5", "polished@1@-5,5", "polished@2@-5,5", "polished@1@-5,0,5",
         "speckle@1@-5,0,5", "real:fei@0@-5,5", "real:quartz@1@-5,5", "polished@0@0,8")
DATA = HERE.parent.parent / "shared" / "data" / "real_sem"


def true_click_positions(exp, shape, pts_view0, tilts):
    """(N, V, 2) true pixel positions, in every view (``shape`` (H, W)), of the material
    points under the view-0 clicks (``truth/view0_material.npz``, the affine camera of
    ``semlab.synth``)."""
    m = np.load(Path(exp.truth_dir) / "view0_material.npz")
    c = synth.image_center(shape)
    s = exp.pixel_size_um
    co = [pts_view0[:, 1], pts_view0[:, 0]]
    X, Y, Z = (ndimage.map_coordinates(m[k].astype(float), co, order=1)
               for k in ("x_um", "y_um", "z_um"))
    t = np.deg2rad(tilts)
    return np.stack([np.column_stack([c[0] + (X * np.cos(a) + Z * np.sin(a)) / s, c[1] + Y / s])
                     for a in t], 1)


def run(spec, tmp):
    kind, seed, tl = spec.split("@")
    tilts = tuple(float(t) for t in tl.split(","))
    if kind.startswith("real:"):
        toml = realtex.make_experiment(Path(tmp) / "e", kind[5:], seed=int(seed), tilts_deg=tilts,
                                       n_frames=0, progress=False, data_root=DATA)
    else:
        toml = synth.make_experiment(Path(tmp) / "e", texture=kind, seed=int(seed),
                                     tilts_deg=tilts, n_frames=0, progress=False)
    exp = experiment.load(toml)
    views, pts = exp.views(), exp.correspondences().pts
    true = true_click_positions(exp, views[0].shape, pts[:, 0], tilts)
    on = refine_correspondences(views, pts)
    off = refine_correspondences(views, pts, max_info_offset=None)
    left = ~np.asarray(on.valid) & (np.char.find(np.asarray(on.reason).astype(str),
                                                 "texture-free") >= 0)
    err = np.sqrt(np.nanmean((off.pts[:, 1:, 0] - true[:, 1:, 0]) ** 2, axis=1))
    z = err / off.sigma_px
    kept = np.asarray(off.valid) & ~left
    return len(pts), int(np.asarray(on.valid).sum()), left, err, z, kept


def main(argv=None):
    specs = (argv if argv is not None else sys.argv[1:]) or SPECS
    warnings.simplefilter("ignore")
    print("| experiment | clicks | valid with the rule | left out by it | their error (px), rule off "
          "| their error / σ | the others within 2σ |\n|---|---|---|---|---|---|---|")
    for spec in specs:
        with tempfile.TemporaryDirectory() as tmp:
            n, n_on, left, err, z, kept = run(spec, tmp)
        rng = (f"{err[left].min():.3f}–{err[left].max():.3f}" if left.any() else "–")
        zr = (f"{z[left].min():.1f}–{z[left].max():.1f}" if left.any() else "–")
        print(f"| {spec} | {n} | {n_on} | {int(left.sum())} | {rng} | {zr} | "
              f"{np.mean(z[kept] <= 2):.2f} |", flush=True)


if __name__ == "__main__":
    sys.exit(main())
