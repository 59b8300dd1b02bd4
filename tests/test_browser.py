"""The correspondence picker of notebook 02 in a real browser.

JupyterLab (from this venv) runs on loopback in a temporary folder holding a copy of
``notebooks/02_correspondences.ipynb`` and a small synthetic stereo experiment; headless
Chromium (Debian's ``/usr/bin/chromium``, driven by Playwright) opens the notebook, runs all
cells from the Run menu, and on the ipympl canvas:

- clicks a point in view 0: both magnifiers then show the image around it;
- clicks its true match in view 1: the panel counts 1 unsaved change;
- presses on the new marker and wobbles the mouse by 1 px: the point does not move;
- clicks a button (Drop, which has nothing to drop), then presses ``u`` and ``a``: the keys
  reach the picker (undo, accept), not JupyterLab (no cell is inserted);
- presses Save: the CSV on disk has one more row at the clicked pixels, its backup holds the
  old rows, the file keeps its permissions (``-rw-rw-r--`` set before), the count says
  "all saved" and the autosave side file is gone.

Screenshots of each step are written to the test's temporary folder (CI keeps it as an
artifact of the run); their paths are printed.

Page coordinates of image pixels come from the canvas bounding box and the same figure
layout drawn here with Agg; the ipympl footer, which shows the data coordinates under the
mouse, confirms (and if needed corrects) each position before the click.

Skipped when Chromium or the playwright package is missing (``scripts/_setup_browser.sh``
installs them). Never downloads a browser.
"""

import csv
import json
import os
import re
import secrets
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time
import urllib.error
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.browser

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "02_correspondences.ipynb"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run"]
TOTAL_BUDGET_S = 140.0  # everything but the server shutdown (bounded separately)
CANVAS_GRACE_S = 15.0  # wait for the canvas to be drawn once every cell has run


def _chromium():
    for cand in ("/usr/bin/chromium", shutil.which("chromium")):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return cand
    return None


class _Deadline:
    """One time budget shared by every wait of the test, so that it cannot hang."""

    def __init__(self, seconds):
        self.end = time.monotonic() + seconds

    def left(self, cap_s):
        left = self.end - time.monotonic()
        if left <= 0:
            raise AssertionError(f"the browser test ran out of its {TOTAL_BUDGET_S:.0f} s budget")
        return min(cap_s, left)

    def ms(self, cap_s):
        return self.left(cap_s) * 1000.0


def _free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _children(pid):
    """{child pid: start time} of the direct children of ``pid`` (read from /proc)."""
    out = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if len(fields) > 19 and int(fields[1]) == pid:
            out[int(stat.parent.name)] = fields[19]
    return out


def _start_time(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _http(url, method="GET", timeout=3.0):
    req = urllib.request.Request(url, method=method, data=b"" if method == "POST" else None)
    with urllib.request.urlopen(req, timeout=timeout) as resp:
        return resp.status


@contextmanager
def _jupyter_lab(root_dir, work, deadline):
    """Run JupyterLab on 127.0.0.1 serving ``root_dir``; yield (base_url, token, log_path).

    Config, data, runtime, settings and IPython folders are private to ``work``, so that no
    user setting or kernel spec of this machine is used. The server and its kernels are shut
    down on exit (REST shutdown, then terminate/kill of the processes started here).
    """
    port, token = _free_port(), secrets.token_hex(16)
    env = {k: v for k, v in os.environ.items()
           if k not in ("MPLBACKEND", "JUPYTER_PATH", "JUPYTER_CONFIG_PATH", "PYTHONSTARTUP")}
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    for var in ("JUPYTER_CONFIG_DIR", "JUPYTER_DATA_DIR", "JUPYTER_RUNTIME_DIR", "IPYTHONDIR"):
        env[var] = str(work / var.lower())
    settings = work / "lab_settings"
    (settings / "@jupyterlab" / "apputils-extension").mkdir(parents=True)
    # no "Would you like to get notified about official Jupyter news?" toast
    (settings / "@jupyterlab" / "apputils-extension" / "notification.jupyterlab-settings"
     ).write_text(json.dumps({"fetchNews": "false", "checkForUpdates": False}))
    cmd = [sys.executable, "-m", "jupyterlab", "--no-browser", "--ip=127.0.0.1",
           f"--port={port}", "--ServerApp.port_retries=0", f"--IdentityProvider.token={token}",
           f"--ServerApp.root_dir={root_dir}", "--allow-root",
           "--ServerApp.terminals_enabled=False", "--LabApp.extension_manager=readonly",
           "--LabApp.news_url=None",
           "--LabApp.check_for_updates_class=jupyterlab.NeverCheckForUpdate",
           f"--LabApp.user_settings_dir={settings}",
           f"--LabApp.workspaces_dir={work / 'lab_workspaces'}"]
    log_path = work / "jupyter_server.log"
    base = f"http://127.0.0.1:{port}"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=env, cwd=root_dir)
        t_up = time.monotonic() + deadline.left(60.0)
        try:
            while True:
                if proc.poll() is not None:
                    tail = log_path.read_text()[-3000:]
                    raise AssertionError(f"JupyterLab exited with code {proc.returncode} before "
                                         f"serving; see {log_path}:\n{tail}")
                try:
                    if _http(f"{base}/api/status?token={token}", timeout=2.0) == 200:
                        break
                except (urllib.error.URLError, OSError):
                    pass
                if time.monotonic() > t_up:
                    raise AssertionError(f"JupyterLab did not answer within 60 s; see {log_path}")
                deadline.left(60.0)
                time.sleep(0.3)
            yield base, token, log_path
        finally:
            kernels = _children(proc.pid)
            try:
                _http(f"{base}/api/shutdown?token={token}", method="POST", timeout=5.0)
            except (urllib.error.URLError, OSError):
                pass
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(timeout=5)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=5)
            # the kernels run in sessions of their own: end any the shutdown left, by id
            # (and start time, so that a reused pid is never hit)
            t_end = time.monotonic() + 5.0
            for pid, started in kernels.items():
                while time.monotonic() < t_end and _start_time(pid) == started:
                    time.sleep(0.1)
                if _start_time(pid) == started:
                    try:
                        os.kill(pid, signal.SIGKILL)
                    except (ProcessLookupError, PermissionError):
                        pass


def _make_workspace(tmp_path):
    """A served folder with the synthetic experiment and the parametrised notebook."""
    from semlab.synth import make_experiment

    served = tmp_path / "served"
    exp = served / "exp"
    make_experiment(exp, seed=3, size=(128, 160), n_frames=0, n_clicks=5, progress=False)
    nb = json.loads(NOTEBOOK.read_text(encoding="utf-8"))
    n_param = 0
    for cell in nb["cells"]:
        if cell["cell_type"] == "code":
            cell["outputs"], cell["execution_count"] = [], None
        if "parameters" in cell.get("metadata", {}).get("tags", []):
            # keep every default of the cell (config, cache_dir, ...), override these
            src = "".join(cell["source"]) if isinstance(cell["source"], list) else cell["source"]
            cell["source"] = (src + f"\nexperiment = {str(exp)!r}\nout_dir = None\n"
                              f"cache_dir = {str(tmp_path / 'cache')!r}\nreview_auto = False\n")
            n_param += 1
    assert n_param == 1, f"{NOTEBOOK.name} must have one cell tagged 'parameters'"
    (served / NOTEBOOK.name).write_text(json.dumps(nb, indent=1), encoding="utf-8")
    return served, exp


def _read_rows(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def _choose_target(exp, old_rows, margin_px=14, min_gap_px=18):
    """A true correspondence (view-0 and view-1 pixels) well inside both images and away
    from every point already picked, so that a click there adds a new point."""
    from semlab.synth import read_truth_points

    truth = read_truth_points(exp)
    p0 = np.column_stack([truth["v0_x_px"], truth["v0_y_px"]])
    p1 = np.column_stack([truth["v1_x_px"], truth["v1_y_px"]])
    old = np.array([[float(v) for v in r[1:5]] for r in old_rows])
    h, w = np.load(exp / "truth" / "height_view0.npy").shape
    ok = np.ones(len(p0), bool)
    for p, o in ((p0, old[:, 0:2]), (p1, old[:, 2:4])):
        ok &= (p[:, 0] > margin_px) & (p[:, 0] < w - 1 - margin_px)
        ok &= (p[:, 1] > margin_px) & (p[:, 1] < h - 1 - margin_px)
        ok &= np.min(np.linalg.norm(p[:, None] - o[None], axis=2), axis=1) > min_gap_px
    assert ok.any(), "no truth point far enough from the clicked ones: change the seed"
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    i = np.flatnonzero(ok)[np.argmin(np.linalg.norm(p0[ok] - centre, axis=1))]
    return p0[i], p1[i]


def _layout(exp, box):
    """Where the image pixels of each view are on the canvas.

    Returns ``frac(view, (x, y) px) -> (fraction from the left, fraction from the top)`` of
    the canvas box, ``scale``: page px per image px of each view, and ``mags``: the
    magnifier boxes ``(left, top, right, bottom)`` as fractions of the canvas. Draws the picker figure with Agg at the canvas aspect ratio: the axes of the views are
    placed by subplot fractions and aspect-equal images, so the fractions do not depend on
    the dpi.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from semlab import experiment as sx
    from semlab.widgets import CorrespondencePicker, PickerFigure

    views = sx.load(exp).views()
    fig = Figure(figsize=(box["width"] / 100.0, box["height"] / 100.0), dpi=100)
    FigureCanvasAgg(fig)
    view_fig = PickerFigure(CorrespondencePicker(views), fig)
    fig.canvas.draw()
    wpx, hpx = fig.bbox.width, fig.bbox.height

    def frac(view, xy):
        dx, dy = view_fig.axes[view].transData.transform(np.asarray(xy, float))
        return dx / wpx, 1.0 - dy / hpx

    scale = [abs(ax.transData.transform([1.0, 0.0])[0] - ax.transData.transform([0.0, 0.0])[0])
             / wpx * box["width"] for ax in view_fig.axes]  # page px per image px
    mags = []
    for ax in view_fig.mag_axes:   # (left, top, right, bottom) fractions of the canvas
        x0, y0, x1, y1 = ax.get_window_extent().extents
        mags.append((x0 / wpx, 1.0 - y1 / hpx, x1 / wpx, 1.0 - y0 / hpx))
    return frac, scale, mags


_FOOTER = re.compile(r"\(x, y\) = \(\s*(-?[0-9.]+),\s*(-?[0-9.]+)\)")


def _footer_xy(footer, deadline, want_none=False):
    """Poll the ipympl footer (data coordinates under the mouse) for up to 5 s.

    Returns the (x, y) shown once the same value is read twice 0.3 s apart (the kernel may
    still be answering the motion events of the way there), or, with ``want_none``, None
    once it shows no coordinates; the last text seen when neither happened.
    """
    t_end = time.monotonic() + deadline.left(5.0)
    shown, prev = "", None
    while True:
        shown = footer.inner_text(timeout=deadline.ms(5.0))
        m = _FOOTER.search(shown)
        if want_none and m is None:
            return None
        if m and not want_none:
            xy = (m.group(1), m.group(2))
            if xy == prev:
                return np.array([float(v) for v in xy])
            prev = xy
        if time.monotonic() >= t_end:
            return shown
        time.sleep(0.3)


def _aim(page, frac, scale, box, view, xy, deadline):
    """Move the mouse onto image pixel ``xy`` of ``view``; returns the page position.

    The computed position is checked against the data coordinates ipympl shows in its
    footer, and corrected when they differ by more than half a pixel (but less than 3).
    The mouse first goes to a blank part of the figure, where the footer shows none, so
    that the coordinates read are those of the new position.
    """
    xy = np.asarray(xy, float)
    fx, fy = frac(view, xy)
    px, py = box["x"] + fx * box["width"], box["y"] + fy * box["height"]
    footer = page.locator(".jupyter-matplotlib-footer").first
    for _ in range(3):
        page.mouse.move(box["x"] + 0.5 * box["width"], box["y"] + 0.02 * box["height"])
        if _footer_xy(footer, deadline, want_none=True) is not None:
            return px, py  # the footer does not follow the mouse: trust the layout
        page.mouse.move(px, py, steps=3)
        seen = _footer_xy(footer, deadline)
        if isinstance(seen, str):
            raise AssertionError(f"ipympl shows no data coordinates ({seen!r}) with the mouse "
                                 f"at the computed position of pixel {tuple(xy)} of view "
                                 f"{view}: the picker figure's layout is not the one drawn "
                                 f"by _layout")
        err = xy - seen
        if np.any(np.abs(err) >= 3.0):
            raise AssertionError(
                f"the mouse at the computed position of pixel {tuple(xy)} of view {view} is "
                f"on pixel {tuple(seen)}: the picker figure's layout is not the one drawn "
                f"by _layout")
        if np.all(np.abs(err) <= 0.5):
            break
        px, py = px + err[0] * scale[view], py + err[1] * scale[view]
    return px, py


def _table_cells(page):
    """The cells of the rows of the picker's table widget (header left out)."""
    tab = page.locator(".semlab-picker-table table").last
    rows = tab.locator("tr").all_inner_texts() if tab.count() else []
    return [[c.strip() for c in r.split("\t")] for r in rows[1:]]


def _table_rows(page):
    """(point_id, status) of the rows of the picker's table widget."""
    return [(cells[0], cells[-1]) for cells in _table_cells(page)]


def _wait_table(page, deadline, what, pred):
    t_end = time.monotonic() + deadline.left(30.0)
    rows = None
    while time.monotonic() < t_end:
        rows = _table_rows(page)
        if pred(rows):
            return rows
        page.wait_for_timeout(200)
    raise AssertionError(f"picker table never showed {what}; last rows: {rows}")


def _run_all_and_wait(page, deadline):
    """Run > Run All Cells, then wait until every code cell ran and the canvas is drawn."""
    page.locator("#jp-MainMenu .lm-MenuBar-item", has_text="Run").first.click(
        timeout=deadline.ms(20.0))
    page.get_by_role("menuitem", name="Run All Cells", exact=True).click(
        timeout=deadline.ms(20.0))
    t_end = time.monotonic() + deadline.left(100.0)
    state = {"prompts": None, "canvas": None}
    while time.monotonic() < t_end:
        state = page.evaluate("""() => {
            const errs = [...document.querySelectorAll(
                '.jp-OutputArea-output[data-mime-type="application/vnd.jupyter.error"]')];
            const prompts = [...document.querySelectorAll('.jp-CodeCell .jp-InputPrompt')]
                .map(p => p.textContent.trim());
            const c = document.querySelector('.jupyter-matplotlib-canvas-div canvas');
            return {errors: errs.map(e => e.innerText.slice(-1500)), prompts: prompts,
                    canvas: c ? [c.width, c.height] : null};
        }""")
        if state["errors"]:
            raise AssertionError("a notebook cell failed:\n" + "\n".join(state["errors"]))
        done = state["prompts"] and all(re.fullmatch(r"\[\d+\]:", p) for p in state["prompts"])
        if done and state["canvas"] and min(state["canvas"]) > 0:
            return
        if done:  # every cell ran: the canvas gets its size within seconds, or never
            t_end = min(t_end, time.monotonic() + deadline.left(CANVAS_GRACE_S))
        page.wait_for_timeout(300)
    raise AssertionError(f"Run All Cells did not finish with a drawn picker canvas in time "
                         f"(cell prompts {state['prompts']}, canvas size {state['canvas']}: "
                         f"a canvas of size 0 means the figure was closed after it was shown)")


def _magnifier_std(page, mags):
    """Grey-level spread of the canvas pixels inside each magnifier box (0 when blank)."""
    return page.evaluate("""(mags) => {
        const c = document.querySelector('.jupyter-matplotlib-canvas-div canvas');
        const ctx = c.getContext('2d');
        return mags.map(([l, t, r, b]) => {
            const x = Math.round(l * c.width) + 2, y = Math.round(t * c.height) + 2;
            const w = Math.max(1, Math.round((r - l) * c.width) - 4);
            const h = Math.max(1, Math.round((b - t) * c.height) - 4);
            const d = ctx.getImageData(x, y, w, h).data;
            let s = 0, s2 = 0, n = 0;
            for (let i = 0; i < d.length; i += 4) { const g = d[i]; s += g; s2 += g * g; n++; }
            const m = s / n;
            return Math.sqrt(Math.max(0, s2 / n - m * m));
        });
    }""", [list(m) for m in mags])


def _wait_for(page, deadline, what, fn, cap_s=20.0):
    t_end = time.monotonic() + deadline.left(cap_s)
    last = None
    while time.monotonic() < t_end:
        last = fn()
        if last is not None and last is not False:
            return last
        page.wait_for_timeout(200)
    raise AssertionError(f"{what} did not happen in {cap_s:.0f} s; last seen: {last!r}")


def _unsaved_text(page):
    loc = page.locator(".semlab-unsaved")
    return loc.first.inner_text() if loc.count() else ""


class _Shots:
    """Screenshots of every step, in the test's temporary folder (printed at the end)."""

    def __init__(self, page, folder):
        self.page, self.folder, self.paths = page, folder, []

    def __call__(self, name):
        path = self.folder / f"browser_{len(self.paths):02d}_{name}.png"
        try:
            self.page.screenshot(path=str(path), timeout=10_000)
            self.paths.append(path)
        except Exception as err:  # the page may be gone; the test says why it failed
            print(f"no screenshot {path.name}: {err}")


def _drive(page, base, token, exp, n_old, target, deadline, shots):
    page.goto(f"{base}/lab/tree/02_correspondences.ipynb?token={token}",
              timeout=deadline.ms(60.0))
    page.wait_for_selector(".jp-Notebook .jp-CodeCell", timeout=deadline.ms(60.0))
    # the kernel must be up before Run All (else the run waits in a queue we cannot see)
    page.wait_for_function(
        "() => /\\|\\s*Idle/.test(document.querySelector('#jp-main-statusbar')?.innerText || '')",
        timeout=deadline.ms(60.0))
    _run_all_and_wait(page, deadline)
    n_cells = page.locator(".jp-Notebook .jp-Cell").count()

    canvas = page.locator(".jupyter-matplotlib-canvas-div canvas").last  # the top canvas
    canvas.scroll_into_view_if_needed(timeout=deadline.ms(10.0))
    page.wait_for_timeout(300)  # let the scrolling settle
    box = canvas.bounding_box(timeout=deadline.ms(10.0))
    assert box and box["width"] > 100 and box["height"] > 100, f"canvas box {box}"
    frac, scale, mags = _layout(exp, box)
    _wait_table(page, deadline, f"{n_old} picked points",
                lambda r: len(r) == n_old and all(s == "picked" for _, s in r))
    assert "all saved" in _unsaved_text(page), _unsaved_text(page)
    blank = _magnifier_std(page, mags)
    shots("loaded")

    # view 0: a new point; both magnifiers show the image around it
    x0, y0 = _aim(page, frac, scale, box, 0, target[0], deadline)
    page.mouse.click(x0, y0)
    _wait_table(page, deadline, "a new point being picked",
                lambda r: len(r) == n_old + 1 and r[-1][1] == "picking")
    shown = _wait_for(page, deadline, "both magnifiers showing the image",
                      lambda: (lambda s: s if min(s) > 8.0 else None)(_magnifier_std(page, mags)))
    shots("magnifiers")
    status = page.locator(".semlab-status").first.inner_text()
    assert status.startswith(f"point {n_old}: check the ×"), status

    # view 1: the true match; one unsaved change
    x1, y1 = _aim(page, frac, scale, box, 1, target[1], deadline)
    page.mouse.click(x1, y1)
    _wait_table(page, deadline, f"{n_old + 1} picked points",
                lambda r: len(r) == n_old + 1 and all(s == "picked" for _, s in r))
    _wait_for(page, deadline, "the unsaved count", lambda: "1 unsaved change" in _unsaved_text(page))
    before = _table_cells(page)[-1]

    # a press on the new marker with a 1 px wobble: the point does not move
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move(x0 + 1, y0)
    page.mouse.move(x0 + 1, y0 + 1)
    page.mouse.move(x0, y0 + 1)
    page.mouse.up()
    page.wait_for_timeout(1500)   # every event has reached the kernel and come back
    after = _table_cells(page)[-1]
    assert after[1:5] == before[1:5], (before, after)
    shots("after_wobble")

    # a button click, then keys: they reach the picker, not JupyterLab
    page.locator(".jupyter-widgets.widget-button[title='Drop']").click(timeout=deadline.ms(10.0))
    _wait_for(page, deadline, "the no-op message",
              lambda: "nothing to drop" in page.locator(".semlab-status").first.inner_text())
    page.wait_for_timeout(300)
    page.keyboard.press("u")      # undo the click in view 1: the point is being picked again
    _wait_table(page, deadline, "the undo by the u key",
                lambda r: len(r) == n_old + 1 and r[-1][1] == "picking")
    page.keyboard.press("a")      # accept the proposal
    _wait_table(page, deadline, "the accept by the a key",
                lambda r: len(r) == n_old + 1 and all(s == "picked" for _, s in r))
    assert page.locator(".jp-Notebook .jp-Cell").count() == n_cells, "a key reached JupyterLab"
    shots("keys_after_button")
    page.locator(".jupyter-widgets.widget-button[title='Save']").click(timeout=deadline.ms(10.0))
    status = page.locator(".widget-html-content", has_text="saved")
    status.first.wait_for(timeout=deadline.ms(30.0))
    _wait_for(page, deadline, "the count after saving", lambda: "all saved" in _unsaved_text(page))
    note = page.locator(".widget-html-content", has_text="saved " + str(n_old + 1)).first
    assert f"saved {n_old + 1} point(s)" in note.inner_text(), note.inner_text()
    shots("saved")
    return scale, blank, shown


def test_pick_and_save_in_browser(tmp_path):
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="needs the playwright package (requirements-dev.txt; "
                                      "scripts/_setup_browser.sh installs it)")
    chromium = _chromium()
    if chromium is None:
        pytest.skip("needs Chromium at /usr/bin/chromium (apt-get install chromium; "
                    "scripts/_setup_browser.sh does it)")
    deadline = _Deadline(TOTAL_BUDGET_S)
    served, exp = _make_workspace(tmp_path)
    csv_path = exp / "annotations" / "correspondences.csv"
    os.chmod(csv_path, 0o664)   # shared with the group: saving must keep it so
    old_text = csv_path.read_text()
    header, old_rows = _read_rows(csv_path)
    n_old = len(old_rows)
    assert n_old >= 2
    target = _choose_target(exp, old_rows)

    with _jupyter_lab(served, tmp_path, deadline) as (base, token, log_path):
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS,
                                         headless=True, timeout=deadline.ms(60.0))
            try:
                page = browser.new_page(viewport={"width": 1600, "height": 1000})
                page.set_default_timeout(30_000)
                shots = _Shots(page, tmp_path)
                try:
                    scale, blank, shown = _drive(page, base, token, exp, n_old, target,
                                                 deadline, shots)
                    assert max(blank) < 1.0, f"magnifiers not blank before a click: {blank}"
                    # the files on disk: one more row, at the clicked pixels; a backup of the old
                    bak = csv_path.with_name("correspondences.bak.csv")
                    assert bak.exists(), f"no backup {bak.name}; files: " + str(
                        sorted(p.name for p in csv_path.parent.iterdir()))
                    assert bak.read_text() == old_text
                    assert stat.S_IMODE(csv_path.stat().st_mode) == 0o664, oct(
                        csv_path.stat().st_mode)
                    assert not csv_path.with_name("correspondences.autosave.json").exists()
                    new_header, new_rows = _read_rows(csv_path)
                    assert new_header[:5] == header[:5]
                    assert len(new_rows) == n_old + 1, new_rows
                    old = np.array([[float(v) for v in r[1:5]] for r in old_rows])
                    kept = np.array([[float(v) for v in r[1:5]] for r in new_rows[:n_old]])
                    np.testing.assert_allclose(kept, old, atol=0.01)
                    new = np.array([float(v) for v in new_rows[-1][1:5]])
                    # view 0: where we clicked (a screen pixel is about half an image pixel)
                    assert np.all(np.abs(new[:2] - target[0]) <= 1.0), (new, target)
                    # view 1: the proposal accepted by the a key (sub-pixel matching, 0.01-0.2
                    # px from the truth), or the click: within a screen pixel of the truth
                    tol = 1.0 + 1.0 / min(scale)
                    assert np.all(np.abs(new[2:] - target[1]) <= tol), (new, target)
                except Exception as err:
                    shots("failure")
                    raise AssertionError(f"{type(err).__name__}: {err}\n"
                                         f"screenshots: {[str(p) for p in shots.paths]}\n"
                                         f"server log: {log_path}") from err
                finally:
                    print("browser test screenshots:", *[str(p) for p in shots.paths],
                          sep="\n  ")
            finally:
                browser.close()
