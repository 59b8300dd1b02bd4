"""Peak memory and time of the height map's writers and metrology on a 3072×4096 map.

The heightmap step of ``semlab run`` on a whole 12.6 Mpx map writes the map (TIFF, x3p,
Gwyddion, PLY) and computes its areal parameters and band profiles after the map itself;
each holds full-size temporaries on top of the map, the views and the dense result. This
measures each call alone (``tracemalloc`` peak above what was allocated before the call:
numpy buffers, which is what these hold) on the slip-banded surface of
``benchmarks/memory_large.py`` (float64 µm, plane removed), σ 4 nm everywhere. Run::

    python benchmarks/memory_metrology.py [--size 3072x4096] [--out RESULTS.md]
"""

from __future__ import annotations

import argparse
import datetime
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None):
    import memory_large as ml
    from semlab import formats, metrology

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="3072x4096", help="HxW of the map")
    ap.add_argument("--out", help="append the markdown table to this file")
    a = ap.parse_args(argv)
    h, w = (int(v) for v in a.size.split("x"))
    s = 0.03
    z = ml.surface_um((h, w), s).astype(np.float64)
    z -= z.mean()
    sig = np.full_like(z, 0.004)
    tmp = Path(tempfile.mkdtemp(prefix="semlab_memory_metrology_"))
    rows = []
    tracemalloc.start()

    def run(name, fn, *args, **kw):
        tracemalloc.reset_peak()
        c0 = tracemalloc.get_traced_memory()[0]
        t = time.perf_counter()
        r = fn(*args, **kw)
        dt = time.perf_counter() - t
        rows.append((name, (tracemalloc.get_traced_memory()[1] - c0) / 1e9, dt))
        print(f"{name:28s} peak +{rows[-1][1]:.2f} GB  {dt:6.1f} s", flush=True)
        return r

    run("write_float_tiff", formats.write_float_tiff, tmp / "h.tif", z, s, "z (um)", {})
    run("write_x3p", formats.write_x3p, tmp / "h.x3p", z, s)
    run("write_gsf", formats.write_gsf, tmp / "h.gsf", z, s, title="semlab")
    run("write_ply", formats.write_ply, tmp / "h.ply", z, s, sigma_um=sig, origin_px=(0, 0))
    run("surface_parameters", metrology.surface_parameters, z, s)
    bands = run("map_bands", metrology.map_bands, z, s, sigma_um=sig)
    run(f"band_profile x {len(bands)}",
        lambda: [metrology.band_profile(z, sig, s, b) for b in bands])
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    lines = [f"memory_metrology.py, {datetime.date.today()}, map {h}x{w} "
             f"({z.nbytes / 1e9:.2f} GB as float64), code {commit}", "",
             "| call | peak above the map (GB) | time (s) |", "|---|---|---|"]
    lines += [f"| {n} | {p:.2f} | {t:.1f} |" for n, p, t in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        with open(a.out, "a") as f:
            f.write("\n" + text)


if __name__ == "__main__":
    main()
