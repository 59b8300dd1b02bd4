"""The dense strain on series with slip bands, against the truth, with and without its parts.

For synthetic series with slip bands (``semlab.synth``, the demo folder, and a real-texture
series of ``semlab.realtex``), ``semlab``'s analysis runs its tracking and strain steps as
``semlab run`` does; the dense strain (a grid of subsets matched from the last frame into the
reference frame, the gradient a plane fit over a window of grid points) is then computed
again from the same tracks: the variational displacement map (the default,
:mod:`semlab.flow`) and the grid of subsets with and without its two parts for bands: smaller
subsets where the 21 px one does not converge (``dense_half_windows``), and the points still
without a match interpolated before the plane fits (``dense_fill``). Each is scored against two
truths relative to the same reference frame (``truth/fields.npz``): the same estimator on
the true displacement of every grid point (a perfect tracker; the RMS error is against this
one), and the Green–Lagrange strain of the true displacement gradient averaged over the dense
gauge (a box of the strain window's width), at the grid points where all are finite.

The reference methods run in the same script: OpenCV DeepFlow and DIS (fine) flows from the
last frame into the reference frame (``accuracy_matrix.dense_flows``, default settings),
sampled at the same grid points and put through the same plane fits (:func:`dense_field_strain`,
same window): a dense DIC-like displacement field with no holes, scored the same way.

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

from semlab import analysis, experiment, realtex, synth, validation
from semlab.strain import DENSE_WINDOW, dense_field_strain, strain_from_tracks

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402

HERE = Path(__file__).resolve().parent
SCENES = ("demo", "polished@1", "speckle@2", "real:fei@0")
COMPONENTS = (("E_xx", 0, 0), ("E_yy", 1, 1), ("E_xy", 0, 1))


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
    """Two truths of the dense strain from ``S``'s reference frame to the last frame, at the
    grid points: ``"tracker"``, the same estimator (:func:`dense_field_strain`, same window)
    on the true displacement of the grid points (what a perfect tracker would give), and
    ``"gauge"``, the Green–Lagrange strain of the true displacement gradient averaged over
    the dense gauge (a box of the strain window's width). Both are relative to the
    reference frame ``S["ref_frame"]``, as the measurement is."""
    f = validation.load_fields(exp.truth_dir)
    s = float(f["pixel_size_um"])
    gx, gy = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    pos = validation.true_track_positions(exp.truth_dir, np.column_stack([gx.ravel(), gy.ravel()]))
    u = (pos[-1] - pos[S["ref_frame"]]) * s  # U(x) = x_end − X_ref, µm
    spacing = float(S["grid_x_px"][1] - S["grid_x_px"][0]) * s
    E_tracker = dense_field_strain(u[:, 0].reshape(gx.shape), u[:, 1].reshape(gx.shape), spacing,
                                   DENSE_WINDOW, fill=False)[1]
    # the gauge: U's gradient on the fields' grid (end-state pixels), scaled to the part of
    # the motion after the reference frame, box-averaged, then F = (I − ∂U/∂x)⁻¹
    frac = 1.0 - float(f["f"][S["ref_frame"]])
    step = float(f["x_px"][1] - f["x_px"][0])
    box = max(1, int(round(S["dense_gauge_um"] / s / step)))
    G = np.empty(f["ux_um"].shape + (2, 2))
    for i, k in enumerate(("ux_um", "uy_um")):
        d_dy, d_dx = np.gradient(frac * f[k].astype(float), step * s)
        G[..., i, 0] = ndimage.uniform_filter(d_dx, box)
        G[..., i, 1] = ndimage.uniform_filter(d_dy, box)
    Fg = np.linalg.inv(np.eye(2) - G)
    Eg = 0.5 * (np.swapaxes(Fg, -1, -2) @ Fg - np.eye(2))
    pts = np.column_stack([gy.ravel(), gx.ravel()])
    E_gauge = np.stack([RegularGridInterpolator((f["y_px"], f["x_px"]), Eg[..., i, j],
                                                bounds_error=False)(pts) for i in (0, 1)
                        for j in (0, 1)], -1).reshape(gx.shape + (2, 2))
    return {"tracker": E_tracker, "gauge": E_gauge}


def reference_strain(frames, S, pixel_size_um):
    """The dense strain of the reference flows (DeepFlow, DIS fine) at ``S``'s grid points:
    each flow from the last frame into the reference frame, sampled there (bilinear), its
    negative the displacement ``x_end − X_ref`` (µm), through :func:`dense_field_strain` with
    the same window. ``{name: (ny, nx, 2, 2) E}``."""
    gx, gy = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    p = np.column_stack([gx.ravel(), gy.ravel()])
    flows, _ = am.dense_flows(frames[-1], frames[S["ref_frame"]])
    spacing = float(S["grid_x_px"][1] - S["grid_x_px"][0]) * pixel_size_um
    out = {}
    for name in ("DeepFlow", "DIS fine"):
        u = -am._sample_flow(flows[name], p) * pixel_size_um
        out[name] = dense_field_strain(u[:, 0].reshape(gx.shape), u[:, 1].reshape(gx.shape),
                                       spacing, DENSE_WINDOW, fill=False)[1]
    return out


def score(E, truth):
    """``(n, [(mean, tracker-truth mean, gauge-truth mean, RMS error against the tracker
    truth) per component])`` at the grid points where the estimate and truths are finite."""
    rows = []
    for _, i, j in COMPONENTS:
        e, t, g = E[..., i, j], truth["tracker"][..., i, j], truth["gauge"][..., i, j]
        m = np.isfinite(e) & np.isfinite(t) & np.isfinite(g)
        rows.append((e[m].mean(), t[m].mean(), g[m].mean(),
                     np.sqrt(np.mean((e[m] - t[m]) ** 2))))
    return int(np.isfinite(E[..., 0, 0]).sum()), rows


def coverage_row(spec, S, truth):
    """A line of the σ table: per component the median ``E_sigma``, the RMS error against
    the perfect tracker and the fractions of grid points within 1σ and 2σ of it."""
    cells = []
    for c, (_, i, j) in enumerate(COMPONENTS):
        e = S["E"][..., i, j] - truth["tracker"][..., i, j]
        sg = S["E_sigma"][..., c]
        m = np.isfinite(e) & np.isfinite(sg)
        z = np.abs(e[m]) / sg[m]
        cells.append(f"{np.median(sg[m]):.4f}, {np.sqrt(np.mean(e[m] ** 2)):.4f}, "
                     f"{np.mean(z < 1):.0%} / {np.mean(z < 2):.0%}")
    return f"| {spec} | " + " | ".join(cells) + " |"


def row(spec, ref_frame, name, counts, rows):
    """One line of the table."""
    return (f"| {spec} | {ref_frame} | {name} | {counts} | "
            + " | ".join(f"{a:+.4f} ({b:+.4f}, {g:+.4f}), {c:.4f}" for a, b, g, c in rows)
            + " |")


VARIANTS = (("variational displacement map (default)", dict(dense_method="variational")),
            ("subsets 21/15/11 px, holes filled (before)",
             dict(dense_method="subsets", dense_half_windows=(10, 7, 5), dense_fill=True)),
            ("subsets 21/15/11 px, holes left",
             dict(dense_method="subsets", dense_half_windows=(10, 7, 5), dense_fill=False)),
            ("subsets 21 px, holes filled",
             dict(dense_method="subsets", dense_half_windows=(10,), dense_fill=True)),
            ("subsets 21 px, holes left",
             dict(dense_method="subsets", dense_half_windows=(10,), dense_fill=False)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--data-root", default=str(HERE.parent.parent / "shared" / "data" / "real_sem"))
    args = ap.parse_args(argv)
    print("| scene | ref frame | dense strain | points measured (filled) | "
          + " | ".join(f"{c}: mean (perfect tracker, gauge truth), RMS error" for c, *_ in COMPONENTS)
          + " |\n" + "|---" * 7 + "|")
    sigma_rows = []
    for spec in args.scenes.split(","):
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            exp = load_scene(spec, tmp, args.data_root)
            a = analysis.Analysis(exp, out_dir=Path(tmp) / "out", progress=False)
            S0 = a.strain()
            tracks = a.tracking().tracks
            frames = exp.frames()
            truth = true_strain_at_grid(exp, S0)
            for name, kw in VARIANTS:
                S = strain_from_tracks(frames, tracks.xy, tracks.valid, exp.pixel_size_um,
                                       S0["ref_frame"], **kw)
                _, rows = score(S["E"], truth)
                matched = int(np.isfinite(S["ux_um"]).sum())
                print(row(spec, S0["ref_frame"], name, f"{matched} of {S['ux_um'].size} "
                          f"({int(S['dense_filled'].sum())})", rows), flush=True)
                if "E_sigma" in S:
                    sigma_rows.append(coverage_row(spec, S, truth))
            for name, E in reference_strain(frames, S0, exp.pixel_size_um).items():
                n, rows = score(E, truth)
                print(row(spec, S0["ref_frame"], f"OpenCV {name} (same grid and fits)",
                          f"{n} of {S0['ux_um'].size} (0)", rows), flush=True)
        print(f"<!-- {spec}: {time.perf_counter() - t:.0f} s -->", flush=True)
    print("\nThe variational map's dense strain 1σ (`E_sigma`) against the perfect tracker's "
          "strain: median σ, RMS error, fraction of grid points within 1σ / 2σ.\n\n| scene | "
          + " | ".join(f"{c}: median σ, RMS error, within 1σ / 2σ" for c, *_ in COMPONENTS)
          + " |\n" + "|---" * 4 + "|")
    print("\n".join(sigma_rows), flush=True)


if __name__ == "__main__":
    sys.exit(main())
