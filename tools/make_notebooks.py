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
    c = new_code_cell("# NBVAL_CHECK_OUTPUT\n" + text.strip("\n"))
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
