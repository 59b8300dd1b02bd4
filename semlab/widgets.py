"""JupyterLab pickers: the figure controllers and panels around the picking state.

The state lives in plain-numpy classes tested without a canvas:
:class:`semlab.picking.CorrespondencePicker` (points in ``V`` views, proposals, undo,
automatic points under review, unsaved changes, autosave) and
:class:`semlab.line_picking.LinePicker` (segments for vanishing-point calibration). This
module turns matplotlib canvas events into calls on the correspondence state
(:class:`PickerFigure`) and builds the ipywidgets panel (:func:`picker_widget`,
interactive with the ipympl backend, ``%matplotlib widget``).

Coordinates are ``(x, y)`` pixels, x to the right, y down, origin at the centre of the
top-left pixel (OpenCV), so that an image of shape ``(H, W)`` covers
``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.

Mouse and keys in the picker figure (each key also has a button in the panel):

=====================  =====================================================================
left click             new point in that view / the current point's position in that view
                       (a click on the current point's proposal × confirms it)
press on a marker      select it; moving the mouse more than ``drag_threshold_px`` (3 screen
                       px) drags it, keeping the offset between the marker and the mouse
right click            select the nearest point within ``pick_radius`` (8 screen px)
``a`` / enter          accept the current point with its proposals
``d`` / delete         delete the selected point
``u`` / ctrl+z         undo (many levels)
escape                 drop the point being picked
``h``                  hide / show the points already picked
=====================  =====================================================================

Clicks in the magnifier beside each view act on that view at the magnified position.
"""

from __future__ import annotations

import html
import itertools
from pathlib import Path

import numpy as np

from ._canvas import (_canvas_widget, _display_scale, _Focus, _image_limits, _new_figure,
                      _ReportsErrors, _show_image, _toolbar_busy)
from .errors import SemlabError
from .line_picking import LinePicker, LinePickerFigure, line_picker_widget
from .picking import (AUTO_PENDING, CorrespondencePicker, autosave_path, read_autosave,
                      write_autosave)
from .proposals import clip_line_to_image, matching_refine, same_position_refine

__all__ = [
    "PickerFigure",
    "picker_widget",
    "picker_layout",
    "table_html",
    # the state classes, importable from here as before the split
    "CorrespondencePicker",
    "LinePicker",
    "LinePickerFigure",
    "line_picker_widget",
    "clip_line_to_image",
    "same_position_refine",
]

_DONE, _PROP, _ACTIVE, _AUTO, _EPI = "#00e5ff", "orange", "red", "#ffe600", "yellow"
#: the magnifier shows this many screen pixels per image pixel, at least
MAGNIFIER_MIN_ZOOM = 8.0
_panel_ids = itertools.count()


def picker_layout(n_views, shape, width_in=10.5, magnifier=True):
    """Figure size and axes rectangles of the picker: tight margins, views side by side,
    each with its magnifier to the right.

    Parameters
    ----------
    n_views : int
    shape : (H, W) of the (first) view
    width_in : float
        Figure width, inches (10.5 at 100 dpi fits a JupyterLab notebook on a 1600 px wide
        window with the file browser open).
    magnifier : bool

    Returns
    -------
    figsize : (float, float) inches
    main : list of [left, bottom, width, height] figure fractions, one per view
    mag : list of rectangles (or None without magnifier)
    """
    h, w = shape[:2]
    col = 1.0 / n_views
    main_w = col * (0.70 if magnifier else 0.92)
    main_h_in = main_w * width_in * h / w
    top_in, bottom_in = 0.30, 0.55     # title; x label and the status line
    height_in = main_h_in + top_in + bottom_in
    main, mag = [], []
    for k in range(n_views):
        left = k * col + col * 0.06
        main.append([left, bottom_in / height_in, main_w, main_h_in / height_in])
        if magnifier:
            side_in = min(col * 0.22 * width_in, main_h_in * 0.6)
            mag.append([left + main_w + col * 0.015,
                        (bottom_in + main_h_in - side_in) / height_in,
                        side_in / width_in, side_in / height_in])
    return (width_in, height_in), main, (mag if magnifier else None)


class PickerFigure(_ReportsErrors):
    """Matplotlib view and mouse/key controller of a :class:`CorrespondencePicker`.

    The views are shown side by side, each with a magnifier (at least
    :data:`MAGNIFIER_MIN_ZOOM` screen px per image px) around the active point. Picked
    points are cyan circles with their ``point_id``, proposals orange crosses, the active
    point (being picked or selected) a red ring, automatic points under review yellow
    dots, and with ``F`` the epipolar line of the active point in yellow. See the module
    docstring for the mouse and keys.

    Parameters
    ----------
    picker : CorrespondencePicker
    fig : matplotlib Figure, optional
        An empty figure to draw in; default a new figure of :func:`picker_layout` size.
    pick_radius : float
        How close (screen px) a right click must be to a point to select it.
    select_radius : float
        How close (screen px) a press must be to a marker to grab it (about its size).
    drag_threshold_px : float
        Screen px the mouse must move with the button down before a drag starts, so that
        the wobble of a click does not move a point.
    magnifier : bool
    figsize : (float, float), optional

    Attributes
    ----------
    axes : list of Axes, one per view
    mag_axes : list of Axes (empty without magnifier)
    message : str
        Feedback on the last action (an error, or why it did nothing); "" when it worked.
    show_points : bool
        Draw the points already picked (the active one is always drawn).
    on_change : list of callables
        Called with no argument after every redraw (the panel refreshes its table).
    """

    def __init__(self, picker, fig=None, pick_radius=8.0, select_radius=6.0,
                 drag_threshold_px=3.0, magnifier=True, figsize=None):
        self.picker = picker
        v = picker.n_views
        size, main_rects, mag_rects = picker_layout(v, picker.shapes[0], magnifier=magnifier)
        if fig is None:
            fig = _new_figure(figsize or size)
        self.fig = fig
        self.pick_radius = float(pick_radius)
        self.select_radius = float(select_radius)
        self.drag_threshold_px = float(drag_threshold_px)
        self.show_points = True
        self.axes = [fig.add_axes(r) for r in main_rects]
        self.mag_axes = [fig.add_axes(r) for r in mag_rects] if magnifier else []
        self._art = []
        for k, ax in enumerate(self.axes):
            _show_image(ax, picker.images[k], picker.titles[k])
            ax.title.set_fontsize(9)
            ax.tick_params(labelsize=8)
            self._art.append(self._marker_artists(ax))
            self._art[k]["labels"] = {}
            self._art[k]["auto"] = ax.plot([], [], ".", color=_AUTO, ms=3, ls="none")[0]
        self._mag_img = []
        for k, ax in enumerate(self.mag_axes):
            lo, hi = _image_limits(picker.images[k])
            self._mag_img.append(ax.imshow(np.zeros((1, 1)), cmap="gray", vmin=lo, vmax=hi,
                                           interpolation="nearest",
                                           extent=(-0.5, 0.5, 0.5, -0.5)))
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_autoscale_on(False)
            ax.set_title(f"{picker.titles[k]} (magnified)", fontsize=8)
            self._art[k]["mag"] = self._marker_artists(ax, scale=1.6)
        self._status = fig.text(0.005, 0.005, "", fontsize=9, va="bottom")
        self.message = ""
        self.on_change = []
        self._drag = None
        self._bg = None
        self._mag_centre = [None] * v
        self._cids = [fig.canvas.mpl_connect(name, cb) for name, cb in (
            ("button_press_event", self._on_press),
            ("motion_notify_event", self._on_motion),
            ("button_release_event", self._on_release),
            ("key_press_event", self._on_key))]
        self.redraw()

    @staticmethod
    def _marker_artists(ax, scale=1.0):
        return {"epi": ax.plot([], [], "-", color=_EPI, lw=1.0, alpha=0.8)[0],
                "done": ax.plot([], [], "o", mfc="none", mec=_DONE, ms=7 * scale,
                                ls="none")[0],
                "prop": ax.plot([], [], "x", color=_PROP, ms=8 * scale, mew=1.5,
                                ls="none")[0],
                "active": ax.plot([], [], "o", mfc="none", mec=_ACTIVE, ms=13 * scale, mew=2,
                                  ls="none")[0]}

    def disconnect(self):
        """Stop listening to the canvas."""
        for cid in self._cids:
            self.fig.canvas.mpl_disconnect(cid)
        self._cids = []

    # ---- drawing
    def redraw(self):
        """Update every artist from the picker state and ask the canvas to redraw."""
        self._update_artists()
        self.fig.canvas.draw_idle()
        for cb in list(self.on_change):
            cb()

    def status_text(self):
        """The status line: the feedback of the last action, else the next step."""
        return self.message or self.picker.status()

    def _dynamic_artists(self):
        """Everything that changes while picking (markers, lines, labels, magnifiers)."""
        arts = []
        for k in range(len(self.axes)):   # the order of a full draw: images, lines, texts
            a = self._art[k]
            arts += [a["epi"], a["auto"], a["done"], a["prop"], a["active"]]
            arts += list(a["labels"].values())
        for k in range(len(self.mag_axes)):
            m = self._art[k]["mag"]
            arts += [self._mag_img[k], m["epi"], m["done"], m["prop"], m["active"]]
        return arts + [self._status]

    def _start_blit(self):
        """Dragging: draw the images once without the markers and keep that background, so
        that each mouse move only redraws the markers (a full draw of two 2048×1536 views
        takes ~0.25 s; see :meth:`_blit`)."""
        canvas = self.fig.canvas
        if not getattr(canvas, "supports_blit", False):
            return
        for a in self._dynamic_artists():
            a.set_animated(True)
        canvas.draw()
        self._bg = canvas.copy_from_bbox(self.fig.bbox)
        self._blit()

    def _blit(self):
        self._update_artists()
        canvas = self.fig.canvas
        canvas.restore_region(self._bg)
        for a in self._dynamic_artists():
            a.set_animated(True)
            self.fig.draw_artist(a)
        canvas.blit(self.fig.bbox)

    def _stop_blit(self):
        if self._bg is None:
            return
        self._bg = None
        for a in self._dynamic_artists():
            a.set_animated(False)

    def active(self):
        """Index of the active point: the one being picked, else the selected one."""
        p = self.picker
        return p.current if p.current is not None else p.selected

    def _update_artists(self):
        p = self.picker
        active = self.active()
        for k, ax in enumerate(self.axes):
            xy = p.pts[:, k] if p.n_points else np.zeros((0, 2))
            fin = np.isfinite(xy).all(axis=1)
            conf = p.confirmed[:, k] if p.n_points else np.zeros(0, bool)
            shown = fin if self.show_points else np.zeros_like(fin)
            if active is not None:
                shown = shown.copy()
                shown[active] = fin[active]
            done, prop = shown & conf, shown & ~conf
            seg = self._epipolar_for(active, k) if active is not None else None
            targets = [self._art[k]] + ([self._art[k]["mag"]] if self.mag_axes else [])
            for art in targets:
                art["done"].set_data(xy[done, 0], xy[done, 1])
                art["prop"].set_data(xy[prop, 0], xy[prop, 1])
                if active is not None and fin[active]:
                    art["active"].set_data([xy[active, 0]], [xy[active, 1]])
                else:
                    art["active"].set_data([], [])
                art["epi"].set_data(*(([], []) if seg is None else (seg[:, 0], seg[:, 1])))
            pend = p.auto_state == AUTO_PENDING
            auto = p.auto_pts[pend, k] if self.show_points else np.zeros((0, 2))
            self._art[k]["auto"].set_data(auto[:, 0], auto[:, 1])
            self._update_labels(k, ax, xy, shown, prop)
            if self.mag_axes:
                self._update_magnifier(k, xy[active] if active is not None else None)
        n_done = int(p.complete().sum())
        self._status.set_text(f"{n_done} point(s) picked, {p.unsaved_changes()} unsaved. "
                              + self.status_text())

    def magnifier_half_px(self, k):
        """Half width (image px) of the part of view ``k`` its magnifier shows, so that one
        image pixel is at least :data:`MAGNIFIER_MIN_ZOOM` screen pixels wide."""
        ax = self.mag_axes[k]
        ratio = getattr(self.fig.canvas, "device_pixel_ratio", 1.0) or 1.0
        width = ax.get_position().width * self.fig.get_figwidth() * self.fig.dpi / ratio
        return max(2, int((width / MAGNIFIER_MIN_ZOOM - 1) // 2))

    def magnifier_zoom(self, k):
        """Screen pixels per image pixel in the magnifier of view ``k`` (as drawn now)."""
        ratio = getattr(self.fig.canvas, "device_pixel_ratio", 1.0) or 1.0
        return _display_scale(self.mag_axes[k]) / ratio

    def _update_magnifier(self, k, centre):
        ax, art = self.mag_axes[k], self._mag_img[k]
        if self._drag is not None and self._drag["started"] and self._drag["axes"] is ax:
            centre = self._mag_centre[k]        # do not move the view under the mouse
        if centre is None or not np.all(np.isfinite(centre)):
            art.set_visible(False)
            self._mag_centre[k] = None
            return
        self._mag_centre[k] = np.asarray(centre, float).copy()
        r = self.magnifier_half_px(k)
        img = self.picker.images[k]
        h, w = img.shape[:2]
        cx, cy = int(np.rint(centre[0])), int(np.rint(centre[1]))
        c0, c1 = max(cx - r - 1, 0), min(cx + r + 2, w)
        r0, r1 = max(cy - r - 1, 0), min(cy + r + 2, h)
        art.set_data(img[r0:r1, c0:c1])
        art.set_extent((c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
        art.set_visible(True)
        ax.set_xlim(cx - r - 0.5, cx + r + 0.5)
        ax.set_ylim(cy + r + 0.5, cy - r - 0.5)

    def _update_labels(self, k, ax, xy, shown, prop):
        """Point-id labels of view ``k``, updated in place (cheap while dragging)."""
        labels = self._art[k]["labels"]
        keep = set()
        for i in np.flatnonzero(shown):
            pid = int(self.picker.point_id[i])
            keep.add(pid)
            pos = (xy[i, 0] + 4, xy[i, 1] - 4)
            color = _PROP if prop[i] else _DONE
            t = labels.get(pid)
            if t is None:
                labels[pid] = ax.text(*pos, str(pid), fontsize=8, color=color, clip_on=True)
            else:
                t.set_position(pos)
                t.set_color(color)
        for pid in set(labels) - keep:
            labels.pop(pid).remove()

    def _epipolar_for(self, i, view_to):
        p = self.picker
        if not p.F:
            return None
        for j in range(p.n_views):
            if j != view_to and p.confirmed[i, j] and np.isfinite(p.pts[i, j]).all():
                line = p._line(j, p.pts[i, j], view_to)
                if line is not None:
                    return clip_line_to_image(line, p.shapes[view_to])
        return None

    # ---- actions (keys and buttons)
    def _on_current(self, fn, none_message):
        """Run ``fn`` on the point being picked, or say ``none_message`` when there is none."""
        if self.picker.current is None:
            self.message = none_message
        else:
            self._run(fn)
        self.redraw()

    def do_accept(self):
        """Accept the current point (key ``a``); says so when there is none."""
        self._on_current(self.picker.accept,
                         "nothing to accept: no point is being picked (click a feature first)")

    def do_delete(self):
        """Delete the selected point (key ``d``); says so when none is selected."""
        p = self.picker
        if p.selected is None and p.current is None:
            self.message = "nothing to delete: select a point first (click on its marker)"
        else:
            pid = self._run(p.delete)
            if pid is not None:
                self.message = f"deleted point {pid} (u undoes)"
        self.redraw()

    def do_undo(self):
        """Undo the last edit (key ``u``); says so when there is nothing to undo."""
        self.message = "" if self.picker.undo() else "nothing to undo"
        self.redraw()

    def do_cancel(self):
        """Drop the point being picked (escape); says so when there is none."""
        self._on_current(self.picker.cancel, "nothing to drop: no point is being picked")

    def toggle_points(self, show=None):
        """Hide or show the points already picked (key ``h``)."""
        self.show_points = (not self.show_points) if show is None else bool(show)
        self.message = "" if self.show_points else ("points hidden (h or the button shows "
                                                    "them): only the active point is drawn")
        self.redraw()

    # ---- events
    def _view_of(self, event):
        if event.inaxes is None or event.xdata is None or event.ydata is None:
            return None
        for axes in (self.axes, self.mag_axes):
            for k, ax in enumerate(axes):
                if event.inaxes is ax:
                    return k
        return None

    def _grab(self, k, ax, xy):
        """The point whose marker in view ``k`` is under the mouse, or None.

        While a point is being picked only its own markers can be grabbed, so that a click
        next to another point still places the current one."""
        p = self.picker
        r = self.select_radius / _display_scale(ax)
        if p.current is not None:
            only = np.arange(p.n_points) == p.current
        elif self.show_points:
            only = None
        else:
            return None
        return p.nearest(k, xy, r, only=only)

    def _on_press(self, event):
        k = self._view_of(event)
        if k is None:
            return
        if _toolbar_busy(self.fig):
            self.message = ("the toolbar's zoom or pan is on, so clicks do not pick: click "
                            "its button again to pick points")
            self.redraw()
            return
        xy = np.array([event.xdata, event.ydata])
        p = self.picker
        if event.button == 1:
            i = self._grab(k, event.inaxes, xy)
            if i is not None:
                self._drag = {"i": i, "k": k, "axes": event.inaxes, "started": False,
                              "press": (event.x, event.y), "offset": p.pts[i, k] - xy}
                if p.current is None:
                    p.selected = i
                self.message = ""
            else:
                self._run(p.add, k, xy)
        elif event.button == 3:
            ax = event.inaxes
            if p.select_nearest(k, xy, self.pick_radius / _display_scale(ax)) is None:
                self.message = f"no point within {self.pick_radius:g} screen px to select"
            else:
                self.message = ""
        else:
            return
        self.redraw()

    def _on_motion(self, event):
        d = self._drag
        if d is None or event.inaxes is not d["axes"] or event.xdata is None:
            return
        if not d["started"]:
            moved = np.hypot(event.x - d["press"][0], event.y - d["press"][1])
            if moved < self.drag_threshold_px:
                return          # the wobble of a click: not a drag
            d["started"] = True
            first = True
        else:
            first = False
        target = np.array([event.xdata, event.ydata]) + d["offset"]
        self._run(self.picker.move, d["i"], d["k"], target, first)
        if first and self._bg is None:
            self._start_blit()
        if self._bg is not None:
            self._blit()
        else:
            self.redraw()

    def _on_release(self, event):
        d = self._drag
        if d is None:
            return
        self._drag = None
        self._stop_blit()
        p = self.picker
        i, k = d["i"], d["k"]
        if not d["started"] and i == p.current and not p.confirmed[i, k]:
            self._run(p.add, k, tuple(p.pts[i, k]))  # a click on a proposal confirms it
        self.redraw()

    def _on_key(self, event):
        key = (event.key or "").lower()
        actions = {"a": self.do_accept, "enter": self.do_accept, "d": self.do_delete,
                   "delete": self.do_delete, "u": self.do_undo, "ctrl+z": self.do_undo,
                   "escape": self.do_cancel, "h": self.toggle_points}
        if key in actions:
            actions[key]()


# --------------------------------------------------------------------------- the panel

def table_html(picker, active=None, n_rows=12):
    """The points as an HTML table showing ``n_rows`` rows around the active one.

    The rows shown are chosen so that the active point (being picked or selected) is in
    view, as a table scrolled to it would show; a line says which rows are shown.
    """
    rows = picker.table()
    v = picker.n_views
    head = ["point_id"] + [f"{a}{k}_px" for k in range(v) for a in "xy"] + ["crack_id", "status"]
    n = len(rows)
    start = 0 if active is None else int(np.clip(active - n_rows // 3, 0, max(n - n_rows, 0)))
    stop = min(start + n_rows, n)
    out = [f"<div class='semlab-picker-table'><div style='font-size:11px'>rows "
           f"{start + 1 if n else 0}–{stop} of {n}</div><table style='font-size:11px'>",
           "<tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for i in range(start, stop):
        r = rows[i]
        bg = " class='semlab-active' style='background:#ffe0b0'" if i == active else ""
        cells = []
        for h in head:
            val = r.get(h)
            cells.append("" if val is None else (f"{val:.2f}" if isinstance(val, float) else
                                                 str(val)))
        out.append(f"<tr{bg}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
    out.append("</table></div>")
    return "".join(out)


_HELP = (
    "<b>Click</b> a feature in one view, then check the orange × the picker proposes in the "
    "other view: click it (or press <b>a</b>) to accept, <b>drag</b> it to adjust, or click the "
    "right place. Press on a marker to select it; <b>d</b> deletes, <b>u</b> undoes, <b>esc</b> "
    "drops, <b>h</b> hides the picked points. The magnifiers show the active point. "
    "<br><span style='color:#b05000'><b>Keys go to the picker only while its image has the "
    "keyboard focus</b> (click in the image once). Elsewhere JupyterLab's own shortcuts act "
    "on the notebook: <b>a</b> inserts a cell, <b>d d</b> deletes one. The buttons give the "
    "focus back to the image.</span>")


def _resolve_refine(refine):
    if isinstance(refine, str):
        if refine != "matching":
            raise ValueError(f"refine must be a callable, None or 'matching', got {refine!r}")
        return matching_refine()
    return refine


def picker_widget(images, save_path, pts=None, refine="matching", F=None, titles=None,
                  load_existing=True, figsize=None, auto=None, autosave=True):
    """A JupyterLab panel to pick corresponding points in 2+ views and save them as CSV.

    Run ``%matplotlib widget`` (ipympl) first so that the figure is interactive.

    Parameters
    ----------
    images : list of V (H, W) arrays
    save_path : str or Path
        The correspondences CSV (e.g. ``annotations/correspondences.csv``). Save keeps a
        backup of the file it replaces, and its permissions.
    pts, F, titles
        See :class:`CorrespondencePicker`.
    refine : callable, None or "matching"
        The refinement of the proposals (see :class:`CorrespondencePicker`); ``"matching"``
        (default) is :func:`semlab.proposals.matching_refine`, None the geometric guess.
    load_existing : bool
        Start from the points in ``save_path`` when it exists and ``pts`` is None.
    figsize : (float, float), optional
    auto : MatchResult or (pts (M, V, 2), sigma_px (M,)), optional
        Automatic points to review in bulk (accept / reject the ones in the visible part of
        view 0, or reject those above a σ).
    autosave : bool
        After every edit write the session to ``<stem>.autosave.json`` beside
        ``save_path``; a re-run of the cell restores it (and says so). Save removes it.

    Returns
    -------
    ipywidgets.VBox
        Buttons for every action, the status line, the unsaved count, notes, the figure and
        a table of the points. ``box.picker`` is the :class:`CorrespondencePicker`,
        ``box.figure`` the :class:`PickerFigure`, ``box.buttons`` a dict of the buttons,
        ``box.status``, ``box.unsaved``, ``box.note``, ``box.table`` the HTML widgets.
    """
    import ipywidgets as W

    save_path = Path(save_path)
    picker = CorrespondencePicker(images, pts=pts, refine=_resolve_refine(refine), F=F,
                                  titles=titles)
    notes = []
    if load_existing and pts is None and save_path.exists():
        corr = picker.load(save_path)
        picker._undo.clear()
        notes.append(f"loaded {corr.n_points} point(s) from <code>{html.escape(str(save_path))}"
                     f"</code>")
    if auto is not None:
        a_pts, a_sig = (auto.pts, auto.sigma_px) if hasattr(auto, "sigma_px") else auto
        picker.set_auto(a_pts, a_sig)
        notes.append(f"{len(picker.auto_pts)} automatic point(s) to review (yellow dots)")
    if autosave:
        try:
            state = read_autosave(save_path)
            if state is not None:
                picker.restore_state(state, source=str(autosave_path(save_path)))
                picker._undo.clear()
                notes.append(
                    f"<span style='color:#b05000'><b>restored {picker.unsaved_changes()} "
                    f"unsaved change(s)</b> from <code>{html.escape(autosave_path(save_path).name)}"
                    f"</code> (autosaved {html.escape(state.get('time', '?'))}): Save keeps "
                    f"them, <i>Discard autosave</i> goes back to the saved file</span>")
        except SemlabError as err:
            notes.append(f"<span style='color:#b00'>{html.escape(str(err))}</span>")
    panel_class = f"semlab-picker-{next(_panel_ids)}"
    fig = _new_figure(figsize or picker_layout(picker.n_views, picker.shapes[0])[0])
    callbacks = []
    canvas = _canvas_widget(fig, callbacks)
    view = PickerFigure(picker, fig)
    focus = _Focus(panel_class)
    status, unsaved, note, table = W.HTML(), W.HTML(), W.HTML(" · ".join(notes)), W.HTML()
    last = {"key": None}

    def state_key():
        return (picker.n_points, picker.current, picker.pts.tobytes(),
                picker.confirmed.tobytes(), picker.crack_id.tobytes())

    def keep_autosave():
        key = state_key()
        if not autosave or key == last["key"] or view._drag is not None:
            return
        last["key"] = key
        side = autosave_path(save_path)
        if picker.unsaved_changes() or picker.current is not None:
            try:
                write_autosave(picker, save_path)
            except OSError as err:
                view.message = f"autosave failed: {err}"
        elif side.exists():
            side.unlink()

    def refresh():
        keep_autosave()
        color = "#b00" if view.message else "#000"
        status.value = (f"<span class='semlab-status' style='color:{color}'>"
                        f"{html.escape(view.status_text())}</span>")
        n = picker.unsaved_changes()
        unsaved.value = (f"<span class='semlab-unsaved'>{int(picker.complete().sum())} "
                         f"point(s) · <b>{n} unsaved change(s)</b></span>" if n else
                         f"<span class='semlab-unsaved'>{int(picker.complete().sum())} "
                         f"point(s) · all saved</span>")
        table.value = table_html(picker, view.active())
        buttons["Hide points"].value = not view.show_points
        for cb in callbacks:
            cb()

    view.on_change.append(refresh)

    def button(fn):
        def handler(_b):
            fn()
            focus()
        return handler

    def save():
        if picker.unsaved_changes() == 0 and save_path.exists():
            view.message = (f"nothing to save: no change since {save_path.name} was saved or "
                            f"loaded (the file is unchanged)")
            view.redraw()
            return
        try:
            bak = picker.save(save_path)
        except (SemlabError, OSError) as err:
            view.message = f"not saved: {err}"
            view.redraw()
            return
        n = int(picker.complete().sum())
        msg = f"saved {n} point(s) to <code>{html.escape(str(save_path))}</code>"
        if bak is not None:
            msg += f"; previous version kept as <code>{html.escape(Path(bak).name)}</code>"
        if picker.current is not None:
            msg += " (the point being picked was not saved: accept it first)"
        note.value = msg
        view.message = ""
        last["key"] = None
        view.redraw()

    def discard():
        side = autosave_path(save_path)
        if not side.exists() and picker.unsaved_changes() == 0:
            view.message = "nothing to discard: no autosave and no unsaved change"
        else:
            if save_path.exists():
                picker.load(save_path)
            if side.exists():
                side.unlink()
            last["key"] = state_key()
            note.value = f"back to the saved <code>{html.escape(save_path.name)}</code>"
            view.message = ""
        view.redraw()

    def review(accept):
        def run():
            if not len(picker.auto_pts):
                view.message = "no automatic points to review"
            else:
                ax = view.axes[0]
                n = picker.review_region(0, ax.get_xlim(), ax.get_ylim(), accept)
                word = "accepted" if accept else "rejected"
                view.message = "" if n else ("no pending automatic point in the visible part "
                                             "of view 0 (zoom to a region first)")
                note.value = (f"{word} {n} automatic point(s) in the visible part of "
                              f"{html.escape(picker.titles[0])}; {picker.auto_counts()}")
            view.redraw()
        return run

    def reject_sigma():
        if not len(picker.auto_pts):
            view.message = "no automatic points to review"
        else:
            n_rej, _ = picker.review_sigma(sigma.value)
            view.message = "" if n_rej else f"no pending automatic point has σ > {sigma.value:g} px"
            note.value = (f"rejected {n_rej} automatic point(s) with σ > {sigma.value:g} px; "
                          f"{picker.auto_counts()}")
        view.redraw()

    def lay(width="auto"):
        return W.Layout(width=width)

    buttons = {
        "Accept": W.Button(description="Accept (a)", tooltip="Accept", layout=lay()),
        "Drop": W.Button(description="Drop (esc)", tooltip="Drop", layout=lay()),
        "Delete": W.Button(description="Delete (d)", tooltip="Delete", layout=lay()),
        "Undo": W.Button(description="Undo (u)", tooltip="Undo", layout=lay()),
        "Hide points": W.ToggleButton(description="Hide points (h)", tooltip="Hide points",
                                      layout=lay()),
        "Save": W.Button(description="Save", tooltip="Save", button_style="primary",
                         layout=lay()),
        "Discard autosave": W.Button(description="Discard autosave",
                                     tooltip="Discard autosave", layout=lay()),
    }
    buttons["Accept"].on_click(button(view.do_accept))
    buttons["Drop"].on_click(button(view.do_cancel))
    buttons["Delete"].on_click(button(view.do_delete))
    buttons["Undo"].on_click(button(view.do_undo))
    buttons["Save"].on_click(button(save))
    buttons["Discard autosave"].on_click(button(discard))

    def on_hide(change):
        if change["new"] == view.show_points:      # the button, not a refresh
            view.toggle_points(not change["new"])
            focus()

    buttons["Hide points"].observe(on_hide, names="value")
    rows = [W.HBox(list(buttons.values()))]
    sigma = W.BoundedFloatText(value=0.1, min=0.0, max=100.0, step=0.01,
                               description="σ max (px)", layout=lay("170px"))
    if len(picker.auto_pts):
        for name, fn in (("Accept auto in view", review(True)),
                         ("Reject auto in view", review(False)),
                         ("Reject auto σ >", reject_sigma)):
            buttons[name] = W.Button(description=name, tooltip=name, layout=lay())
            buttons[name].on_click(button(fn))
        rows.append(W.HBox([buttons["Accept auto in view"], buttons["Reject auto in view"],
                            buttons["Reject auto σ >"], sigma]))
    box = W.VBox([W.HTML(_HELP)] + rows + [status, unsaved, note, canvas, table,
                                           focus.output])
    box.add_class(panel_class)
    box.picker, box.figure, box.buttons = picker, view, buttons
    box.status, box.unsaved, box.note, box.table, box.sigma = status, unsaved, note, table, sigma
    box.focus = focus
    last["key"] = state_key()   # the state on disk (file + autosave): nothing to write yet
    refresh()
    return box
