"""The ``semlab`` command line.

::

    semlab init OUT --views IMG... [--frames IMG...]
                                        a new experiment folder naming existing images
    semlab info EXPERIMENT              what was loaded: views, frames, sizes, pixel size, tilts
    semlab synth OUT [--seed ...]       write a synthetic experiment folder with truth/
    semlab run EXPERIMENT --out DIR     run the analysis and write reports + result files

Errors are one line ``semlab: error: ...`` (exit code 2) naming the file, the key and the
fix; warnings are one line ``semlab: warning: ...``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import SemlabError


def _floats(text):
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _size(text):
    try:
        h, w = (int(v) for v in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW, e.g. 384x512, got {text!r}") from None
    return h, w


def _texture(text):
    if text in ("speckle", "polished", "featureless") or (text.startswith("real:") and text[5:]):
        return text
    raise argparse.ArgumentTypeError(f"expected speckle, polished, featureless or real:NAME "
                                     f"(fei, quartz, pollen or an image path), got {text!r}")


def _cmd_info(args):
    from .experiment import load

    exp = load(args.experiment)
    print(exp.summary())
    return 0


def _cmd_init(args):
    from .experiment import init_experiment

    exp = init_experiment(args.out, views=args.views, frames=args.frames, name=args.name,
                          pixel_size_um=args.pixel_size, tilt_deg=args.tilts,
                          cycles=args.cycles)
    print(f"wrote {exp.toml_path}")
    print(exp.summary())
    st = exp.stereo
    if st is not None and st.tilt_deg is None and len(st.view_paths) == 2:
        print("  next: two views without tilts give no heights; add tilt_deg = [..., ...] "
              f"under [stereo] in {exp.toml_path} (or re-run init with --tilts)")
    print(f"  next: semlab run {args.out} --out RESULTS_FOLDER")
    return 0


def _cmd_synth(args):
    import dataclasses

    from .synth import NOISE_LEVELS, make_experiment

    detector = None
    if args.noise != "gaussian":
        detector = NOISE_LEVELS[args.noise]
        if args.dose is not None:
            detector = dataclasses.replace(detector, dose_e_per_px=args.dose)
        if args.scan_jitter:
            detector = dataclasses.replace(detector, jitter_px=args.scan_jitter)
    elif args.dose is not None or args.scan_jitter:
        raise SemlabError("--dose and --scan-jitter need the detector noise model: add "
                          "--noise realistic (or --noise low)")
    kw = dict(seed=args.seed, pixel_size_um=args.pixel_size, tilts_deg=args.tilts,
              n_frames=args.frames, n_clicks=args.clicks, click_noise_px=args.click_noise,
              slip_um=args.slip, detector=detector, progress=not args.quiet)
    drift = {}
    if args.drift:
        if len(args.drift) not in (3, 4):
            raise SemlabError(f"--drift takes SHIFT_PX,ROT_DEG,SCALE[,SCAN_PX] (e.g. 30,1.2,0.003), "
                              f"got {len(args.drift)} values")
        if args.texture.startswith("real:"):
            raise SemlabError("--drift is not available with real: textures yet; use a synthetic "
                              "texture (speckle, polished, featureless)")
        drift = dict(zip(("drift_shift_px", "drift_rotation_deg", "drift_scale", "scan_drift_px"),
                         args.drift))
    if args.texture.startswith("real:"):
        from . import realtex

        path = realtex.make_experiment(args.out, args.texture[5:],
                                       size=args.size, **kw)
    else:
        path = make_experiment(args.out, size=args.size or (384, 512), texture=args.texture, **kw,
                               **drift)
    print(f"wrote {path}")
    return 0


def _settings(pairs):
    """``--set KEY=VALUE`` pairs as an analysis configuration (values in TOML syntax: true,
    12, 0.5, "subset"; a bare word is a string)."""
    from .analysis import AnalysisConfig
    from .errors import SemlabError
    from .experiment import tomllib

    d = {}
    for pair in pairs or []:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise SemlabError(f"--set {pair!r}: give KEY=VALUE, e.g. --set heightmap=false")
        try:
            d[key.strip()] = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            d[key.strip()] = value.strip()
    try:
        return AnalysisConfig.from_dict(d)
    except TypeError as exc:
        raise SemlabError(f"--set: {exc}") from None


def _cmd_run(args):
    from .report import run

    if args.scheduler:
        from .parallel import set_default_scheduler

        set_default_scheduler(args.scheduler)   # the notebooks' kernels inherit it
    only = [s.strip() for s in args.only.split(",")] if args.only else None
    out = run(args.experiment, args.out, force=args.force, only=only, progress=not args.quiet,
              config=_settings(args.set))
    print(f"results in {out}")
    return 0


def build_parser():
    p = argparse.ArgumentParser(prog="semlab", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)

    pn = sub.add_parser("init", help="write a new experiment folder naming existing images",
                        description="Write OUT/experiment.toml naming existing images (they stay "
                                    "where they are; paths relative to OUT). Pixel size and "
                                    "tilts come from the images' SEM metadata unless given. "
                                    "The file is loaded back before init returns: it writes "
                                    "nothing it cannot load.")
    pn.add_argument("out", help="new (or empty) folder for experiment.toml")
    pn.add_argument("--views", nargs="+", default=None, metavar="IMG",
                    help="end-state views at different stage tilts: files, folders or glob "
                         "patterns, in tilt order (natural order within a folder: v2 before v10)")
    pn.add_argument("--frames", nargs="+", default=None, metavar="IMG",
                    help="series frames, earliest first: files, folders or glob patterns")
    pn.add_argument("--name", default=None, help="experiment name (default: OUT's name)")
    pn.add_argument("--pixel-size", type=float, default=None,
                    help="µm per pixel (needed when the images carry no SEM metadata)")
    pn.add_argument("--tilts", type=_floats, default=None,
                    help="stage tilt of every view in degrees, comma-separated, e.g. -5,5 "
                         "(default: the metadata, or estimated from 3+ views)")
    pn.add_argument("--cycles", type=_floats, default=None,
                    help="fatigue cycles of every frame, comma-separated")
    pn.set_defaults(func=_cmd_init)

    pi = sub.add_parser("info", help="print what an experiment folder holds")
    pi.add_argument("experiment", help="experiment folder or its experiment.toml")
    pi.set_defaults(func=_cmd_info)

    ps = sub.add_parser("synth", help="write a synthetic experiment with ground truth")
    ps.add_argument("out", help="new folder to write")
    ps.add_argument("--seed", type=int, default=0)
    ps.add_argument("--tilts", type=_floats, default=[-5.0, 5.0],
                    help="stage tilts in degrees, comma-separated (default -5,5); '' for none")
    ps.add_argument("--frames", type=int, default=6, help="series frames (default 6; 0 for none)")
    ps.add_argument("--size", type=_size, default=None,
                    help="HxW pixels (default 384x512; real textures: the largest that fits, "
                         "at most 384x512)")
    ps.add_argument("--pixel-size", type=float, default=0.03, help="µm per pixel (default 0.03)")
    ps.add_argument("--clicks", type=int, default=50, help="hand-click-like correspondences")
    ps.add_argument("--click-noise", type=float, default=0.5, help="click noise in px (default 0.5)")
    ps.add_argument("--slip", type=float, default=0.15, help="slip step across bands in µm")
    ps.add_argument("--texture", type=_texture, default="speckle",
                    help="texture regime: speckle (default), polished (weak grains, sparse "
                         "particles, slip lines), featureless (bands only), or a real SEM image "
                         "carried by the known surface: real:fei, real:quartz, real:pollen "
                         "(../shared/data/real_sem) or real:PATH")
    ps.add_argument("--noise", choices=("gaussian", "low", "realistic"), default="gaussian",
                    help="gaussian: additive noise, 16-bit (default); low/realistic: SE shot "
                         "noise for a dose, per-image gain/offset, 8-bit with saturation")
    ps.add_argument("--dose", type=float, default=None,
                    help="detected electrons per pixel at full signal (overrides the --noise preset)")
    ps.add_argument("--scan-jitter", type=float, default=0.0,
                    help="scan-line jitter in px (1σ row shift; default 0)")
    ps.add_argument("--drift", type=_floats, default=None,
                    help="stage drift of every series frame but the last: SHIFT_PX,ROT_DEG,SCALE"
                         "[,SCAN_PX], e.g. 30,1.2,0.003 (truth in truth/drift.csv)")
    ps.add_argument("--quiet", action="store_true")
    ps.set_defaults(func=_cmd_synth)

    pr = sub.add_parser("run", help="run the analysis notebooks on an experiment")
    pr.add_argument("experiment", help="experiment folder or its experiment.toml")
    pr.add_argument("--out", required=True,
                    help="output folder (new or empty), outside the experiment folder")
    pr.add_argument("--force", action="store_true",
                    help="replace the semlab results in a non-empty --out folder (only once the "
                         "run has succeeded; other files are kept)")
    pr.add_argument("--only", default="", help="comma-separated notebook numbers, e.g. 04,05")
    pr.add_argument("--quiet", action="store_true")
    pr.add_argument("--set", action="append", metavar="KEY=VALUE",
                    help="an analysis setting (semlab.AnalysisConfig), e.g. --set heightmap=false "
                         "--set track_method=subset; repeatable")
    pr.add_argument("--scheduler", default="",
                    help="dask.distributed scheduler address tcp://HOST:PORT to run the tiled "
                         "matching and tracking on (default: a local cluster on this machine)")
    pr.set_defaults(func=_cmd_run)
    return p


def main(argv=None):
    """Entry point of the ``semlab`` console script. Returns the exit code."""
    args = build_parser().parse_args(argv)
    from .parallel import limit_heap_growth

    limit_heap_growth()   # the run's tiles: freed work arrays go back to the system
    try:
        return args.func(args)
    except SemlabError as exc:
        print(f"semlab: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("semlab: interrupted (no result file was written)", file=sys.stderr)
        return 130
    except OSError as exc:  # a file system refusal semlab did not foresee: still one line
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"semlab: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
