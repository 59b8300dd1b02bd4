"""Strain end to end: a synthetic series under a known uniform strain, through tracking.

Run:  python benchmarks/strain_accuracy.py

semlab.synth makes a frontal series whose displacement from the first to the last frame is a
uniform small strain (no slip bands); semlab.pipeline.run_tracking tracks it backwards and
derives the strain (dense IC-GN grid, Delaunay triangles, local least squares). The table
compares the median Green–Lagrange strain with the truth (truth/fields.npz).
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np

from semlab import experiment, pipeline, synth, validation


def run(strain=(0.02, -0.01, 0.008), method="lk", seed=0):
    with tempfile.TemporaryDirectory() as tmp:
        toml = synth.make_experiment(Path(tmp) / "e", seed=seed, tilts_deg=(), n_frames=4,
                                     slip_um=0.0, uniform_strain=strain, early_contrast=1.0,
                                     progress=False)
        exp = experiment.load(toml)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            r = pipeline.run_tracking(exp, method=method, progress=False)
        f = validation.load_fields(exp.root)
        S = r.strain
        # U(x) = E x (end-state coordinates); frame r holds x - (1 - f_r) E x, so the deformation
        # from the pipeline's reference frame r to the end is F = (I - (1 - f_r) E)^-1 exactly
        frac = 1.0 - f["f"][S["ref_frame"]]
        Em = np.array([[strain[0], strain[2]], [strain[2], strain[1]]])
        Fm = np.linalg.inv(np.eye(2) - frac * Em)
        GL = 0.5 * (Fm.T @ Fm - np.eye(2))
        true_part = np.array([GL[0, 0], GL[1, 1], GL[0, 1]])
        out = {}
        for name, E in (("dense", S["E"]), ("triangles", S["E_tri"]), ("local LSQ", S["E_lsq"])):
            axes = tuple(range(E.ndim - 2))
            m = np.nanmedian(E, axis=axes)
            out[name] = np.array([m[0, 0], m[1, 1], m[0, 1]])
        return true_part, out, S["ref_frame"]


def main():
    print("| method | strain component | truth | measured | relative error |")
    print("|---|---|---|---|---|")
    for method in ("lk", "subset"):
        true, out, ref = run(method=method)
        for name, m in out.items():
            for k, comp in enumerate(("Exx", "Eyy", "Exy")):
                rel = abs(m[k] / true[k] - 1) * 100
                print(f"| {method}, {name} (ref frame {ref}) | {comp} | {true[k]:.5f} | {m[k]:.5f} | {rel:.1f} % |")


if __name__ == "__main__":
    main()
