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
import shutil
import tempfile
import sys
from pathlib import Path

from .errors import SemlabError
from .io import atomic_write_text, quiet_loggers

_TOGGLE = """
<div style="position:fixed;top:8px;right:12px;z-index:1000">
<button onclick="document.body.classList.toggle('semlab-hide-code');
 this.textContent=document.body.classList.contains('semlab-hide-code')?'show code':'hide code'">hide code</button>
</div>
<style>body.semlab-hide-code .jp-InputArea, body.semlab-hide-code .input_area,
body.semlab-hide-code .jp-Cell-inputWrapper {display:none}</style>
"""


#: The analysis steps each numbered notebook shows (``--only`` runs just these).
NOTEBOOK_STEPS = {"03": ("stereo",), "04": ("stereo", "heightmap"), "05": ("stereo", "tracking"),
                  "06": ("stereo", "tracking"), "07": ("stereo", "tracking", "strain"),
                  "08": ("stereo", "tracking")}


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


#: The page style shared by the HTML pages of a report (written beside them).
REPORT_CSS = "report.css"
#: Result files a run writes (the README's results contract) besides the notebook reports.
RESULT_FILES = ("experiment_summary.txt", "points3d.csv", "calibration.json", "tracks.csv",
                "displacements.csv", "strain.npz", "heightmap.tif", "heightmap_sigma.tif",
                "heightmap.x3p", "heightmap.gsf", "heightmap.ply", "surface_parameters.csv",
                "bands.csv", "drift.csv", "index.html", REPORT_CSS)
#: Where a failed run leaves its partial report (executed notebooks and HTML, no results).
FAILED_DIR = "failed_run"
#: The analysis step cache (semlab.analysis), kept between runs into the same folder.
CACHE_DIR = ".semlab"
_STAGING_PREFIX = ".semlab-run-"
_SYSTEM_DIRS = (Path("/proc"), Path("/sys"), Path("/dev"))
#: Kernel options: no "[IPKernelApp] WARNING | Kernel is running over TCP..." (nor other
#: kernel log lines) in the terminal; a failing cell's error is in the notebook and the message.
#: The kernel's tornado loggers too: a shutdown race of ipykernel's control channel (a flush
#: after its socket closed, "ZMQError: Socket operation on non-socket") otherwise prints a
#: traceback from the kernel process after a failing notebook (seen once in CI, 2026-12-03).
KERNEL_ARGUMENTS = ["--IPKernelApp.log_level=CRITICAL",
                    "--IPKernelApp.exec_lines=__import__('logging').getLogger('tornado')"
                    ".setLevel(50)"]
#: Loggers of the notebook machinery silenced during a run (they log kernel shutdown noise).
_QUIET_LOGGERS = ("tornado", "traitlets", "papermill", "nbclient", "asyncio")


def _inside(path, folder):
    return path == folder or folder in path.parents


def _owned(path):
    """Is ``path`` (an entry of an output folder) something ``semlab run`` writes?"""
    name = path.name
    return (name in RESULT_FILES or name == FAILED_DIR or name.startswith(_STAGING_PREFIX)
            or (re.match(r"^\d\d_.*\.(ipynb|html)$", name) is not None))


def _has_content(out):
    """Entries of ``out`` other than an earlier failed run's partial report."""
    return [p for p in out.iterdir() if p.name not in (FAILED_DIR, CACHE_DIR)
            and not p.name.startswith(_STAGING_PREFIX)]


def check_out_dir(out, experiment_root=None, force=False):
    """Refuse an output folder that cannot or must not receive results, before any work.

    Parameters
    ----------
    out : str or Path
        The ``--out`` folder.
    experiment_root : str or Path, optional
        The experiment folder, which semlab only reads.
    force : bool
        Allow a non-empty folder (its semlab result files are replaced, see :func:`run`).

    Returns
    -------
    Path
        ``out`` resolved (symlinks followed).

    Raises
    ------
    SemlabError
        ``out`` is a file or lies under one, is inside (or equal to) the experiment folder or
        the package's ``notebooks/``, is a system folder (``/proc``, ``/sys``, ``/dev``),
        cannot be written, or is not empty without ``force``. One line naming the folder and
        the fix.
    """
    given = Path(out).expanduser()
    res = given.resolve()
    for sys_dir in _SYSTEM_DIRS:
        if _inside(res, sys_dir):
            raise SemlabError(f"--out {given}: {sys_dir} is a system folder, not a place for "
                              "results; give a folder of your own, e.g. --out ~/semlab-reports/run1")
    if experiment_root is not None:
        root = Path(experiment_root).resolve()
        if _inside(res, root):
            raise SemlabError(f"--out {given} is inside the experiment folder {root}, which semlab "
                              f"only reads; write the results beside it, e.g. --out "
                              f"{root.parent / (root.name + '-report')}")
    env = os.environ.get("SEMLAB_NOTEBOOKS")
    nb_dir = (Path(env) if env else Path(__file__).resolve().parents[1] / "notebooks").resolve()
    if _inside(res, nb_dir):
        raise SemlabError(f"--out {given} is inside semlab's notebooks folder {nb_dir}; write the "
                          "results elsewhere, e.g. --out reports/run1")
    if res.exists() and not res.is_dir():
        raise SemlabError(f"--out {given} is a file; give a folder (new, or empty)")
    parent = res
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise SemlabError(f"--out {given}: {parent} is a file, so no folder can be made there; "
                          "give another --out")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise SemlabError(f"--out {given}: cannot write in {parent} (permission denied or a "
                          "read-only file system); give a folder you can write to")
    if res.exists() and _has_content(res) and not force:
        raise SemlabError(f"--out {given} is not empty; choose a new folder or pass --force to "
                          "replace the semlab results in it (other files are kept)")
    return res


def prepare_out_dir(out, force=False):
    """Create ``out`` after :func:`check_out_dir`; return it (resolved)."""
    out = check_out_dir(out, force=force)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SemlabError(f"--out {out}: cannot create the folder ({exc.strerror}); give a "
                          "folder you can write to") from None
    return out


def to_html(nb_path, html_path):
    """Convert an executed notebook to an HTML page with a show/hide-code button."""
    import nbformat
    from nbconvert import HTMLExporter

    nb = nbformat.read(str(nb_path), as_version=4)
    body, _ = HTMLExporter().from_notebook_node(nb)
    body = re.sub(r"(<body[^>]*>)", lambda m: m.group(1) + _TOGGLE, body, count=1)
    body = _shared_css(body, Path(html_path).parent / REPORT_CSS)
    atomic_write_text(html_path, body)
    return html_path


def _shared_css(page, css_path, min_chars=2000):
    """Move the large ``<style>`` blocks of the page's head into ``css_path`` and link it.

    nbconvert's lab template inlines ~260 kB of JupyterLab CSS into every page; nine pages of
    a report carried 2.4 MB of the same style. The file is written once per content.
    """
    head_end = page.find("</head>")
    if head_end < 0:
        return page
    head, rest = page[:head_end], page[head_end:]
    blocks = [m for m in re.finditer(r"<style[^>]*>(.*?)</style>", head, flags=re.S)
              if len(m.group(1)) >= min_chars]
    if not blocks:
        return page
    css = "\n".join(m.group(1) for m in blocks)
    if not (css_path.exists() and css_path.read_text(encoding="utf-8") == css):
        atomic_write_text(css_path, css)
    for m in reversed(blocks):
        head = head[:m.start()] + head[m.end():]
    link = f'<link rel="stylesheet" href="{css_path.name}">'
    return head.replace("<head>", "<head>\n" + link, 1) + rest


def _write_index(out, entries, exp, status=None):
    steps = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>"
                    for k, v in (status or {}).items())
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
<h2>Analysis steps</h2><table>{steps}</table>
<h2>Notebooks</h2><table>{rows}</table><h2>Result files</h2><ul>{flist}</ul></body></html>"""
    atomic_write_text(out / "index.html", page)


def _remove(path):
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


def _show_final_paths(nb_path, stage, final):
    """In an executed notebook, name the folder its files end up in, not the staging folder."""
    text = Path(nb_path).read_text(encoding="utf-8")
    if str(stage) in text:
        atomic_write_text(nb_path, text.replace(str(stage), str(final)))


def _publish(stage, out, clear_owned):
    """Move the staged run into ``out``: each file by ``os.replace`` (atomic per file)."""
    for p in list(out.iterdir()):
        if p == stage:
            continue
        if p.name == FAILED_DIR or p.name.startswith(_STAGING_PREFIX) or (clear_owned and _owned(p)):
            _remove(p)
    for p in sorted(stage.iterdir()):
        dest = out / p.name
        if dest.is_dir() and not dest.is_symlink():
            shutil.rmtree(dest)
        os.replace(p, dest)
    stage.rmdir()


def _keep_failed(stage, out):
    """A failed run: drop its result files, keep its reports as ``out/failed_run/``."""
    for p in list(stage.iterdir()):
        if not (re.match(r"^\d\d_.*\.(ipynb|html)$", p.name) or p.name == REPORT_CSS):
            _remove(p)
    failed = out / FAILED_DIR
    _remove(failed)
    os.replace(stage, failed)
    return failed


def step_warning_lines(warnings_by_step):
    """``semlab: warning (steps): message`` lines, each message once with every step that
    said it (the refined-clicks and the stereo step repeat the same clicks' warning)."""
    steps_of = {}
    for step, said in warnings_by_step.items():
        for msg in said:
            steps_of.setdefault(msg, []).append(step)
    return [f"semlab: warning ({', '.join(steps)}): {msg}" for msg, steps in steps_of.items()]


def run(experiment, out, force=False, only=None, progress=True, kernel_name=None, config=None):
    """Run the analysis of an experiment, then execute the notebooks on its results.

    The analysis (:class:`semlab.analysis.Analysis`) computes every step once and writes the
    result files into ``out``; the notebooks then load the cached results and show them.

    The run is all or nothing: the notebooks write into a hidden staging folder inside
    ``out``; only when every notebook has finished are the files moved into ``out`` (each by
    an atomic rename). A failing run changes nothing in ``out``: its result files are
    deleted and its executed notebooks (with the error) are kept in ``out/failed_run/``.

    Parameters
    ----------
    experiment : str or Path
        Experiment folder or its ``experiment.toml`` (only read).
    out : str or Path
        Output folder: created; must be empty unless ``force``. It must not be inside the
        experiment folder or semlab's ``notebooks/`` (see :func:`check_out_dir`).
    force : bool
        Replace the results in a non-empty ``out``: on success the semlab files already
        there (``NN_*.ipynb``/``.html``, ``index.html`` and the result files of the contract)
        are removed and the new ones moved in; files semlab does not write are kept. With
        ``only``, the results of the other notebooks are kept (and available to the re-run).
    only : list of str, optional
        Notebook numbers to run (e.g. ``["04", "05"]``).
    progress : bool
        Progress bars over the analysis steps and the notebooks.
    config : semlab.AnalysisConfig or dict, optional
        Settings of the analysis (default: the defaults), passed to the notebooks too.

    Returns
    -------
    Path of the output folder.

    Raises
    ------
    SemlabError
        Invalid experiment or ``out`` (checked before any work), a failing notebook (its
        name and the failing cell's error are in the message), or a failed analysis step
        (named, with its error, after the report of everything else has been written).
    """
    import papermill as pm
    from tqdm.auto import tqdm

    from .analysis import Analysis
    from .experiment import find_experiment_root, load

    check_out_dir(out, find_experiment_root(experiment), force)
    exp = load(experiment)
    nbs = list_notebooks(only)
    out = prepare_out_dir(out, force)
    try:
        stage = Path(tempfile.mkdtemp(prefix=_STAGING_PREFIX, dir=out))
    except OSError as exc:
        raise SemlabError(f"--out {out}: cannot write there ({exc.strerror}); give a folder you "
                          "can write to") from None
    try:
        if only:  # a partial re-run reads the other notebooks' results (points3d.csv, ...)
            for name in RESULT_FILES:
                if (out / name).is_file():
                    shutil.copy2(out / name, stage / name)
        atomic_write_text(stage / "experiment_summary.txt", exp.summary() + "\n")
        # the analysis computes every step once (or loads it from the cache in out/.semlab,
        # which outlives the run) and writes its result files into the staging folder
        cache_dir = out / CACHE_DIR / "cache"
        analysis = Analysis(exp, stage, config=config, progress=progress, cache_dir=cache_dir)
        wanted = {s for nb in nbs for s in NOTEBOOK_STEPS.get(nb.name[:2], ())}
        status = analysis.run([s for s in analysis.applicable_steps() if s in wanted])
        for line in step_warning_lines(analysis.warnings):
            print(line, file=sys.stderr)
        params = {"experiment": str(exp.root), "out_dir": str(stage),
                  "cache_dir": str(cache_dir), "config": analysis.config.as_dict()}
        entries = []
        for nb in tqdm(nbs, desc="notebooks", disable=not progress):
            dest = stage / nb.name
            try:
                with quiet_loggers(*_QUIET_LOGGERS):
                    pm.execute_notebook(str(nb), str(dest), parameters=params,
                                        cwd=str(nb.parent), kernel_name=kernel_name,
                                        progress_bar=False, extra_arguments=KERNEL_ARGUMENTS)
            except Exception as exc:  # a failing cell, or a kernel that died or never started
                if dest.is_file():
                    _show_final_paths(dest, stage, out / FAILED_DIR)
                    to_html(dest, dest.with_suffix(".html"))
                failed = _keep_failed(stage, out)
                if isinstance(exc, pm.PapermillExecutionError):
                    what = f"failed in cell {exc.exec_count}: {exc.ename}: {exc.evalue}"
                else:
                    what = f"could not be run ({type(exc).__name__}: {exc})"
                raise SemlabError(
                    f"notebook {nb.name} {what} (no result file was written; nothing else in "
                    f"{out} changed; partial report: {failed / dest.with_suffix('.html').name})"
                ) from None
            _show_final_paths(dest, stage, out)
            to_html(dest, dest.with_suffix(".html"))
            entries.append((nb.stem, dest.with_suffix(".html").name, "ok"))
        _write_index(stage, entries, exp, status)
        _publish(stage, out, clear_owned=force and not only)
    except BaseException:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)
        raise
    failed = {k: v for k, v in status.items() if v != "ok"}
    if failed:
        raise SemlabError("; ".join(failed.values()) + f" (the report in {out} shows the rest)")
    return out
