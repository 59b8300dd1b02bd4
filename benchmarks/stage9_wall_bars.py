"""Do stage 9's error bars hold on slip-band walls? The subset's model error kept in full.

Stage 9 of :func:`semlab.matching.auto_match` averages each point's subset match ``a`` with
the variational map ``b``. Both round a slip band's wall (their errors correlate,
``stage9_bar.md``), so the part of the subset's σ that is its model error (the relief its
window averages, ``model_x``) is not averaged away: since 2026-12-07 the average's 1σ keeps it
in full (:func:`semlab.fusion.inverse_variance`'s ``shared_sigma``). For each cell
(``accuracy_matrix.make_cell``, or a ``semlab synth`` experiment with ``default`` noise and
``#HxW`` size) this script records stage 9's inputs (``stage9_bar.record_stage9``), scores the
average's height error against the truth (parallax pixels, plane removed) and gives the
fraction within 1σ / 2σ of

- the bar with the model error kept in full (the default), and
- the bar before (``shared_sigma`` left out: the whole subset σ weighted by ``1 − w``),

over all points and by the true surface slope at the point (flat < 0.02, walls > 0.1; slope
of the true height map, nm per nm). The average itself does not change, only its bar.

Run:  python benchmarks/stage9_wall_bars.py [--cells polished/realistic/-5/5@0,...]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_matrix as am  # noqa: E402
import stage9_bar as s9  # noqa: E402

from semlab import experiment, fusion, synth  # noqa: E402

CELLS = tuple(f"{r}/{n}/{t}@0" for r in ("speckle", "polished", "real:fei", "real:quartz")
              for n in ("low", "realistic") for t in ("-5/5", "0/8")) + (
    "polished/low/-5/5@1", "polished/realistic/0/8@1", "real:quartz/realistic/-5/5@1",
    "speckle/default/-5/5@9#200x300", "polished/low/-4/4@6")


def make(tmp, spec):
    """The experiment of ``REGIME/NOISE/T0/T1@SEED[#HxW]``; NOISE ``default``: a plain
    ``semlab synth`` experiment (its default detector)."""
    cellseed, _, size = spec.partition("#")
    _, regime, noise, tilts, seed = s9.parse_cell(cellseed)
    size = tuple(int(v) for v in size.split("x")) if size else (384, 512)
    if noise == "default":
        toml = synth.make_experiment(Path(tmp) / "x", seed=seed, size=size, tilts_deg=tilts,
                                     n_frames=0, n_clicks=5, texture=regime,
                                     write_block=False, progress=False)
        return experiment.load(toml), tilts
    return am.make_cell(tmp, regime, noise, tilts, seed=seed, size=size), tilts


def score(exp, tilts, rec):
    """Rows of (class, n, within 1σ / 2σ now, before)."""
    keys = ("p0", "a", "sa", "b", "sp", "sw", "sm")
    p0, a, sa, b, sp, sw, sm = (np.asarray(rec[k], float) for k in keys)
    now = fusion.inverse_variance(a, sa, b, sp, weight_sigma_b=sw, shared_sigma=sm)
    before = fusion.inverse_variance(a, sa, b, sp, weight_sigma_b=sw)
    assert np.array_equal(now[0], before[0], equal_nan=True)     # the same average
    e = s9.errors_px(exp, tilts, p0, now[0])
    ok = np.isfinite(e) & np.isfinite(now[1]) & (now[2] > 0)    # the map was averaged in
    z_nm = 1000 * np.load(exp.truth_dir / "height_view0.npy")
    pix_nm = 1000 * exp.pixel_size_um
    slope = ndimage.map_coordinates(np.hypot(*np.gradient(z_nm)) / pix_nm,
                                    [p0[:, 1], p0[:, 0]], order=1)
    rows = []
    for name, m in (("all", ok), ("flat", ok & (slope < 0.02)), ("walls", ok & (slope > 0.1))):
        f = lambda s, k: float(np.mean(np.abs(e[m]) < k * s[m])) if m.any() else np.nan  # noqa
        rows.append((name, int(m.sum()), (f(now[1], 1), f(now[1], 2)),
                     (f(before[1], 1), f(before[1], 2))))
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", default=",".join(CELLS),
                    help="REGIME/NOISE/T0/T1@SEED[#HxW], comma-separated (default: %(default)s)")
    args = ap.parse_args(argv)
    pct = lambda f: f"{100 * f[0]:.0f} / {100 * f[1]:.0f} %"  # noqa: E731
    print("| cell | points (flat, walls) | all: now / before (within 1σ / 2σ) | flat: now / "
          "before | walls: now / before |\n|---|---|---|---|---|")
    for spec in args.cells.split(","):
        t = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            exp, tilts = make(tmp, spec)
            rows = score(exp, tilts, s9.record_stage9(exp))
        n = f"{rows[0][1]} ({rows[1][1]}, {rows[2][1]})"
        cols = " | ".join(f"{pct(r[2])} / {pct(r[3])}" for r in rows)
        print(f"| {spec} | {n} | {cols} |", flush=True)
        print(f"<!-- {spec}: {time.perf_counter() - t:.0f} s -->", flush=True)


if __name__ == "__main__":
    main()
