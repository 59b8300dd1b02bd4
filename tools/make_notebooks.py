"""Write the numbered notebooks in notebooks/ from the cell lists below (outputs stripped).

Run ``python tools/make_notebooks.py`` after editing; the .ipynb files are what users open.
Each notebook starts with a papermill ``parameters`` cell (experiment path, out_dir, knobs)
that defaults to the demo experiment in data_samples/.
"""

from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parents[1] / "notebooks"

PARAMS = '''# parameters (papermill injects new values after this cell)
experiment = "../data_samples/demo"   # experiment folder or its experiment.toml
out_dir = None                        # folder for result files; None = do not write files
'''

SETUP = '''%matplotlib inline
import numpy as np
import matplotlib.pyplot as plt
import semlab
from semlab import experiment as sx, plots
exp = sx.load(experiment)
print(exp.summary())
'''


def md(text):
    return new_markdown_cell(text.strip("\n"))


def code(text, tags=None):
    c = new_code_cell(text.strip("\n"))
    if tags:
        c.metadata["tags"] = list(tags)
    return c


def check(text, expected):
    """A ``# NBVAL_CHECK_OUTPUT`` cell: nbval compares its printed output with ``expected``.

    These few lines of expected text are the only outputs stored in the notebooks (they are the
    test's reference values, not results).
    """
    c = new_code_cell("# NBVAL_CHECK_OUTPUT\n" + text.strip("\n"), execution_count=1)
    c.outputs = [nbformat.v4.new_output("stream", name="stdout", text=expected.rstrip("\n") + "\n")]
    return c


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
'''),
    md("## Key numbers (checked by nbval)"),
    check('''
n_views = 0 if exp.stereo is None else len(exp.stereo.view_paths)
n_frames = 0 if exp.series is None else len(exp.series.frame_paths)
print(f"views={n_views} frames={n_frames} pixel_size_um={exp.pixel_size_um:.4f}")
''', "views=2 frames=6 pixel_size_um=0.0300"),
]

NOTEBOOKS["02_correspondences"] = [
    md("""
# 02 · Picking correspondences

Click the same surface feature in every view. A click in one view proposes the match in the
others (same place shifted by the offset of the points picked so far, moved onto the epipolar
line once F is known, then refined by sub-pixel matching); press **a** or click the proposal
to accept, drag a marker to adjust, select with a right click and press **d** to delete,
**u** to undo; zoom with the toolbar. **Save** writes the experiment's correspondences CSV and
keeps a backup of the file it replaces (`correspondences.bak.csv`, `.bak1.csv`, ...).

The picker needs a live JupyterLab (ipympl). When this notebook is executed as a report, the
interactive cell only shows a still picture and the cells after it read the saved file.
"""),
    params(),
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
from semlab.widgets import picker_widget
if save_path is not None:
    box = picker_widget(exp.views(), save_path, titles=[p.name for p in exp.stereo.view_paths])
    display(box)
'''),
    md("## The saved points"),
    code('''
%matplotlib inline
corr = exp.correspondences() if exp.stereo is not None else None
if corr is None:
    print("No correspondences file yet: pick points above and press Save (or run automatic "
          "matching in 04_depth).")
else:
    fig, axes = plt.subplots(1, corr.n_views, figsize=(6 * corr.n_views, 4.5))
    for i, ax in enumerate(np.atleast_1d(axes)):
        plots.show_image(exp.views()[i], ax=ax, title=f"view {i}", points=corr.pts[:, i],
                         labels=corr.point_id)
    fig.tight_layout()
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
    fig, axes = plt.subplots(1, len(lines), figsize=(7 * len(lines), 5.2))
    for i, ax in enumerate(np.atleast_1d(axes)):
        if images[i] is not None:
            plots.show_line_families(images[i], lines[i], ax=ax, title=f"view {i}", vps=cal.vps[i])
    fig.tight_layout()
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
    params('stability_resamples = 40   # random subsets per size in the stability plot\n'),
    code(SETUP),
    code('''
from semlab import epipolar
corr = exp.correspondences() if exp.stereo is not None else None
if corr is None:
    print("No correspondences: this notebook needs [stereo] correspondences (see 02).")
else:
    x0, x1 = corr.pts[:, 0], corr.pts[:, 1]
    Fa = epipolar.fundamental_affine(x0, x1)
    axis, line = epipolar.affine_tilt_axis(Fa)
    print("affine F (clicked points) =\\n", (Fa / np.abs(Fa).max()).round(5))
    print(f"tilt axis in view 0: {axis[0]:.2f}° from x (90° = image y); epipolar lines at {line[0]:.2f}°")
    print(f"median Sampson distance: {np.median(epipolar.sampson_distance(Fa, x0, x1)):.3f} px")
    try:
        F8 = epipolar.fundamental_8point(x0, x1)
        e0, e1 = epipolar.epipoles(F8)
        print("eight-point F =\\n", (F8 / np.abs(F8).max()).round(5))
        print("epipoles (homogeneous):", e0.round(4), e1.round(4))
    except semlab.SemlabError as exc:
        F8 = None
        print("eight-point F:", exc)
'''),
    md("## Epipolar lines over both views (affine F)"),
    code('''
if corr is not None:
    views = exp.views()
    fig = plots.show_epipolar_lines(views[0], views[1], Fa, x0, x1, title=" (affine F)")
'''),
    md("""
## Stability: how F settles with the number of points

For each number of points, random subsets of the clicks are fitted and compared with F from
all of them (the paper saw F settle at about 30 points).
"""),
    code('''
if corr is not None and len(x0) >= 12:
    sizes = np.unique(np.linspace(8, len(x0), 8).round().astype(int))
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for model in ("affine", "8point"):
        try:
            st = epipolar.stability(x0, x1, sizes, n_resamples=stability_resamples, model=model,
                                    progress=False)
            plots.plot_stability(st, ax=ax, label=model)
        except semlab.SemlabError as exc:
            print(model, ":", exc)
    ax.set_title("F stability against the number of clicked points")
'''),
]


def main():
    HERE.mkdir(exist_ok=True)
    for name, cells in NOTEBOOKS.items():
        nb = new_notebook(cells=cells)
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
        nb.metadata["language_info"] = {"name": "python"}
        nbformat.write(nb, str(HERE / f"{name}.ipynb"))
        print("wrote", HERE / f"{name}.ipynb")


if __name__ == "__main__":
    main()
