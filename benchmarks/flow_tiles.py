"""The dense strain's displacement map in tiles: equal to the whole-frame solve, and its memory.

Frames wider or taller than ``FlowParams.tile_px`` (768 px) are solved in core tiles with a
halo (:mod:`semlab.flow`). Two checks:

1. **Tiled = untiled** on the series of ``dense_strain_bands.py`` (the demo folder and the
   real FEI texture's series, 384×512 frames with slip bands): ``strain_from_tracks`` with
   ``FlowParams(tile_px=192)`` (6 tiles, 64 px halo) against the default (one solve), from
   the same tracks: the largest difference of the dense strain in units of its 1σ
   (``E_sigma``), and both strains' RMS error against the perfect tracker.
2. **A large frame**: a band-limited random texture of ``--size`` (default 1536×2048,
   3.1 Mpx; above the 1.5 Mpx that one solve could take within 3 GB) displaced by a smooth
   field (a 0.2 % stretch, a 0.1 % compression and 0.3 px of shift) with noise, solved from
   zero with the 1σ's 16 draws as ``strain_from_tracks`` does, in a fresh process: peak
   RSS (``ru_maxrss``), time, tiles, RMS error against the true field away from the borders.

Run::

    python benchmarks/flow_tiles.py                       # both, ~15 min on 2 cores
    python benchmarks/flow_tiles.py --skip-large
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

LARGE = r'''
import resource, sys, time
import numpy as np
from scipy import ndimage
from semlab.flow import variational_flow
H, W = {h}, {w}
rng = np.random.default_rng(0)
f0 = 100 + 400 * ndimage.gaussian_filter(rng.normal(size=(H, W)), 2.0)
yy, xx = np.mgrid[0:H, 0:W].astype(float)
u_true = 0.002 * (xx - W / 2) + 0.3
v_true = -0.001 * (yy - H / 2)
f1 = ndimage.map_coordinates(f0, [yy - v_true, xx - u_true], order=3, mode="nearest")
f0 = f0 + rng.normal(0, 5, f0.shape)
f1 = f1 + rng.normal(0, 5, f0.shape)
g = np.column_stack([xx[8::16, 8::16].ravel(), yy[8::16, 8::16].ravel()])
del xx, yy
t = time.perf_counter()
u, v, info = variational_flow(f0, f1, np.zeros((H, W)), np.zeros((H, W)), n_samples=16,
                              sample_at=g.astype(int))
dt = time.perf_counter() - t
m = (slice(40, -40), slice(40, -40))
print(f"| {{H}}×{{W}} ({{H * W / 1e6:.1f}} Mpx) | {{info['tiles']}} | "
      f"{{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f}} GB | {{dt:.0f}} s | "
      f"{{np.sqrt(np.mean((u - u_true)[m] ** 2)):.4f}} / {{np.sqrt(np.mean((v - v_true)[m] ** 2)):.4f}} px | "
      f"{{np.median(info['samples_px'].std(0), 0).round(4).tolist()}} |")
'''


def equality(spec, data_root):
    import dense_strain_bands as dsb
    from semlab import analysis
    from semlab.flow import FlowParams
    from semlab.strain import strain_from_tracks

    with tempfile.TemporaryDirectory() as tmp:
        exp = dsb.load_scene(spec, tmp, data_root)
        a = analysis.Analysis(exp, out_dir=Path(tmp) / "out", progress=False)
        S0 = a.strain()
        tracks = a.tracking().tracks
        frames = exp.frames()
        truth = dsb.true_strain_at_grid(exp, S0)
        kw = dict(pixel_size_um=exp.pixel_size_um, ref_frame=S0["ref_frame"])
        out = {}
        for name, prm in (("untiled", None), ("tiled", FlowParams(tile_px=192))):
            t = time.perf_counter()
            S = strain_from_tracks(frames, tracks.xy, tracks.valid, dense_flow_params=prm, **kw)
            out[name] = (S, time.perf_counter() - t, dsb.score(S["E"], truth)[1])
    (Su, tu, ru), (St, tt, rt) = out["untiled"], out["tiled"]
    d = [np.nanmax(np.abs(St["E"][..., i, j] - Su["E"][..., i, j]) / Su["E_sigma"][..., c])
         for c, (_, i, j) in enumerate(dsb.COMPONENTS)]

    def rms(rows):
        return " / ".join(f"{r[-1]:.4f}" for r in rows)
    return (f"| {spec} | {St['dense_flow_tiles']} | {' / '.join(f'{x:.3f}' for x in d)} | "
            f"{rms(ru)} | {rms(rt)} | {tu:.0f} / {tt:.0f} s |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="demo,real:fei@0")
    ap.add_argument("--size", default="1536x2048")
    ap.add_argument("--skip-large", action="store_true")
    ap.add_argument("--data-root", default=str(HERE.parent.parent / "shared" / "data" / "real_sem"))
    args = ap.parse_args(argv)
    print(f"`python benchmarks/flow_tiles.py` on {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n")
    print("| scene | tiles | max |tiled − untiled| / σ (E_xx / E_yy / E_xy) | RMS error untiled "
          "(E_xx / E_yy / E_xy) | RMS error tiled | time untiled / tiled |\n|---|---|---|---|---|---|",
          flush=True)
    for spec in args.scenes.split(","):
        print(equality(spec, args.data_root), flush=True)
    if not args.skip_large:
        h, w = (int(x) for x in args.size.split("x"))
        print("\n| frame | tiles | peak RSS | time | RMS error u / v | median posterior 1σ (u, v) px |"
              "\n|---|---|---|---|---|---|", flush=True)
        r = subprocess.run([sys.executable, "-c", LARGE.format(h=h, w=w)], capture_output=True,
                           text=True)
        print(r.stdout.strip() or r.stderr[-2000:], flush=True)


if __name__ == "__main__":
    sys.exit(main())
