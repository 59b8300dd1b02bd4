"""``semlab run``: execute the numbered notebooks on an experiment and keep them as reports.

Each notebook in ``notebooks/`` (``NN_name.ipynb``) has a papermill ``parameters`` cell with at
least ``experiment`` (path of the experiment folder) and ``out_dir`` (where result files go).
:func:`run` injects both, executes the notebooks in order with papermill, writes the executed
notebooks, one HTML page per notebook (code cells hideable) and an ``index.html``; result
files (``points3d.csv``, ``calibration.json``, ``tracks.csv``, ...) are written by the
notebooks into the same folder through semlab's functions.
"""

from __future__ import annotations

import html
import os
import re
from pathlib import Path

from .errors import SemlabError

_TOGGLE = """
<div style="position:fixed;top:8px;right:12px;z-index:1000">
<button onclick="document.body.classList.toggle('semlab-hide-code');
 this.textContent=document.body.classList.contains('semlab-hide-code')?'show code':'hide code'">hide code</button>
</div>
<style>body.semlab-hide-code .jp-InputArea, body.semlab-hide-code .input_area,
body.semlab-hide-code .jp-Cell-inputWrapper {display:none}</style>
"""


def notebooks_dir():
    """Folder of the numbered notebooks (``SEMLAB_NOTEBOOKS`` overrides the repository's)."""
    env = os.environ.get("SEMLAB_NOTEBOOKS")
    d = Path(env) if env else Path(__file__).resolve().parents[1] / "notebooks"
    if not d.is_dir():
        raise SemlabError(f"notebooks folder not found at {d}; run semlab from a clone of the "
                          "repository (pip install -e .) or set SEMLAB_NOTEBOOKS")
    return d


def list_notebooks(only=None):
    """The numbered notebooks, in order, optionally only those whose number is in ``only``."""
    nbs = sorted(p for p in notebooks_dir().glob("[0-9][0-9]_*.ipynb"))
    if only:
        wanted = {o.zfill(2) for o in only}
        unknown = wanted - {p.name[:2] for p in nbs}
        if unknown:
            raise SemlabError(f"--only {','.join(sorted(unknown))}: no such notebook; have "
                              f"{', '.join(p.name[:2] for p in nbs)}")
        nbs = [p for p in nbs if p.name[:2] in wanted]
    return nbs


def prepare_out_dir(out, force=False):
    """Create ``out``; refuse a non-empty folder unless ``force`` (never overwrite silently)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise SemlabError(f"--out {out} is a file; give a folder")
    if out.exists() and any(out.iterdir()) and not force:
        raise SemlabError(f"--out {out} is not empty; choose a new folder or pass --force to "
                          "write into it (files of the same name are replaced)")
    out.mkdir(parents=True, exist_ok=True)
    return out


def to_html(nb_path, html_path):
    """Convert an executed notebook to an HTML page with a show/hide-code button."""
    import nbformat
    from nbconvert import HTMLExporter

    nb = nbformat.read(str(nb_path), as_version=4)
    body, _ = HTMLExporter().from_notebook_node(nb)
    body = re.sub(r"(<body[^>]*>)", lambda m: m.group(1) + _TOGGLE, body, count=1)
    Path(html_path).write_text(body, encoding="utf-8")
    return html_path


def _write_index(out, entries, exp):
    rows = "\n".join(
        f"<tr><td><a href='{html.escape(h)}'>{html.escape(n)}</a></td><td>{html.escape(s)}</td></tr>"
        for n, h, s in entries)
    files = sorted(p.name for p in out.iterdir() if p.is_file() and p.suffix in
                   (".csv", ".json", ".npz", ".txt"))
    flist = "".join(f"<li><a href='{html.escape(f)}'>{html.escape(f)}</a></li>" for f in files)
    page = f"""<!doctype html><html><head><meta charset='utf-8'><title>semlab: {html.escape(exp.name)}</title>
<style>body{{font-family:sans-serif;max-width:900px;margin:2em auto}} td{{padding:4px 12px}}</style>
</head><body><h1>semlab report: {html.escape(exp.name)}</h1>
<pre>{html.escape(exp.summary())}</pre>
<h2>Notebooks</h2><table>{rows}</table><h2>Result files</h2><ul>{flist}</ul></body></html>"""
    (out / "index.html").write_text(page, encoding="utf-8")


def run(experiment, out, force=False, only=None, progress=True, kernel_name=None):
    """Execute the notebooks on an experiment and write reports and result files to ``out``.

    Parameters
    ----------
    experiment : str or Path
        Experiment folder or its ``experiment.toml``.
    out : str or Path
        Output folder: created; must be empty unless ``force``.
    force : bool
    only : list of str, optional
        Notebook numbers to run (e.g. ``["04", "05"]``).
    progress : bool
        A progress bar over notebooks.

    Returns
    -------
    Path of the output folder.

    Raises
    ------
    SemlabError
        Invalid experiment, non-empty ``out``, or a failing notebook (its name and the failing
        cell's error are in the message; the partly executed notebook is kept in ``out``).
    """
    import papermill as pm
    from tqdm.auto import tqdm

    from .experiment import load

    exp = load(experiment)
    nbs = list_notebooks(only)
    out = prepare_out_dir(out, force).resolve()
    (out / "experiment_summary.txt").write_text(exp.summary() + "\n", encoding="utf-8")
    params = {"experiment": str(exp.root), "out_dir": str(out)}
    entries = []
    for nb in tqdm(nbs, desc="notebooks", disable=not progress):
        dest = out / nb.name
        try:
            pm.execute_notebook(str(nb), str(dest), parameters=params, cwd=str(nb.parent),
                                kernel_name=kernel_name, progress_bar=False)
        except pm.PapermillExecutionError as exc:
            to_html(dest, dest.with_suffix(".html"))
            raise SemlabError(f"notebook {nb.name} failed in cell {exc.exec_count}: "
                              f"{exc.ename}: {exc.evalue} (partial report: {dest})") from None
        to_html(dest, dest.with_suffix(".html"))
        entries.append((nb.stem, dest.with_suffix(".html").name, "ok"))
    _write_index(out, entries, exp)
    return out
