"""The dense strain with and without a ZNCC floor on its subsets, against the truth.

For synthetic series with slip bands (``semlab.synth``, the demo folder, and a real-texture
series of ``semlab.realtex``), ``semlab``'s analysis runs its tracking and strain steps as
``semlab run`` does; the dense strain (``strain.npz`` ``E``: a grid of subsets matched from
the last frame into the reference frame, the gradient a plane fit over a window of grid
points) is then computed from the same subsets' displacements with every converged subset
(the default since 2026-12-07) and with the former floor ZNCC ≥ 0.95
(:func:`semlab.strain.dense_field_strain`). Each is scored against the true Green–Lagrange
strain (``truth/fields.npz``) averaged over the same gauge (a box of the strain window's
width), at the grid points where the estimate is finite: mean and RMS error per component.

Run:  python benchmarks/dense_strain_bands.py [--scenes demo,polished@1,speckle@2,real:fei@0]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.interpolate import RegularGridInterpolator

from semlab import analysis, experiment, realtex, synth
from semlab.strain import DENSE_WINDOW, dense_field_strain

HERE = Path(__file__).resolve().parent
SCENES = ("demo", "polished@1", "speckle@2", "real:fei@0")
COMPONENTS = (("E_xx", 0, 0, "Exx"), ("E_yy", 1, 1, "Eyy"), ("E_xy", 0, 1, "Exy"))


def load_scene(spec, tmp, data_root):
    """The experiment of a scene: ``demo`` (data_samples/demo), ``TEXTURE@SEED`` (synthetic
    6-frame series) or ``real:NAME@SEED`` (a real texture's series)."""
    if spec == "demo":
        return experiment.load(HERE.parent / "data_samples" / "demo")
    kind, seed = spec.split("@")
    out = Path(tmp) / "exp"
    if kind.startswith("real:"):
        toml = realtex.make_experiment(out, kind[5:], seed=int(seed), n_frames=6,
                                       progress=False, data_root=data_root)
    else:
        toml = synth.make_experiment(out, texture=kind, seed=int(seed), n_frames=6,
                                     progress=False)
    return experiment.load(toml)


def true_strain_at_grid(exp, S):
    """The true strain components averaged over the dense gauge, at the grid points."""
    f = np.load(Path(exp.truth_dir) / "fields.npz")
    step = float(f["x_px"][1] - f["x_px"][0])
    box = max(1, int(round(S["dense_gauge_um"] / exp.pixel_size_um / step)))
    gx, gy = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    pts = np.column_stack([gy.ravel(), gx.ravel()])
    return {k: RegularGridInterpolator((f["y_px"], f["x_px"]), ndimage.uniform_filter(f[k], box),
                                       bounds_error=False)(pts).reshape(gx.shape)
            for _, _, _, k in COMPONENTS}


def score(E, truth):
    """``(n, [(mean, true mean, RMS error) per component])`` at the finite grid points."""
    rows = []
    for _, i, j, k in COMPONENTS:
        e = E[..., i, j]
        m = np.isfinite(e) & np.isfinite(truth[k])
        rows.append((e[m].mean(), truth[k][m].mean(), np.sqrt(np.mean((e[m] - truth[k][m]) ** 2))))
    return int(np.isfinite(E[..., 0, 0]).sum()), rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--data-root", default=str(HERE.parent.parent / "shared" / "data" / "real_sem"))
    args = ap.parse_args(argv)
    print("| scene | subsets (ZNCC < 0.95) | dense strain | grid points | "
          + " | ".join(f"{c}: mean (truth), RMS error" for c, *_ in COMPONENTS) + " |\n"
          + "|---" * 7 + "|")
    for spec in args.scenes.split(","):
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            exp = load_scene(spec, tmp, args.data_root)
            S = analysis.Analysis(exp, out_dir=Path(tmp) / "out", progress=False).strain()
            truth = true_strain_at_grid(exp, S)
            spacing = float(S["grid_x_px"][1] - S["grid_x_px"][0]) * exp.pixel_size_um
            low = f"{S['zncc'].size} ({int((S['zncc'] < 0.95).sum())})"
            for name, min_zncc in (("every converged subset (default)", None),
                                   ("ZNCC ≥ 0.95 (before)", 0.95)):
                E = dense_field_strain(S["ux_um"], S["uy_um"], spacing, DENSE_WINDOW, S["zncc"],
                                       min_zncc)[1]
                n, rows = score(E, truth)
                print(f"| {spec} | {low} | {name} | {n} | "
                      + " | ".join(f"{a:+.4f} ({b:+.4f}), {c:.4f}" for a, b, c in rows) + " |",
                      flush=True)
        print(f"<!-- {spec}: {time.perf_counter() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    sys.exit(main())
