"""Write the numbered notebooks in notebooks/ from the cell lists below (outputs stripped).

Run ``python tools/make_notebooks.py`` after editing; the .ipynb files are what users open.
Each notebook starts with a papermill ``parameters`` cell (experiment path, out_dir, knobs)
that defaults to the demo experiment in data_samples/.
"""

import hashlib
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parents[1] / "notebooks"

PARAMS = '''# parameters (papermill injects new values after this cell)
# experiment: the experiment folder or its experiment.toml
experiment = "../data_samples/demo"
# out_dir: folder for result files and the step cache (semlab run sets it);
# None = no result files (results are cached in ~/.cache/semlab)
out_dir = None
# config: analysis settings (semlab.AnalysisConfig fields, e.g. {"track_method": "subset"})
config = {}
# cache_dir: the step cache (semlab run sets it); None = out_dir/.semlab/cache
cache_dir = None
'''

SETUP = '''%matplotlib inline
import numpy as np
import matplotlib.pyplot as plt
import semlab
from semlab import experiment as sx, plots
exp = sx.load(experiment)
print(exp.summary())
# every result below comes from this one analysis: computed once (by semlab run, or here on
# first use) and cached in out_dir; the notebooks only show it
an = semlab.Analysis(exp, out_dir, config=config, cache_dir=cache_dir, progress=False)
'''


def md(text):
    return new_markdown_cell(text.strip("\n"))


def code(text, tags=None):
    c = new_code_cell(text.strip("\n"))
    if tags:
        c.metadata["tags"] = list(tags)
    return c


def check(text, expected):
    """A known-answer cell: ``text`` sets ``summary`` (a string of rounded key numbers) and
    prints it; on the shipped demo experiment the cell asserts ``summary == expected``, so
    nbval fails on a wrong number while the notebooks are committed without outputs. On any
    other experiment (papermill runs) it only prints.
    """
    return code(text.strip("\n") + f"""
print(summary)
# the shipped demo has a known answer: a wrong number fails the notebook (nbval in CI)
from pathlib import Path
DEMO = Path(semlab.__file__).resolve().parents[1] / "data_samples" / "demo"
if Path(experiment).resolve() in (DEMO, DEMO / "experiment.toml"):
    assert summary == {expected!r}, summary
""")


def check_demo(text, condition, extra=""):
    """A known-answer cell against the demo's ground truth: ``text`` computes the key numbers
    and prints them; on the shipped demo the cell asserts ``condition`` (an expression of
    those numbers), so nbval fails on a wrong result. On other experiments it only prints.
    ``extra``: more lines of the demo's block (indented by four spaces)."""
    return code(text.strip("\n") + f"""
# the shipped demo has a known answer: a wrong number fails the notebook (nbval in CI)
from pathlib import Path
DEMO = Path(semlab.__file__).resolve().parents[1] / "data_samples" / "demo"
if Path(experiment).resolve() in (DEMO, DEMO / "experiment.toml"):
    assert {condition}, "known answer missed on the demo: " + {condition!r}
""" + extra)


def params(extra=""):
    return code(PARAMS + extra, tags=["parameters"])


NOTEBOOKS = {}

NOTEBOOKS["00_experiment"] = [
    md("""
# 00 · The experiment

What semlab loaded from the experiment folder: the end-state stereo views (stage tilts), the
frontal image series taken during the fatigue test, the pixel size and where it came from
(the TOML file or the SEM metadata written into the TIFF tags). Every later notebook starts
from the same `semlab.experiment.load`.
"""),
    params(),
    code(SETUP),
    md("""
## End-state views
The same area seen at each stage tilt (about the image y axis). The scale bar uses the pixel
size shown above.
"""),
    code('''
if exp.stereo is None:
    print("This experiment has no [stereo] table: no end-state views to show.")
else:
    titles = [f"view {i}: tilt {'?' if exp.stereo.tilt_deg is None else f'{t:+.2f}°'}"
              for i, t in enumerate(exp.stereo.tilt_deg or [None] * len(exp.stereo.view_paths))]
    fig = plots.show_images(exp.views(), titles, exp.pixel_size_um)
    plots.show_static(fig, fmt="jpeg")  # SEM images: JPEG keeps the report small
'''),
    md("""
## The series during the test
Frame 0 is the earliest. Early frames are nearly featureless; contrast grows as slip bands
form.
"""),
    code('''
if exp.series is None:
    print("This experiment has no [series] table: no frames to show.")
else:
    frames = exp.frames()
    idx = sorted(set([0, len(frames) // 2, len(frames) - 1]))
    cyc = exp.series.cycles
    titles = [f"frame {i}" + ("" if cyc is None else f" ({cyc[i]:g} cycles)") for i in idx]
    fig = plots.show_images([frames[i] for i in idx], titles, exp.pixel_size_um)
    plots.show_static(fig, fmt="jpeg")  # SEM images: JPEG keeps the report small
'''),
    md("## Key numbers (checked against the known answer on the demo)"),
    check('''
n_views = 0 if exp.stereo is None else len(exp.stereo.view_paths)
n_frames = 0 if exp.series is None else len(exp.series.frame_paths)
summary = f"views={n_views} frames={n_frames} pixel_size_um={exp.pixel_size_um:.4f}"
''', "views=2 frames=6 pixel_size_um=0.0300"),
]

NOTEBOOKS["02_correspondences"] = [
    md("""
# 02 · Picking correspondences

Click the same surface feature in every view. A click in one view proposes the match in the
others (the orange ×: same place shifted by the offset of the points picked so far, moved onto
the yellow epipolar line once F is known, then refined by sub-pixel matching). The status
line says what to do next: click the × or press **a** to accept, drag it to adjust (a drag
starts after 3 screen pixels, so a click's wobble moves nothing), or click the right place.
Press on a marker to select it, **d** deletes, **u** undoes, **esc** drops, **h** hides the
points; every key has a button. The magnifier beside each view shows the active point at
8+ screen pixels per image pixel (clicks there work too); the toolbar zooms and pans.

**Keys reach the picker only while its image has the keyboard focus** (click in it once;
the buttons give it back). Elsewhere JupyterLab's own shortcuts act on the notebook: **a**
inserts a cell, **d d** deletes one.

**Save** writes the experiment's correspondences CSV, keeps a backup of the file it replaces
(`correspondences.bak.csv`, `.bak1.csv`, ...) and its permissions. Until then every edit is
autosaved beside it (`correspondences.autosave.json`); re-running the picker cell restores
it and says so. With `review_auto = True` the automatic matches are shown as yellow dots to
accept or reject in bulk (the visible region of view 0, or by σ).

The picker needs a live JupyterLab (ipympl). When this notebook is executed as a report, the
interactive cell only shows a still picture and the cells after it read the saved file.
"""),
    params('# review_auto: also match automatically and review those points in the picker\n'
           '# (about 15 s on the demo)\n'
           'review_auto = False\n'),
    code("%matplotlib widget\n" + SETUP.replace("%matplotlib inline\n", "")),
    code('''
from pathlib import Path
if exp.stereo is None:
    print("This experiment has no [stereo] table: nothing to pick.")
    save_path = None
else:
    save_path = exp.stereo.correspondences_path or (exp.root / "annotations" / "correspondences.csv")
    print("picks are saved to", save_path)
    if exp.stereo.correspondences_path is None:
        print('add  correspondences = "annotations/correspondences.csv"  to [stereo] in',
              exp.toml_path.name, "to use them")
'''),
    code('''
# NBVAL_SKIP  (interactive: needs a browser)
from semlab.proposals import fundamental_from_points
from semlab.widgets import picker_widget
if save_path is not None:
    auto = None
    if review_auto:
        from semlab import matching
        auto = matching.auto_match(exp.views(), progress=False).only_valid()
    known = exp.correspondences()
    F, why = fundamental_from_points(auto.pts if auto is not None and len(auto) >= 8
                                     else (known.pts if known is not None else []))
    print("epipolar line:", "shown (F from the points so far)" if F else f"not yet ({why})")
    box = picker_widget(exp.views(), save_path, F=F, auto=auto,
                        titles=[p.name for p in exp.stereo.view_paths])
    display(box)
'''),
    md("## The saved points"),
    code('''
corr = exp.correspondences() if exp.stereo is not None else None
if corr is None:
    print("No correspondences file yet: pick points above and press Save (or run automatic "
          "matching in 04_depth).")
else:
    fig = plots.show_picked_points(exp.views(), corr.pts, corr.point_id,
                                   titles=[f"view {i}" for i in range(corr.n_views)])
    plots.show_static(fig, fmt="jpeg")  # a still picture: the picker keeps the live canvas
    print(f"{corr.n_points} points in {corr.n_views} views")
'''),
]

NOTEBOOKS["01_calibration"] = [
    md("""
# 01 · Camera calibration from vanishing points

The reference method (paper §4.1): on images of an object with three families of mutually
orthogonal parallel edges (here the calibration block), the lines of each family meet at a
vanishing point. Three orthogonal vanishing points give the intrinsic matrix **K** (zero skew,
square pixels: Hartley & Zisserman §8.8) and each view's rotation **R**; the relative rotation
between the views measures the stage tilt. At SEM magnifications the projection is nearly
parallel, so the block is a calibration object imaged at lower magnification.
"""),
    params(),
    code(SETUP),
    code('''
from semlab import vanishing, io
lines = exp.lines()
if lines is None:
    print("This experiment has no lines.json: no vanishing-point calibration (heights then use "
          "the stage tilts).")
else:
    import json
    doc = json.loads(exp.stereo.lines_path.read_text())
    images = [io.read_image(exp.root / v["image"]).data if v.get("image") else None for v in doc["views"]]
    cal = vanishing.calibrate_views(lines)
    print(f"focal length {cal.focal_px:.1f} px, principal point {cal.principal_point.round(1)} px")
    print("K =\\n", cal.K.round(2))
'''),
    md("## Line families and their vanishing points (dotted: toward the vanishing point)"),
    code('''
if lines is not None:
    fig = plots.show_line_families_views(images, lines, vps=cal.vps)
    plots.show_static(fig, fmt="jpeg")  # SEM images: JPEG keeps the report small
'''),
    md("## Rotations: each view, and view i relative to view 0 (axis–angle and angles about the camera z, y, x axes)"),
    code('''
if lines is not None:
    for i in range(len(lines)):
        print(f"view {i}: R =\\n{cal.R[i].round(4)}")
        if i:
            print(f"  relative rotation {cal.angle_deg[i]:.3f}° about axis {cal.axis[i].round(3)}; "
                  f"z, y, x angles {np.round(cal.euler_zyx_deg[i], 3)} deg")
        res = np.concatenate(list(cal.residuals_px[i].values()))
        print(f"  line residuals: RMS {np.sqrt(np.mean(res ** 2)):.2f} px over {res.size} segments")
'''),
    md("## Against the truth (synthetic experiments only)"),
    code('''
if lines is not None and exp.truth_dir is not None and (exp.truth_dir / "block.json").exists():
    import json
    tb = json.loads((exp.truth_dir / "block.json").read_text())
    f_true = tb["K"][0][0]
    R0, R1 = (np.array(v["R"]) for v in tb["views"][:2])
    Rrel = R1 @ R0.T
    ang = np.degrees(np.arccos(np.clip((np.trace(Rrel.T @ cal.relative_R[1]) - 1) / 2, -1, 1)))
    print(f"focal length error {100 * (cal.focal_px / f_true - 1):+.2f} %; "
          f"relative rotation error {ang:.3f}°")
'''),
]

NOTEBOOKS["03_epipolar"] = [
    md("""
# 03 · Epipolar geometry

The fundamental matrix F relates the views: a point in view 0 must lie, in view 1, on its
epipolar line. The reference paper estimates F with the normalised eight-point algorithm
(Hartley & Zisserman Alg. 11.1); SEM views at these magnifications are parallel projections,
for which the affine F (Gold Standard, H&Z Alg. 14.1) is the right model: its epipolar lines are
parallel and perpendicular to the tilt axis. With nearly flat samples and parallel projection
the eight-point F is poorly determined — semlab says so instead of returning a bad matrix.
"""),
    params('# stability_resamples: random subsets per size in the stability plot\n'
           'stability_resamples = 40\n'),
    code(SETUP),
    code('''
from semlab import epipolar


def fit(fn, x0, x1):
    """F by one method, or None and the reason."""
    try:
        return fn(x0, x1), None
    except semlab.SemlabError as exc:
        return None, str(exc)


corr = exp.correspondences() if exp.stereo is not None else None
if corr is None:
    print("No correspondences: this notebook needs [stereo] correspondences (see 02).")
else:
    views = exp.views()
    refined = an.optional("stereo", method="refined")  # computed once, cached; None if it failed
    sets = {"clicked": corr.pts}
    if refined is not None:
        sets["refined"] = refined.pts[refined.kind == "click"]
    F = {}
    for name, p in sets.items():
        x0, x1 = p[:, 0], p[:, 1]
        for model, fn in (("affine", epipolar.fundamental_affine), ("8point", epipolar.fundamental_8point)):
            F[name, model], err = fit(fn, x0, x1)
            if err:
                print(f"{model:>6} F from {len(p)} {name} points: undetermined -- {err}")
                continue
            d = np.median(epipolar.sampson_distance(F[name, model], x0, x1))
            line = f"{model:>6} F from {len(p)} {name} points: median Sampson distance {d:.3f} px"
            if model == "affine":
                axis, _ = epipolar.affine_tilt_axis(F[name, model])
                line += f", tilt axis {axis[0]:.2f}° from x (90° = image y)"
            print(line)
    best = "refined" if "refined" in sets else "clicked"
    x0, x1 = sets[best][:, 0], sets[best][:, 1]
    Fa = F[best, "affine"]
    if Fa is not None:
        print(f"affine F ({best} points) =\\n", (Fa / np.abs(Fa).max()).round(5))
        print("epipoles (at infinity for affine views):", [e.round(4) for e in epipolar.epipoles(Fa)])
'''),
    md("## Epipolar lines over both views (affine F)"),
    code('''
if corr is not None and Fa is not None:
    fig = plots.show_epipolar_lines(views[0], views[1], Fa, x0, x1, title=f" (affine F, {best} points)")
    plots.show_static(fig, fmt="jpeg")  # SEM images: JPEG keeps the report small
'''),
    md("""
## Stability: how F settles with the number of points

For each number of points, random subsets of the clicks are fitted and compared with F from
all of them (the paper saw F settle at about 30 points).
"""),
    code('''
if corr is not None and len(x0) >= 12:
    sizes = np.unique(np.linspace(8, len(x0), 8).round().astype(int))
    stabs = {}
    for model in ("affine", "8point"):
        try:
            stabs[model] = epipolar.stability(x0, x1, sizes, n_resamples=stability_resamples,
                                              model=model, progress=False)
        except semlab.SemlabError as exc:
            print(model, ":", exc)
    fig = plots.stability_figure(stabs)
'''),
]

NOTEBOOKS["04_depth"] = [
    md("""
# 04 · Heights of the end-state surface

Heights come from the sub-pixel x-parallax between the tilted views
(`u = cx + (x cosθ + z sinθ)/s`): at ±5° and 0.03 µm/px one pixel of parallax is 0.17 µm of
height, so the matching has to be good to a few hundredths of a pixel. The chain:
correspondences (hand clicks refined by sub-pixel matching, plus automatic matching) → tilts
(experiment, SEM metadata, estimated from 3+ views, or vanishing points) → least-squares
(x, z) per point → heights above a robustly fitted reference plane, z > 0 = extrusion, with
1σ error bars (matching σ propagated, plus a bootstrap of the plane fit).

The reference method — raw clicks through the same geometry — is shown alongside: its error
is of the size of the thing measured.
"""),
    params(),
    code(SETUP),
    code('''
from semlab import surface
if exp.stereo is None:
    print("This experiment has no [stereo] table: no heights to compute.")
    res = None
else:
    res = an.optional("stereo")  # None if the step failed (its error printed)
if res is not None:
    print(f"{len(res.z_um)} points ({(res.kind == 'click').sum()} clicked, {(res.kind == 'auto').sum()} automatic), "
          f"method {res.method}")
    print(f"tilts {np.round(res.tilt_deg, 3)} deg from {res.tilt_source}; tilt axis {res.tilt_axis_deg:.2f}°")
    print(f"z from {res.z_um.min():+.3f} to {res.z_um.max():+.3f} µm; median 1σ {np.median(res.z_err_um) * 1000:.1f} nm")
    for n in res.notes:
        print("note:", n)
'''),
    md("## Height map: measured points over view 0 (colour = z; nm below 1 µm)"),
    code('''
if res is not None:
    ax = plots.show_height_points(exp.views()[0], res.pts[:, 0], res.z_um, exp.pixel_size_um)
    plots.show_static(ax.figure, dpi=100, fmt="jpeg")
'''),
    md("""## The reference surface

Heights are measured from `[stereo] reference_region` (a rectangle, polygon or mask in view
0), `reference_points` (three-point levelling) or, by default, the dominant flat surface
(RANSAC with each point's own height σ). Outlined: the points that define it.
"""),
    code('''
if res is not None:
    rs = res.calibration["reference_surface"]
    print(f"reference: {rs['method']}, {rs['n_inliers']} of {rs['n_points']} points, residual "
          f"RMS {rs['residual_rms_um'] * 1000:.1f} nm, 5-95 % spread {rs['spread_5_95_um'] * 1000:.1f} nm")
    ax = plots.show_reference_surface(exp.views()[0], res.pts[:, 0], res.z_um, res.reference.inliers)
    plots.show_static(ax.figure, dpi=100, fmt="jpeg")  # SEM image: JPEG keeps the report small
'''),
    md("## x–z and y–z projections, with 1σ error bars"),
    code('''
if res is not None:
    fig = plots.plot_height_projections(res.xyz_um, res.z_um, res.z_err_um)
'''),
    md("## Profile along the crack (points with a crack_id)"),
    code('''
profiles = surface.crack_profiles(res.xyz_um, res.z_um, res.crack_id, width_um=1.0) if res is not None else []
for cid, prof in profiles:
    ax = plots.plot_point_profile(prof["distance_um"], prof["z_um"], res.z_err_um[prof["index"]],
                                  title=f"crack {cid}: heights within 0.5 µm of its line")
if not profiles:
    print("No crack (crack_id) with two or more matched points in the correspondences.")
'''),
    md("## Trend of z with x and y (the paper saw more extrusion at high y; does this sample?)"),
    code('''
if res is not None:
    for k, name in ((0, "x"), (1, "y")):
        print(plots.trend_sentence(res.xyz_um[:, k], res.z_um, axis=name))
'''),
    md("## The reference method: raw clicks (no refinement) through the same geometry"),
    code('''
raw = (an.optional("stereo", method="raw")
       if res is not None and exp.correspondences() is not None else None)
if raw is not None:
    print(f"raw clicks: {len(raw.z_um)} points, median 1σ {np.median(raw.z_err_um) * 1000:.0f} nm "
          f"(a 0.5 px click error is ~{0.5 * 2 ** 0.5 * exp.pixel_size_um / np.sin(np.deg2rad(np.ptp(raw.tilt_deg))) * 1000:.0f} nm of height)")
'''),
    md("""
## Dense height map: every pixel of view 0

By default (`heightmap_method = "variational"`) the parallax of every pixel is found at once,
seeded by the points above: one unknown per pixel along the epipolar line, a robust data term
on the locally normalised views and an edge-preserving (Huber/TV) prior between neighbours, so
slip-band steps stay sharp while weak texture borrows from its neighbours; the prior's scale
comes from the measured image noise, and each pixel's 1σ from the posterior of the solve plus
the smoothing's bias. `heightmap_method = "subset"` matches an affine 15×15 subset at every
pixel instead (as good on speckle-like texture, but it leaves weak texture unmeasured). Heights
are above the same reference plane as the points. Written by
`semlab run` as `heightmap.tif`, `heightmap_sigma.tif`, `heightmap.x3p`, `heightmap.gsf`,
`heightmap.ply`, `surface_parameters.csv` and `bands.csv`.
"""),
    code('''
hm = None
if res is not None and not an.config.heightmap:
    print("The dense height map is switched off for this run (config heightmap = false).")
elif res is not None:
    hm, bands = an.optional("heightmap") or (None, None)  # computed once by the analysis
if hm is not None:
    print(f"measured {100 * hm.valid.mean():.1f} % of view 0; median 1σ {np.nanmedian(hm.sigma_um) * 1e3:.1f} nm "
          f"(σ scale {hm.parallax.sigma_scale:.2f} from the map itself)")
    for n in hm.notes:
        print("note:", n)
    plots.show_static(plots.show_heightmap_panels(hm.z_um, hm.sigma_um, exp.pixel_size_um),
                      fmt="jpeg")
'''),
    code('''
if hm is not None:
    plots.show_static(plots.show_hillshade(hm.z_um, exp.pixel_size_um).figure, fmt="jpeg")
'''),
    md("## Areal parameters (ISO 25178-2, `surfalize`) and profiles across the bands"),
    code('''
if hm is not None:
    measured = an.map_metrology()  # computed with the map ([metrology] regions included)
    for r in measured["surface_parameters"]:
        print(", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()))
    profs = measured["band_profiles"]
    plots.show_static(plots.show_bands(hm.z_um, bands, pixel_size_um=exp.pixel_size_um).figure,
                      fmt="jpeg")
    if profs:
        plots.plot_band_profiles(profs[:6])
'''),
    md("""
## Profile tool

Run `%matplotlib widget` first, then click two points on the map: the profile between them
appears with its ±1σ band (a third click starts a new one). Here it shows one segment across
the bands.
"""),
    code('''
if hm is not None:
    from semlab.profile_tool import ProfileTool
    tool = ProfileTool(hm.z_um, hm.sigma_um, exp.pixel_size_um, width_px=3)
    h, w = hm.z_um.shape
    tool.set_points((0.35 * w, 0.85 * h), (0.65 * w, 0.15 * h))
'''),
    md("## Key numbers against the truth (checked on the demo)"),
    check_demo('''
from semlab import validation
if res is not None and exp.truth_dir is not None:
    e = validation.height_errors(res.z_um, validation.true_height_at(exp.truth_dir, res.pts[:, 0]),
                                 res.xyz_um[:, :2])
    rmse_nm = e["rmse_um"] * 1000
    within_1sigma = float(np.mean(np.abs(e["err_um"]) <= res.z_err_um))
    within_2sigma = float(np.mean(np.abs(e["err_um"]) <= 2 * res.z_err_um))
    print(f"{e['n']} points: height RMSE {rmse_nm:.1f} nm, {100 * within_1sigma:.0f} % / "
          f"{100 * within_2sigma:.0f} % within 1σ / 2σ")
# (the points' bars are conservative since stage 9 weighs the map by its noise-plus-bias σ
# and keeps its posterior σ, and the subset's model error, for the bar: README, "Error bars";
# the demo's points were 96.99 % / 99.6 % within 1σ / 2σ on 2026-12-07, conservative on its
# flats by design since the wall term: the upper bound catches bars grown past that)
''', "e['n'] >= 500 and rmse_nm < 15 and 0.55 <= within_1sigma <= 0.99 and within_2sigma >= 0.95",
        extra="""    # its slip bands stand ~0.1 µm above a flat surface: the tilt check must not call it flat
    assert res.calibration["tilt_check"].get("relief_detected", True), "known answer missed on the demo: its bands are relief, not a flat surface"
"""),
    check_demo('''
if hm is not None and exp.truth_dir is not None:
    d = validation.heightmap_errors(hm.z_um, hm.sigma_um, hm.valid, exp.truth_dir, roi=hm.roi)
    map_rmse_nm = d["rmse_um"] * 1000
    print(f"dense map: {100 * d['measured']:.1f} % of the interior (20 px border left out) "
          f"measured, height RMSE {map_rmse_nm:.1f} nm, {100 * d['within_1sigma']:.0f} % / "
          f"{100 * d['within_2sigma']:.0f} % within 1σ / 2σ")
''', "d['measured'] > 0.95 and map_rmse_nm < 20 and 0.6 <= d['within_1sigma'] <= 0.9 "
       "and d['within_2sigma'] >= 0.9"),
]

TRACK_SETUP = '''
from semlab import stats
if exp.series is None:
    print("This experiment has no [series] table: nothing to track.")
    tr = None
else:
    tr = an.optional("tracking")  # None if the step failed (its error printed, and named by semlab run)
if tr is not None:
    t = tr.tracks
    print(f"{t.n_tracks} tracks ({(tr.seed == 'corner').sum()} corner-seeded, "
          f"{(tr.seed == 'grid').sum()} on the grid, "
          f"{(tr.seed == 'stereo').sum()} stereo-seeded), method {t.method}")
    print("valid fraction per frame (0 = earliest):", np.round(t.valid.mean(axis=1), 2))
    if tr.registration:
        print(f"stereo view 0 -> last frame registration residual {tr.registration['residual_px']:.3f} px")
'''

NOTEBOOKS["05_tracking"] = [
    md("""
# 05 · Back in time: tracking the surface through the fatigue test

During the test only a frontal view exists. Points found at the end — Shi–Tomasi corners of
the last frame and the stereo points of 04, registered into it — are tracked backwards to the
first frame (pyramidal Lucas–Kanade, or the DIC-grade subset matching), frame by frame with a
direct re-match against the last frame so drift cannot accumulate. Early frames are nearly
featureless: every step carries its forward–backward error and a valid flag, and an invalid
step suspends the track instead of turning into a jump. Results are stored by frame index,
0 = earliest.
"""),
    params(),
    code(SETUP),
    code(TRACK_SETUP),
    md("""
## Stage drift between the frames

Before tracking, every frame was registered to the last one (SIFT features, RANSAC, refined by
ECC; `drift.csv`): the shift of the image centre, the rotation about it and the
magnification change, relative to the last frame. Tracks are followed in the registered
geometry; `tracks.csv` keeps each frame's own pixels and `displacements.csv` has this rigid
motion removed (raw columns kept). Open squares: frames registered through their neighbour.
"""),
    code('''
if tr is not None and t.registration is not None:
    from semlab.registration import read_drift_csv
    truth_drift = exp.root / "truth" / "drift.csv"
    plots.plot_drift(t.registration, truth=read_drift_csv(truth_drift) if truth_drift.is_file() else None)
    for r in t.registration.table():
        print(f"frame {r['frame']}: dx {r['dx_px']:+.2f} px, dy {r['dy_px']:+.2f} px, "
              f"rotation {r['rotation_deg']:+.3f}°, scale {r['scale']:.5f} ({r['method']})")
'''),
    md("## Tracks over the frames, latest first (at most 4 frames)"),
    code('''
if tr is not None:
    fig = plots.tracks_overview(exp.frames(), t.xy, t.valid, cycles=exp.series.cycles)
    plots.show_static(fig, dpi=80, fmt="jpeg")
'''),
    md("## Forward–backward error of every step (the reliability flag)"),
    code('''
if tr is not None:
    ax = plots.plot_fb_errors(t.fb_error_px[:-1], t.valid[:-1], t.params.get("fb_threshold_px", 0.5))
'''),
    md("## Lateral displacement from the earliest valid frame to the end (µm)"),
    code('''
if tr is not None:
    ok = np.isfinite(tr.d_um)
    fig = plots.displacement_histograms(tr.dx_um, tr.dy_um, tr.d_um, tr.seed)
    if ok.sum() >= 10:
        b = stats.bimodality(tr.d_um[ok])
        print(f"|d|: two-component mixture preferred: {b['prefers_two']} (ΔBIC = {b['delta_bic']:.1f})")
    else:
        print(f"only {ok.sum()} displacements: too few for the bimodality test (needs 10)")
    a, c = tr.d_um[ok & (tr.seed == "corner")], tr.d_um[ok & (tr.seed == "stereo")]
    if len(a) > 3 and len(c) > 3:
        ks = stats.compare_distributions(a, c)
        print(f"corner- vs stereo-seeded |d|: KS statistic {ks['ks_statistic']:.3f}, p = {ks['p_value']:.3g}")
'''),
    md("## Key numbers against the truth (checked on the demo)"),
    check_demo('''
from semlab import validation
if tr is not None and exp.truth_dir is not None:
    true = validation.true_track_positions(exp.truth_dir, t.xy[-1])
    err = np.hypot(*(t.xy - true).transpose(2, 0, 1))
    bad_valid_steps = int(sum((err[f, t.valid[f]] > 0.5).sum() for f in range(t.n_frames)))
    valid_one_back = float(t.valid[-2].mean())
    print(f"valid steps with an error above 0.5 px: {bad_valid_steps}; "
          f"{100 * valid_one_back:.0f} % of the tracks valid one frame back from the end")
''', "bad_valid_steps == 0 and valid_one_back >= 0.5"),
]

NOTEBOOKS["06_lateral_vs_depth"] = [
    md("""
# 06 · Lateral motion against depth

For the stereo points that could be tracked back, the in-plane displacement during the test
against the end-state height: do the points that rose the most also move the most? Pearson
and Spearman coefficients with bootstrap 95 % confidence intervals.
"""),
    params(),
    code(SETUP),
    code(TRACK_SETUP),
    code('''
if tr is not None:
    sel = (tr.seed == "stereo") & np.isfinite(tr.d_um) & np.isfinite(tr.z_um)
    print(f"{sel.sum()} stereo points with a height and a displacement")
    if sel.sum() >= 5:
        fig = plots.lateral_vs_depth(tr.d_um[sel], tr.z_um[sel], tr.dx_um[sel], tr.dy_um[sel])
    else:
        print("Too few stereo-seeded tracks survived to correlate lateral motion with depth.")
'''),
]

NOTEBOOKS["07_strain"] = [
    md("""
# 07 · Strain

Displacement gradients give the strain tensor. Sparse: constant-strain Delaunay triangles and
a local least-squares gradient with a stated gauge length on the tracks. Dense: a variational
displacement map from the last frame into the reference frame (started at the tracks,
sampled on a grid, plane fits over a window of grid points). Green–Lagrange strain
E = ½(FᵀF − I), principal strains and
directions, maximum shear; with heights from the stereo step, the surface strain that includes
the out-of-plane gradient (heights taken as the out-of-plane displacement of a surface that was
flat when polished). Reference: the earliest frame with enough valid tracks.
"""),
    params(),
    code(SETUP),
    code(TRACK_SETUP + '''
S = {}
if tr is not None:
    S = an.optional("strain") or {}  # said once, as the error of the strain step
if S:
    if S.get("sparse_strain", True):
        print(f"reference frame {S['ref_frame']}, gauge length {S['gauge_length_um']:.2f} µm")
    else:
        print(f"reference frame {S['ref_frame']}: no frame had enough valid tracks, so no "
              "sparse strain; the dense strain is the variational map's alone (see the "
              "step's warning)")
    measured = np.isfinite(S["E"][..., 0, 0])
    if S["dense_method"] == "variational":
        print(f"dense displacement: variational map (prior scale "
              f"{float(S['dense_prior_scale_px']):.3f} px), {np.isfinite(S['ux_um']).sum()} of "
              f"{measured.size} grid points inside the reference frame")
        print("median 1σ of the dense E (xx, yy, xy):",
              np.round(np.nanmedian(S["E_sigma"], axis=(0, 1)), 5))
    else:
        print(f"{np.isfinite(S['ux_um']).sum()} of {measured.size} grid subsets matched; "
              f"{int(S['dense_filled'].sum())} points without a match (mostly on the bands) "
              "interpolated from their neighbours before the strain window's fits")
    print(f"mean dense E (xx, yy, xy) over the {measured.sum()} of {measured.size} grid points "
          "with a strain window:",
          np.round([np.nanmean(S["E"][..., 0, 0]), np.nanmean(S["E"][..., 1, 1]),
                    np.nanmean(S["E"][..., 0, 1])], 5))
'''),
    md("## Dense strain maps (Green–Lagrange, dimensionless) and principal directions"),
    code('''
if S:
    maps = {"E_xx": S["E"][..., 0, 0], "E_yy": S["E"][..., 1, 1], "E_xy": S["E"][..., 0, 1],
            "max shear": S["max_shear"]}
    fig = plots.strain_maps(S["grid_x_px"], S["grid_y_px"], maps, exp.pixel_size_um,
                            interpolated=S["dense_filled"])
    ax = plots.principal_directions(S["grid_x_px"], S["grid_y_px"], S["e1"], S["angle_deg"],
                                    exp.pixel_size_um)
'''),
    md("""
## How well the dense strain is measured

The 1σ of each dense strain component (the variational map's posterior through the same plane
fits, with its rounding of a slip band's step): where |E| is below about 2σ the strain is not
resolved. Largest on the bands and where the frames have little texture.
"""),
    code('''
if S and "E_sigma" in S:
    fig = plots.strain_maps(S["grid_x_px"], S["grid_y_px"],
                            {f"1σ of {c}": S["E_sigma"][..., i]
                             for i, c in enumerate(("E_xx", "E_yy", "E_xy"))},
                            exp.pixel_size_um, sigma=True)
    E3 = np.stack([S["E"][..., 0, 0], S["E"][..., 1, 1], S["E"][..., 0, 1]], -1)
    measured = np.isfinite(E3) & np.isfinite(S["E_sigma"])
    resolved = (np.abs(np.where(measured, E3, 0.0)) > 2 * S["E_sigma"]) & measured
    print("grid points with a strain where |E| > 2σ (xx, yy, xy):",
          np.round(100 * resolved.sum(axis=(0, 1)) / measured.sum(axis=(0, 1)), 1), "%")
'''),
    md("## Sparse strain (tracks) and the surface strain with heights"),
    code('''
if S:
    if len(S["pts_px"]):
        print("triangles: mean E", np.round(np.nanmean(S["E_tri"], axis=0), 5).tolist())
        print("local LSQ: mean E", np.round(np.nanmean(S["E_lsq"], axis=0), 5).tolist())
    if "E_surface" in S:
        print("surface strain incl. out-of-plane gradients: mean E",
              np.round(np.nanmean(S["E_surface"], axis=(0, 1)), 5).tolist())
'''),
    md("## Strain against cycles (mean strain of each frame relative to the end state)"),
    code('''
if S and "history" in S:
    ax = plots.strain_history(S["history"], exp.series.cycles)
'''),
    md("## Key numbers against the truth (checked on the demo)"),
    check_demo('''
from semlab import validation
if S and exp.truth_dir is not None:
    GX, GY = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    g = np.column_stack([GX.ravel(), GY.ravel()])
    true = validation.true_track_positions(exp.truth_dir, g)
    u_true = (true[-1] - true[S["ref_frame"]]) * exp.pixel_size_um
    u = np.column_stack([S["ux_um"].ravel(), S["uy_um"].ravel()])
    good = np.all(np.isfinite(u), axis=1)
    err_um = np.linalg.norm(u[good] - u_true[good], axis=1)
    dense_median_um = float(np.median(err_um))
    print(f"dense grid: {good.sum()} points, displacement error median {dense_median_um * 1000:.1f} nm, "
          f"RMS {np.sqrt(np.mean(err_um ** 2)) * 1000:.1f} nm from reference frame {S['ref_frame']} "
          f"(largest true displacement {np.abs(u_true).max() * 1000:.0f} nm)")
''', "good.sum() >= 0.95 * good.size and dense_median_um < 0.004 and S['ref_frame'] <= exp.frames().__len__() - 2"),
]

NOTEBOOKS["08_validation"] = [
    md("""
# 08 · Validation against ground truth

For synthetic experiments (made by `semlab synth`, with a `truth/` folder): height errors of
the raw clicks (the reference method), the refined clicks and the automatic matches, tracking
errors per frame, and the strain against the true field. Height errors are measured after
removing the best-fit plane of the difference (the reference plane is a convention).
"""),
    params(),
    code(SETUP),
    code('''
from semlab import validation
truth = exp.truth_dir
if truth is None:
    print("No truth/ folder: validation needs a synthetic experiment (semlab synth).")
'''),
    md("## Heights"),
    code('''
rows = {}
if truth is not None and exp.stereo is not None:
    for m in (["raw", "refined"] if exp.correspondences() is not None else []) + ["auto"]:
        r = an.optional("stereo", method=m)
        if r is None:
            continue
        zt = validation.true_height_at(truth, r.pts[:, 0])
        e = validation.height_errors(r.z_um, zt, r.xyz_um[:, :2])
        rows[m] = (r, e)
        print(f"{m:>8}: {e['n']:5d} points, RMSE {e['rmse_um'] * 1000:6.1f} nm, p95 {e['p95_um'] * 1000:6.1f} nm")
    if rows:
        ax = plots.error_histograms({m: e["err_um"] for m, (r, e) in rows.items()})
'''),
    md("## Tracking"),
    code('''
tr = an.optional("tracking") if truth is not None and exp.series is not None else None
if tr is not None:
    t = tr.tracks
    true = validation.true_track_positions(truth, t.xy[-1])
    err = np.hypot(*(t.xy - true).transpose(2, 0, 1))
    for f in range(t.n_frames):
        v = t.valid[f]
        rms = np.sqrt(np.mean(err[f, v] ** 2)) if v.any() else np.nan
        print(f"frame {f}: {v.sum():4d} valid, RMS error {rms:.3f} px, "
              f"valid steps with error > 0.5 px: {(err[f, v] > 0.5).sum()}")
'''),
    md("""
## Key numbers (checked on the demo)
The demo is a low-texture (`polished`) scene: hand clicks land on band edges and sparse
particles, where a refined click reaches about 15–20 nm; the automatic matches average over
many more points.
"""),
    check_demo('''
if rows:
    rmse_nm = {m: e["rmse_um"] * 1000 for m, (r, e) in rows.items()}
    print("height RMSE (nm):", {m: round(v, 1) for m, v in rmse_nm.items()})
''', "rmse_nm['raw'] > 5 * rmse_nm['refined'] and rmse_nm['auto'] < 15 and rmse_nm['refined'] < 20"),
]


def _stable_ids(name, cells):
    """Cell ids from the notebook name and the cell's text (not random), so that
    regenerating the notebooks changes only the cells whose text changed."""
    seen = set()
    for cell in cells:
        digest = hashlib.sha1(f"{name}\n{cell.cell_type}\n{cell.source}".encode()).hexdigest()
        cid, k = digest[:8], 0
        while cid in seen:
            k += 1
            cid = f"{digest[:8]}-{k}"
        seen.add(cid)
        cell.id = cid
    return cells


def main():
    HERE.mkdir(exist_ok=True)
    for name, cells in NOTEBOOKS.items():
        nb = new_notebook(cells=_stable_ids(name, cells))
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
        nb.metadata["language_info"] = {"name": "python"}
        nbformat.write(nb, str(HERE / f"{name}.ipynb"))
        print("wrote", HERE / f"{name}.ipynb")


if __name__ == "__main__":
    main()
