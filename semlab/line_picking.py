"""Picking line segments of a calibration image into line families (``lines.json``).

:class:`LinePicker` is the state (plain numpy, tested without a canvas);
:class:`LinePickerFigure` turns matplotlib events into calls on it and
:func:`line_picker_widget` is the JupyterLab panel (ipympl, ``%matplotlib widget``).

Coordinates are ``(x, y)`` pixels, x to the right, y down, origin at the centre of the
top-left pixel (OpenCV).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ._canvas import (_canvas_widget, _display_scale, _new_figure, _ReportsErrors, _show_image,
                      _toolbar_busy)
from .errors import ExperimentError, GeometryError, SemlabError
from .io import read_text, write_with_backup
from .picking import _UNDO_LEVELS, _check_images, _inside

__all__ = ["LinePicker", "LinePickerFigure", "line_picker_widget"]

_LINES_SCHEMA = "semlab-lines/1"


def _point_segment_distance(xy, seg):
    p, a, b = np.asarray(xy, float), seg[:2], seg[2:]
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-300), 0.0, 1.0)
    return float(np.hypot(*(p - (a + t * ab))))


class LinePicker:
    """The state of picking line segments in families of parallel 3D lines (one image).

    Two clicks make a segment, put in the selected family. See ``lines.json``
    (schema ``"semlab-lines/1"``) for the file written by :meth:`save`.

    Parameters
    ----------
    image : (H, W) array
    families : sequence of str
        Names of the line families (default ``("x", "y", "z")``, the three orthogonal
        directions of a calibration block).
    segments : dict, optional
        ``{family: [[x1, y1, x2, y2], ...]}`` already picked, pixels.

    Attributes
    ----------
    family : str
        The family new segments go to.
    pending : (2,) array or None
        The first end of the segment being picked.
    selected : int or None
        Index (in :meth:`segment_list` order) of the selected segment.
    """

    def __init__(self, image, families=("x", "y", "z"), segments=None):
        self.image = _check_images([image])[0]
        self.shape = self.image.shape[:2]
        self.families = tuple(str(f) for f in families)
        if not self.families or len(set(self.families)) != len(self.families):
            raise GeometryError(f"families must be distinct names, got {families!r}")
        self.family = self.families[0]
        self._segs = []  # list of (family, (4,) array)
        self.pending = None
        self.selected = None
        self.save_warning = None
        self._undo = []
        if segments:
            self._set_from_families(segments)

    def _set_from_families(self, fams):
        segs = []
        for f, lst in fams.items():
            if f not in self.families:
                raise GeometryError(f"family {f!r} is not one of {self.families}")
            for s in lst:
                s = np.asarray(s, dtype=float).reshape(-1)
                if s.shape != (4,) or not np.all(np.isfinite(s)):
                    raise GeometryError(f"segment {s!r} of family {f!r} must be 4 finite "
                                        f"numbers x1, y1, x2, y2")
                segs.append((f, s))
        self._segs = segs

    # ---- undo
    def _push(self):
        self._undo.append(([(f, s.copy()) for f, s in self._segs],
                           None if self.pending is None else self.pending.copy(),
                           self.selected, self.family))
        if len(self._undo) > _UNDO_LEVELS:
            del self._undo[0]

    def undo(self):
        """Undo the last edit; returns False when there is nothing to undo."""
        if not self._undo:
            return False
        self._segs, self.pending, self.selected, self.family = self._undo.pop()
        return True

    # ---- editing
    def set_family(self, family):
        """Choose the family of the next segments."""
        if family not in self.families:
            raise GeometryError(f"family {family!r} is not one of {self.families}")
        self.family = family

    def add(self, xy):
        """Click at ``xy`` (pixels): the first or second end of a segment.

        Returns
        -------
        int or None
            Index of the new segment when this click completes one, else None.
        """
        xy = np.asarray(xy, dtype=float).reshape(-1)
        if xy.shape != (2,) or not _inside(xy, self.shape):
            h, w = self.shape
            raise GeometryError(f"{xy!r} is not a pixel position inside the {w}x{h} image")
        if self.pending is None:
            self._push()
            self.pending = xy
            return None
        if np.hypot(*(xy - self.pending)) < 1.0:
            raise GeometryError("the segment is shorter than 1 px: click its other end farther "
                                "away")
        self._push()
        self._segs.append((self.family, np.concatenate([self.pending, xy])))
        self.pending = None
        self.selected = len(self._segs) - 1
        return self.selected

    def cancel(self):
        """Forget the first end of the segment being picked."""
        if self.pending is not None:
            self._push()
            self.pending = None

    def select_nearest(self, xy, max_dist_px):
        """Select the segment nearest to ``xy`` if within ``max_dist_px``; returns its index."""
        d = [_point_segment_distance(xy, s) for _, s in self._segs]
        if not d or min(d) > max_dist_px:
            self.selected = None
            return None
        self.selected = int(np.argmin(d))
        return self.selected

    def delete(self, index=None):
        """Delete a segment (default: the selected one, else the last one).

        Returns
        -------
        (str, (4,) array) or None
            The family and end points of the deleted segment.
        """
        if index is None:
            index = self.selected if self.selected is not None else len(self._segs) - 1
        if not (0 <= index < len(self._segs)):
            return None
        self._push()
        out = self._segs.pop(index)
        self.selected = None
        return out

    # ---- access
    def segment_list(self):
        """List of ``(family, (4,) array [x1, y1, x2, y2])`` in picking order."""
        return list(self._segs)

    def segments(self, family):
        """``(M, 4)`` array of the segments ``[x1, y1, x2, y2]`` (pixels) of ``family``."""
        arr = [s for f, s in self._segs if f == family]
        return np.asarray(arr, dtype=float).reshape(-1, 4)

    def to_lines_dict(self, view=0, image=None):
        """The segments in the ``"semlab-lines/1"`` schema (one view; empty families left out).

        Parameters
        ----------
        view : int
            View number written in the file.
        image : str, optional
            Image path relative to the experiment folder (e.g. ``"calibration/block_0.png"``).
        """
        entry = {"view": int(view)}
        if image is not None:
            entry["image"] = str(image)
        entry["families"] = {f: [[float(v) for v in s] for s in self.segments(f)]
                             for f in self.families if len(self.segments(f))}
        return {"schema": _LINES_SCHEMA, "views": [entry]}

    def load(self, path, view=0):
        """Replace the segments by those of ``view`` in a lines.json file (undoable)."""
        data = _read_lines_json(path)
        for entry in data.get("views", []):
            if int(entry.get("view", -1)) == int(view):
                self._push()
                fams = entry.get("families", {})
                for f in fams:
                    if f not in self.families:
                        self.families = self.families + (str(f),)
                self._set_from_families(fams)
                self.pending = self.selected = None
                return True
        return False

    def save(self, path, view=0, image=None, backup=True):
        """Write the segments as ``view`` of a lines.json file, keeping its other views.

        An existing file is kept as a backup first. Uses ``semlab.vanishing.write_lines``
        when available (its backup is ``lines.json.bak``, ``.bak1``, ...); work in progress
        it refuses (a family with fewer than 2 segments) is still written, with the same
        schema and a ``<stem>.bak.json`` backup, and :attr:`save_warning` says why it is not
        usable for calibration yet.

        Returns
        -------
        Path or None
            The backup written.
        """
        path = Path(path)
        mine = self.to_lines_dict(view, image)
        views = []
        if path.exists():
            views = [e for e in _read_lines_json(path).get("views", [])
                     if int(e.get("view", -1)) != int(view)]
        views.append(mine["views"][0])
        views.sort(key=lambda e: int(e.get("view", 0)))
        bak, self.save_warning = _write_lines_json(
            path, {"schema": _LINES_SCHEMA, "views": views}, backup)
        return bak


def _read_lines_json(path):
    path = Path(path)
    if not path.is_file():
        raise ExperimentError(f"{path}: lines file not found")
    try:
        data = json.loads(read_text(path, "lines file"))
    except json.JSONDecodeError as err:
        raise ExperimentError(f"{path}: not valid JSON ({err}); fix it or move it away "
                              f"before saving lines") from None
    if not isinstance(data, dict) or data.get("schema") != _LINES_SCHEMA:
        raise ExperimentError(f"{path}: expected a JSON object with \"schema\": "
                              f"\"{_LINES_SCHEMA}\"; fix it or move it away")
    return data


def _write_lines_json(path, data, backup=True):
    """Write a lines dict with a backup of the file it replaces.

    ``semlab.vanishing.write_lines`` (the canonical writer, which validates the file for
    calibration) is used when it exists and can represent ``data`` (views numbered
    ``0..n-1``, image names for all views or none). Work in progress that it refuses (a
    family with a single segment, a view with none) is written by the same schema here.

    Returns
    -------
    backup : Path or None
    warning : str or None
        Why the canonical writer refused the file (it is saved but not yet usable for
        calibration), None when it wrote it.
    """
    path = Path(path)
    views = data["views"]
    try:
        from .vanishing import read_lines, write_lines
    except ImportError:
        read_lines = write_lines = None
    n_img = sum("image" in v for v in views)
    if (write_lines is not None and backup and n_img in (0, len(views))
            and [int(v["view"]) for v in views] == list(range(len(views)))):
        images = [v["image"] for v in views] if n_img else None
        try:
            bak = write_lines(path, [v["families"] for v in views], images=images)
            return (Path(bak) if isinstance(bak, (str, Path)) else None), None
        except SemlabError:
            pass  # work in progress: written below, with the reason in the warning
    text = json.dumps(data, indent=1) + "\n"
    bak = write_with_backup(path, text, backup=backup)
    warning = None
    if read_lines is not None:
        try:
            read_lines(path)
        except SemlabError as err:
            warning = f"saved, but not usable for calibration yet: {err}"
    return bak, warning


_FAMILY_COLORS = {"x": "#ff4040", "y": "#40ff40", "z": "#4090ff"}
_OTHER_COLORS = ["#ffd000", "#ff40ff", "#40ffff", "#ff9000"]


class LinePickerFigure(_ReportsErrors):
    """Matplotlib view and controller of a :class:`LinePicker`.

    Left click twice: a segment in the selected family (a dashed line follows the mouse
    after the first click); right click: select the nearest segment; keys: a family name
    (e.g. ``x``) selects that family, ``d``/delete deletes the selected (else last) segment,
    ``u``/ctrl+z undoes, escape drops the first end.

    Parameters
    ----------
    picker : LinePicker
    fig : matplotlib Figure, optional
    title : str, optional
    pick_radius : float
        Display pixels within which a right click selects a segment.
    """

    def __init__(self, picker, fig=None, title=None, pick_radius=8.0, figsize=None):
        self.picker = picker
        if fig is None:
            fig = _new_figure(figsize or (6.5, 5.5))
        self.fig = fig
        self.pick_radius = float(pick_radius)
        self.ax = fig.subplots()
        _show_image(self.ax, picker.image, title or "lines")
        self._lines = {}
        self._colors = {}
        for j, f in enumerate(picker.families):
            self._add_family_artist(f, j)
        self._sel = self.ax.plot([], [], "-", color="white", lw=3, alpha=0.6)[0]
        self._pending = self.ax.plot([], [], "+", color="white", ms=12, mew=2)[0]
        self._rubber = self.ax.plot([], [], "--", color="white", lw=1)[0]
        self._status = fig.text(0.01, 0.005, "", fontsize=8, va="bottom")
        self.message = ""
        self.on_change = []
        self._cids = [fig.canvas.mpl_connect(name, cb) for name, cb in (
            ("button_press_event", self._on_press),
            ("motion_notify_event", self._on_motion),
            ("key_press_event", self._on_key))]
        self.redraw()

    def _add_family_artist(self, f, j):
        color = _FAMILY_COLORS.get(f, _OTHER_COLORS[j % len(_OTHER_COLORS)])
        self._colors[f] = color
        self._lines[f] = self.ax.plot([], [], "-o", color=color, lw=1.5, ms=3, label=f)[0]

    def disconnect(self):
        """Stop listening to the canvas."""
        for cid in self._cids:
            self.fig.canvas.mpl_disconnect(cid)
        self._cids = []

    def redraw(self):
        """Update the artists from the picker state and ask the canvas to redraw."""
        p = self.picker
        for j, f in enumerate(p.families):
            if f not in self._lines:
                self._add_family_artist(f, j)
            segs = p.segments(f)
            xs = np.column_stack([segs[:, 0], segs[:, 2], np.full(len(segs), np.nan)]).ravel()
            ys = np.column_stack([segs[:, 1], segs[:, 3], np.full(len(segs), np.nan)]).ravel()
            self._lines[f].set_data(xs, ys)
        segs = p.segment_list()
        if p.selected is not None and p.selected < len(segs):
            s = segs[p.selected][1]
            self._sel.set_data([s[0], s[2]], [s[1], s[3]])
        else:
            self._sel.set_data([], [])
        if p.pending is None:
            self._pending.set_data([], [])
            self._rubber.set_data([], [])
        else:
            self._pending.set_data([p.pending[0]], [p.pending[1]])
        counts = ", ".join(f"{f}: {len(p.segments(f))}" for f in p.families)
        self._status.set_text(f"family {p.family!r} | {counts}. " + (
            self.message or "click twice: segment | right click: select | d: delete | "
                            "u: undo | family key: choose family"))
        self._pending.set_color(self._colors.get(p.family, "white"))
        self.fig.canvas.draw_idle()
        for cb in list(self.on_change):
            cb()

    def _on_press(self, event):
        if event.inaxes is not self.ax or event.xdata is None:
            return
        if _toolbar_busy(self.fig):
            self.message = ("the toolbar's zoom or pan is on, so clicks do not pick: click "
                            "its button again to pick segments")
            self.redraw()
            return
        xy = (event.xdata, event.ydata)
        if event.button == 1:
            self._run(self.picker.add, xy)
        elif event.button == 3:
            self.picker.select_nearest(xy, self.pick_radius / _display_scale(self.ax))
        else:
            return
        self.redraw()

    def _on_motion(self, event):
        p = self.picker
        if p.pending is None or event.inaxes is not self.ax or event.xdata is None:
            return
        self._rubber.set_data([p.pending[0], event.xdata], [p.pending[1], event.ydata])
        self.fig.canvas.draw_idle()

    def _on_key(self, event):
        key = event.key or ""
        p = self.picker
        if key in p.families:
            p.set_family(key)
        elif key.lower() in ("d", "delete"):
            if p.delete() is None:
                self.message = "no segment to delete"
        elif key.lower() in ("u", "ctrl+z"):
            if not p.undo():
                self.message = "nothing to undo"
        elif key == "escape":
            p.cancel()
        else:
            return
        self.redraw()


def line_picker_widget(image, save_path, view=0, image_name=None, families=("x", "y", "z"),
                       load_existing=True, figsize=None):
    """A JupyterLab panel to pick line segments of a calibration image into lines.json.

    Parameters
    ----------
    image : (H, W) array
    save_path : str or Path
        The lines.json file; Save replaces only entry ``view`` and keeps a backup.
    view : int
        View number of this image in lines.json.
    image_name : str, optional
        Image path relative to the experiment folder, stored with the view.
    families : sequence of str
    load_existing : bool
        Start from the segments of ``view`` in ``save_path`` when it exists.

    Returns
    -------
    ipywidgets.VBox
        A family ToggleButtons, buttons Undo / Delete / Save, a status line and the
        figure. ``box.picker`` is the :class:`LinePicker`, ``box.figure`` the
        :class:`LinePickerFigure`, ``box.family`` the ToggleButtons, ``box.buttons`` a dict.
    """
    import ipywidgets as W

    save_path = Path(save_path)
    picker = LinePicker(image, families=families)
    status = W.HTML()
    if load_existing and save_path.exists():
        if picker.load(save_path, view=view):
            picker._undo.clear()
            status.value = f"loaded view {view} from <code>{save_path}</code>"
    fig = _new_figure(figsize or (6.5, 5.5))
    callbacks = []
    canvas = _canvas_widget(fig, callbacks)
    view_fig = LinePickerFigure(picker, fig, title=image_name or f"view {view}")
    family = W.ToggleButtons(options=list(picker.families), value=picker.family,
                             description="family")

    def on_family(change):
        picker.set_family(change["new"])
        view_fig.redraw()

    family.observe(on_family, names="value")

    def refresh():
        if family.value != picker.family and picker.family in family.options:
            family.value = picker.family
        for cb in callbacks:
            cb()

    view_fig.on_change.append(refresh)

    def undo(_b):
        if not picker.undo():
            view_fig.message = "nothing to undo"
        view_fig.redraw()

    def delete(_b):
        if picker.delete() is None:
            view_fig.message = "no segment to delete"
        view_fig.redraw()

    def save(_b):
        try:
            bak = picker.save(save_path, view=view, image=image_name)
        except (SemlabError, OSError) as err:
            status.value = f"<span style='color:#b00'>not saved: {err}</span>"
            return
        msg = f"saved view {view} to <code>{save_path}</code>"
        if bak is not None:
            msg += f"; previous version kept as <code>{bak}</code>"
        if picker.save_warning:
            msg += f"<br><span style='color:#b60'>{picker.save_warning}</span>"
        status.value = msg

    buttons = {name: W.Button(description=name, layout=W.Layout(width="90px"))
               for name in ("Undo", "Delete", "Save")}
    buttons["Undo"].on_click(undo)
    buttons["Delete"].on_click(delete)
    buttons["Save"].on_click(save)
    box = W.VBox([family, W.HBox(list(buttons.values())), status, canvas])
    box.picker, box.figure, box.family, box.buttons = picker, view_fig, family, buttons
    refresh()
    return box
