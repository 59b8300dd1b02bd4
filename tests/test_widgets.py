"""Pickers driven by real matplotlib events through the canvas callbacks (Agg, no browser)."""

import json

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.backend_bases import KeyEvent, MouseEvent, NavigationToolbar2  # noqa: E402

import semlab  # noqa: E402
from semlab.annotations import read_correspondences  # noqa: E402
from semlab.errors import GeometryError  # noqa: E402
from semlab.picking import autosave_path  # noqa: E402
from semlab.widgets import (MAGNIFIER_MIN_ZOOM, CorrespondencePicker, LinePicker,  # noqa: E402
                            LinePickerFigure, PickerFigure, line_picker_widget,
                            picker_widget, table_html)

H, W = 60, 80
F_AFFINE = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # x1ᵀ F x0 = 0  <=>  y1 = y0


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _vanishing_read_lines():
    try:
        from semlab.vanishing import read_lines
    except ImportError:
        return None
    return read_lines


def _images(n=2, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random((H, W)) for _ in range(n)]


def _display(ax, xy):
    return ax.transData.transform(xy)


def _send_px(fig, name, xpx, ypx, button=1):
    event = MouseEvent(name, fig.canvas, xpx, ypx, button=button)
    fig.canvas.callbacks.process(name, event)


def _send(fig, ax, name, xy, button=1):
    _send_px(fig, name, *_display(ax, xy), button=button)


def click(fig, ax, xy, button=1):
    _send(fig, ax, "button_press_event", xy, button)
    _send(fig, ax, "button_release_event", xy, button)


def drag(fig, ax, start, end):
    _send(fig, ax, "button_press_event", start)
    mid = (np.asarray(start) + np.asarray(end)) / 2
    _send(fig, ax, "motion_notify_event", tuple(mid))
    _send(fig, ax, "motion_notify_event", end)
    _send(fig, ax, "button_release_event", end)


def key(fig, k):
    fig.canvas.callbacks.process("key_press_event", KeyEvent("key_press_event", fig.canvas, k))


# --------------------------------------------------------------------------- picker via events

def test_figure_events_pick_accept_drag_undo_delete_save(tmp_path):
    picker = CorrespondencePicker(_images(), F=F_AFFINE)
    view = PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    assert [ax.get_xlabel() for ax in view.axes] == ["x (px)", "x (px)"]
    assert a0.get_ylabel() == "y (px)"

    # point 0: clicked in both views -> complete without accept
    click(fig, a0, (20.0, 30.0))
    assert picker.current == 0 and not picker.confirmed[0, 1]
    click(fig, a1, (26.0, 31.0))
    assert picker.current is None
    np.testing.assert_allclose(picker.pts[0], [[20, 30], [26, 31]], atol=1e-6)

    # point 1: clicked in view 0, proposal in view 1, accepted with the 'a' key
    click(fig, a0, (50.0, 10.0))
    assert picker.current == 1
    prop = picker.pts[1, 1].copy()
    assert np.all(np.isfinite(prop)) and not picker.confirmed[1, 1]
    key(fig, "a")
    assert picker.current is None and picker.confirmed[1].all()
    np.testing.assert_allclose(picker.pts[1, 1], prop)

    # drag point 0 in view 1; one undo brings it back in one step
    drag(fig, a1, (26.0, 31.0), (40.0, 44.0))
    np.testing.assert_allclose(picker.pts[0, 1], [40, 44], atol=1e-6)
    key(fig, "u")
    np.testing.assert_allclose(picker.pts[0, 1], [26, 31], atol=1e-6)

    path = tmp_path / "correspondences.csv"
    assert picker.save(path) is None
    # select point 1 with a right click in view 1, delete with the 'delete' key
    click(fig, a1, tuple(picker.pts[1, 1] + 1.0), button=3)
    assert picker.selected == 1
    key(fig, "delete")
    assert picker.point_id.tolist() == [0]
    assert set(view._art[1]["labels"]) == {0}  # the deleted point's label is gone
    assert view._art[1]["labels"][0].get_position() == pytest.approx((26 + 4, 31 - 4))
    bak = picker.save(path)
    assert bak == tmp_path / "correspondences.bak.csv"
    assert read_correspondences(path, n_views=2).point_id.tolist() == [0]
    key(fig, "ctrl+z")
    assert picker.point_id.tolist() == [0, 1]


def test_a_click_wobble_does_not_move_a_point_and_a_drag_keeps_the_grab_offset():
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, a0 = view.fig, view.axes[0]
    click(fig, a0, (20.0, 30.0))
    click(fig, view.axes[1], (22.0, 30.0))
    before = picker.pts.copy()
    # press 3 screen px beside the marker (on it), wobble 1-2 px, release
    x, y = _display(a0, (20.0, 30.0))
    _send_px(fig, "button_press_event", x + 3, y)
    _send_px(fig, "motion_notify_event", x + 4, y + 1)
    _send_px(fig, "motion_notify_event", x + 3, y + 2)
    _send_px(fig, "button_release_event", x + 3, y + 2)
    np.testing.assert_array_equal(picker.pts, before)
    assert picker.selected == 0 and picker.n_points == 1
    # a real drag from 3 px beside the marker: the marker keeps its offset to the mouse
    scale = view.axes[0].transData.transform([1.0, 0.0])[0] - a0.transData.transform([0, 0])[0]
    _send_px(fig, "button_press_event", x + 3, y)
    _send_px(fig, "motion_notify_event", x + 3 + 10 * scale, y)
    _send_px(fig, "button_release_event", x + 3 + 10 * scale, y)
    np.testing.assert_allclose(picker.pts[0, 0], [30.0, 30.0], atol=1e-6)


def test_select_needs_a_press_on_the_marker():
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, a0 = view.fig, view.axes[0]
    click(fig, a0, (20.0, 30.0))
    click(fig, view.axes[1], (22.0, 30.0))
    picker.selected = None
    x, y = _display(a0, (20.0, 30.0))
    # 8 screen px away is beside the marker: a new point, not a selection (nor a move)
    _send_px(fig, "button_press_event", x + 8, y)
    _send_px(fig, "button_release_event", x + 8, y)
    assert picker.n_points == 2 and picker.current == 1
    np.testing.assert_allclose(picker.pts[0, 0], [20, 30])


def test_click_in_the_other_view_places_the_point_unless_on_the_proposal():
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    click(fig, a0, (30.0, 20.0))
    prop = picker.pts[0, 1].copy()
    np.testing.assert_allclose(prop, [30, 20])
    # 5 image px beside the proposal: the point is placed there, not the proposal accepted
    click(fig, a1, (35.0, 20.0))
    assert picker.current is None
    np.testing.assert_allclose(picker.pts[0, 1], [35, 20])
    # on the proposal: confirms it
    click(fig, a0, (60.0, 40.0))
    prop = tuple(picker.pts[1, 1])
    click(fig, a1, prop)
    assert picker.current is None and picker.confirmed[1].all()
    np.testing.assert_allclose(picker.pts[1, 1], prop)
    # while a point is picked, a click next to ANOTHER point's marker places the current one
    click(fig, a0, (10.0, 50.0))
    click(fig, a1, (35.5, 20.5))
    assert picker.n_points == 3 and picker.current is None
    np.testing.assert_allclose(picker.pts[0, 1], [35, 20])
    np.testing.assert_allclose(picker.pts[2, 1], [35.5, 20.5])
    click(fig, a0, (70.0, 40.0))
    key(fig, "escape")
    assert picker.n_points == 3 and picker.current is None


def test_magnifier_in_both_views_follows_the_active_point():
    picker = CorrespondencePicker([np.arange(H * W, dtype=float).reshape(H, W)] * 2)
    view = PickerFigure(picker)
    fig = view.fig
    fig.canvas.draw()
    assert len(view.mag_axes) == 2
    assert not any(im.get_visible() for im in view._mag_img)   # nothing active yet
    click(fig, view.axes[0], (40.0, 25.0))
    fig.canvas.draw()
    for k, ax in enumerate(view.mag_axes):
        assert view._mag_img[k].get_visible()
        assert view.magnifier_zoom(k) >= MAGNIFIER_MIN_ZOOM
        x0, x1 = ax.get_xlim()
        assert x0 < 40 < x1 and (x1 - x0) < 40
        # the magnified pixels are the image's
        arr = view._mag_img[k].get_array()
        left, _, _, top = view._mag_img[k].get_extent()
        assert arr[0, 0] == picker.images[k][int(top + 0.5), int(left + 0.5)]
    # a click in the magnifier acts on that view at the magnified position
    click(fig, view.mag_axes[1], (41.0, 26.0))
    np.testing.assert_allclose(picker.pts[0, 1], [41, 26])
    assert picker.current is None


def test_drag_redraws_only_the_markers_and_matches_a_full_draw():
    """While dragging, each mouse move blits the markers over a saved background (no full
    canvas draw), and what is on the canvas equals a full redraw of the same state."""
    picker = CorrespondencePicker(_images(), F=F_AFFINE)
    view = PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    click(fig, a0, (20.0, 30.0))
    click(fig, a1, (26.0, 31.0))
    click(fig, a0, (50.0, 10.0))
    key(fig, "a")
    fig.canvas.draw()
    full_draws = []
    real_draw = fig.canvas.draw

    def counting_draw(*a, **k):
        full_draws.append(1)
        return real_draw(*a, **k)

    fig.canvas.draw = counting_draw
    _send(fig, a1, "button_press_event", (26.0, 31.0))
    full_draws.clear()
    for xy in ((30.0, 35.0), (35.0, 40.0), (40.0, 44.0)):
        _send(fig, a1, "motion_notify_event", xy)
    assert len(full_draws) == 1                      # the background, once for 3 moves
    assert view._bg is not None
    blitted = np.asarray(fig.canvas.buffer_rgba()).copy()
    np.testing.assert_allclose(picker.pts[0, 1], [40, 44], atol=1e-6)
    # a full draw of the same state gives the same pixels, except where lines meet an axes
    # frame (blitted lines are drawn over the frame, a full draw puts the frame on top)
    for a in view._dynamic_artists():
        a.set_animated(False)
    real_draw()
    diff = np.any(blitted != np.asarray(fig.canvas.buffer_rgba()), axis=-1)
    frames_px = sum(2 * sum(ax.get_window_extent().size) for ax in view.axes + view.mag_axes)
    assert diff.sum() < 2 * frames_px
    h = diff.shape[0]
    r, c = np.nonzero(diff)
    on_frame = np.zeros(len(r), bool)
    for ax in view.axes + view.mag_axes:
        x0, y0, w, hh = ax.get_window_extent().bounds
        on_frame |= (np.abs(c[:, None] - np.array([x0, x0 + w])).min(1) <= 1.5)
        on_frame |= (np.abs((h - r)[:, None] - np.array([y0, y0 + hh])).min(1) <= 1.5)
    assert on_frame.all()
    _send(fig, a1, "button_release_event", (40.0, 44.0))
    assert view._bg is None and not any(a.get_animated() for a in view._dynamic_artists())
    np.testing.assert_allclose(picker.pts[0, 1], [40, 44], atol=1e-6)


def test_clicks_in_zoom_mode_say_why_they_do_not_pick():
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, a0 = view.fig, view.axes[0]
    toolbar = NavigationToolbar2(fig.canvas)
    toolbar.zoom()  # zoom mode: clicks belong to the toolbar
    click(fig, a0, (20.0, 30.0))
    assert picker.n_points == 0 and "zoom or pan is on" in view.message
    toolbar.zoom()  # zoom mode off
    event = MouseEvent("button_press_event", fig.canvas, 1, 1, button=1)  # figure corner
    fig.canvas.callbacks.process("button_press_event", event)
    assert picker.n_points == 0
    click(fig, a0, (20.0, 30.0))
    assert picker.n_points == 1 and view.message == ""


def test_actions_that_do_nothing_say_so():
    view = PickerFigure(CorrespondencePicker(_images()))
    for fn, words in ((view.do_accept, "nothing to accept"), (view.do_delete, "nothing to delete"),
                      (view.do_undo, "nothing to undo"), (view.do_cancel, "nothing to drop")):
        fn()
        assert view.message.startswith(words)
        assert words in view._status.get_text()
    click(view.fig, view.axes[0], (20.0, 30.0), button=3)
    assert "no point within" in view.message


def test_hide_points_keeps_the_active_one():
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    for x in (10.0, 30.0):
        click(fig, a0, (x, 20.0))
        click(fig, a1, (x + 1, 20.0))
    click(fig, a0, (50.0, 40.0))
    key(fig, "h")
    assert not view.show_points
    xs, _ = view._art[0]["done"].get_data()
    assert list(xs) == pytest.approx([50.0])      # only the point being picked
    assert set(view._art[0]["labels"]) == {2}
    # hidden points cannot be grabbed: a click on one places the current point
    click(fig, a1, (11.0, 20.0))
    np.testing.assert_allclose(picker.pts[2, 1], [11, 20])
    key(fig, "h")
    assert len(view._art[0]["done"].get_data()[0]) == 3


def test_figure_shows_epipolar_line_of_active_point():
    picker = CorrespondencePicker(_images(), F=F_AFFINE)
    view = PickerFigure(picker)
    click(view.fig, view.axes[0], (20.0, 30.0))
    xs, ys = view._art[1]["epi"].get_data()
    np.testing.assert_allclose(xs, [-0.5, W - 0.5])
    np.testing.assert_allclose(ys, [30.0, 30.0], atol=1e-9)
    assert picker.pts[0, 1, 1] == pytest.approx(30.0)   # the proposal lies on that line
    xs, ys = view._art[1]["mag"]["epi"].get_data()      # and the magnifier shows it too
    np.testing.assert_allclose(ys, [30.0, 30.0], atol=1e-9)


def test_table_shows_the_rows_around_the_active_point():
    picker = CorrespondencePicker(_images(), pts=np.tile([[[5.0, 5.0]]], (40, 2, 1)) +
                                  np.arange(40)[:, None, None])
    html_text = table_html(picker, active=30, n_rows=12)
    assert "rows 27–38 of 40" in html_text
    assert "class='semlab-active'" in html_text and "<td>30</td>" in html_text
    assert "<td>5</td>" not in html_text
    assert "rows 1–12 of 40" in table_html(picker, active=None, n_rows=12)


# --------------------------------------------------------------------------- widget panel

def _saved(path, n=1):
    first = CorrespondencePicker(_images())
    for i in range(n):
        first.add(0, (10.0 + 10 * i, 10.0))
        first.add(1, (11.0 + 10 * i, 10.0))
    first.save(path)


def test_picker_widget_buttons_unsaved_count_save_with_backup(tmp_path):
    path = tmp_path / "correspondences.csv"
    _saved(path)
    box = picker_widget(_images(), path, F=F_AFFINE, refine=None)
    picker, view = box.picker, box.figure
    assert picker.n_points == 1 and "loaded 1 point(s)" in box.note.value
    assert "all saved" in box.unsaved.value
    click(view.fig, view.axes[0], (40.0, 25.0))
    assert "point 1: check the ×" in box.status.value
    box.buttons["Accept"].click()
    assert picker.current is None and picker.n_points == 2
    assert "1 unsaved change(s)" in box.unsaved.value
    assert "<td>1</td>" in box.table.value and "40.00" in box.table.value
    assert autosave_path(path).exists()           # the session is kept beside the file
    box.buttons["Save"].click()
    assert "correspondences.bak.csv" in box.note.value and "saved 2 point(s)" in box.note.value
    assert "all saved" in box.unsaved.value and not autosave_path(path).exists()
    assert read_correspondences(tmp_path / "correspondences.bak.csv").n_points == 1
    assert read_correspondences(path).n_points == 2
    box.buttons["Save"].click()
    assert "nothing to save" in box.status.value
    picker.selected = 0
    box.buttons["Delete"].click()
    assert picker.point_id.tolist() == [1] and "deleted point 0" in box.status.value
    box.buttons["Undo"].click()
    assert picker.point_id.tolist() == [0, 1]
    box.buttons["Drop"].click()
    assert "nothing to drop" in box.status.value
    box.buttons["Hide points"].value = True
    assert not view.show_points
    # every button gives the keyboard focus back to the canvas
    assert box.focus.count == 7
    outputs = box.focus.output.outputs
    assert outputs and "jupyter-matplotlib-canvas-div" in outputs[-1]["data"][
        "application/javascript"] and box.focus.css_class in box._dom_classes


def test_picker_widget_restores_the_autosave_on_a_rerun(tmp_path):
    path = tmp_path / "correspondences.csv"
    _saved(path)
    box = picker_widget(_images(), path, refine=None)
    click(box.figure.fig, box.figure.axes[0], (40.0, 25.0))
    click(box.figure.fig, box.figure.axes[1], (42.0, 25.0))
    click(box.figure.fig, box.figure.axes[0], (60.0, 45.0))   # being picked
    # the cell is run again without saving: nothing is lost, and the panel says so; showing
    # the panel writes nothing (a report run only reads the experiment folder)
    side = autosave_path(path)
    stamp = side.stat().st_mtime_ns
    again = picker_widget(_images(), path, refine=None)
    assert side.stat().st_mtime_ns == stamp
    assert again.picker.n_points == 3 and again.picker.current == 2
    assert "restored 1 unsaved change(s)" in again.note.value
    assert "1 unsaved change(s)" in again.unsaved.value
    again.buttons["Discard autosave"].click()
    assert again.picker.n_points == 1 and not autosave_path(path).exists()
    third = picker_widget(_images(), path, refine=None)
    assert third.picker.n_points == 1 and "restored" not in third.note.value


def test_picker_widget_bulk_review_of_automatic_points(tmp_path):
    auto = np.array([[[10.0, 10.0], [11.0, 10.0]], [[60.0, 40.0], [61.0, 40.0]]])
    box = picker_widget(_images(), tmp_path / "c.csv", refine=None,
                        auto=(auto, np.array([0.02, 0.5])))
    ax = box.figure.axes[0]
    assert len(box.figure._art[0]["auto"].get_data()[0]) == 2
    ax.set_xlim(-0.5, 30.0)                       # zoomed to the left part
    box.buttons["Accept auto in view"].click()
    assert box.picker.n_points == 1 and "accepted 1" in box.note.value
    box.sigma.value = 0.1
    box.buttons["Reject auto σ >"].click()
    assert "rejected 1" in box.note.value
    assert box.picker.auto_counts() == {"pending": 0, "accepted": 1, "rejected": 1}
    assert len(box.figure._art[0]["auto"].get_data()[0]) == 0
    box.buttons["Reject auto in view"].click()
    assert "no pending automatic point" in box.status.value


# --------------------------------------------------------------------------- lines

def test_line_picker_events_to_lines_dict_and_save(tmp_path):
    lp = LinePicker(_images(1)[0])
    view = LinePickerFigure(lp)
    fig, ax = view.fig, view.ax
    click(fig, ax, (5.0, 5.0))
    _send(fig, ax, "motion_notify_event", (30.0, 8.0))
    assert len(view._rubber.get_data()[0]) == 2
    click(fig, ax, (40.0, 10.0))
    click(fig, ax, (5.0, 30.0))
    click(fig, ax, (40.0, 35.0))
    key(fig, "y")
    click(fig, ax, (10.0, 2.0))
    click(fig, ax, (12.0, 50.0))
    click(fig, ax, (60.0, 2.0))
    click(fig, ax, (62.0, 50.0))
    key(fig, "z")
    click(fig, ax, (70.0, 10.0))
    click(fig, ax, (70.5, 10.2))  # shorter than 1 px: refused, first end kept
    assert "shorter" in view.message and lp.pending is not None
    key(fig, "escape")
    assert lp.pending is None
    d = lp.to_lines_dict(view=0, image="calibration/block_0.png")
    assert d["schema"] == "semlab-lines/1"
    entry = d["views"][0]
    assert entry["view"] == 0 and entry["image"] == "calibration/block_0.png"
    assert entry["families"]["x"] == [[5, 5, 40, 10], [5, 30, 40, 35]]
    assert entry["families"]["y"] == [[10, 2, 12, 50], [60, 2, 62, 50]]
    assert "z" not in entry["families"]  # empty families are left out

    # right click selects the nearest segment, 'd' deletes it, 'u' restores it
    click(fig, ax, (61.0, 26.0), button=3)
    assert lp.selected == 3
    key(fig, "d")
    assert lp.segments("y").tolist() == [[10, 2, 12, 50]]
    key(fig, "u")
    assert len(lp.segments("y")) == 2

    path = tmp_path / "lines.json"
    assert lp.save(path, view=0, image="calibration/block_0.png") is None
    assert lp.save_warning is None  # 2 families of 2 segments: a valid file
    if _vanishing_read_lines() is not None:  # readable by the calibration's reader
        fams = _vanishing_read_lines()(path)[0]
        np.testing.assert_allclose(fams["y"], lp.segments("y"))
    first = path.read_text()
    other = LinePicker(_images(1)[0])
    other.add((1.0, 1.0))
    other.add((20.0, 1.0))
    bak = other.save(path, view=1)  # one segment: work in progress, still saved
    assert bak is not None and bak.read_text() == first
    if _vanishing_read_lines() is not None:  # the calibration writer refused it: say so
        assert "2 segments" in other.save_warning
    data = json.loads(path.read_text())
    assert [v["view"] for v in data["views"]] == [0, 1]  # view 0 kept
    assert data["views"][0]["families"]["x"] == entry["families"]["x"]
    assert data["views"][1]["families"]["x"] == [[1, 1, 20, 1]]
    again = LinePicker(_images(1)[0])
    assert again.load(path, view=0)
    np.testing.assert_allclose(again.segments("y"), lp.segments("y"))


def test_line_picker_says_why_clicks_do_not_pick_in_zoom_mode():
    view = LinePickerFigure(LinePicker(_images(1)[0]))
    toolbar = NavigationToolbar2(view.fig.canvas)
    toolbar.pan()
    click(view.fig, view.ax, (10.0, 10.0))
    assert view.picker.pending is None and "zoom or pan is on" in view.message
    toolbar.pan()
    click(view.fig, view.ax, (10.0, 10.0))
    assert view.picker.pending is not None


def test_line_picker_errors(tmp_path):
    lp = LinePicker(_images(1)[0])
    with pytest.raises(GeometryError, match="family"):
        lp.set_family("w")
    with pytest.raises(GeometryError, match="inside"):
        lp.add((-3.0, 4.0))
    with pytest.raises(GeometryError, match="distinct"):
        LinePicker(_images(1)[0], families=("x", "x"))
    bad = tmp_path / "lines.json"
    bad.write_text("{not json")
    lp.add((1.0, 1.0))
    lp.add((9.0, 1.0))
    with pytest.raises(semlab.errors.ExperimentError, match="not valid JSON"):
        lp.save(bad)
    assert bad.read_text() == "{not json"


def test_line_picker_widget_family_toggle(tmp_path):
    box = line_picker_widget(_images(1)[0], tmp_path / "lines.json", view=0)
    lp, view = box.picker, box.figure
    box.family.value = "z"
    assert lp.family == "z"
    click(view.fig, view.ax, (5.0, 5.0))
    click(view.fig, view.ax, (5.0, 40.0))
    assert lp.segments("z").shape == (1, 4)
    key(view.fig, "x")
    assert box.family.value == "x"  # the keyboard choice shows in the toggle
    box.buttons["Save"].click()
    data = json.loads((tmp_path / "lines.json").read_text())
    assert data["views"][0]["view"] == 0
    assert data["views"][0]["families"]["z"] == [[5, 5, 5, 40]]


def test_screen_image_shows_the_visible_part_at_screen_resolution():
    """Zoomed out, a full-size view is shown block-averaged (fewer pixels to resample on
    every draw) with pixel centres kept at integer coordinates; zoomed in, the visible crop
    is the image itself."""
    import matplotlib.pyplot as plt

    from semlab._canvas import _ScreenImage

    rng = np.random.default_rng(0)
    img = rng.random((1536, 2048))
    fig, ax = plt.subplots(figsize=(4, 3), dpi=100)
    try:
        si = _ScreenImage(ax, img, cmap="gray")
        fig.canvas.draw()
        si.update()
        c0, c1, r0, r1, k = si.key
        assert k > 1 and (c0, r0) == (0, 0) and (c1, r1) == (2048, 1536)
        shown = si.artist.get_array()
        left, right, bottom, top = si.artist.get_extent()
        assert (left, top) == (-0.5, -0.5)
        assert shown.shape[1] * k == pytest.approx(right - left)
        # block (2, 3) is the mean of its k × k pixels
        assert shown[2, 3] == pytest.approx(img[2 * k:3 * k, 3 * k:4 * k].mean(), rel=1e-5)
        # zoom into a 40 × 30 px region: full resolution, exact pixels, half-pixel extent
        ax.set_xlim(100.5, 140.5)
        ax.set_ylim(230.5, 200.5)
        c0, c1, r0, r1, k = si.key
        assert k == 1
        np.testing.assert_array_equal(si.artist.get_array(), img[r0:r1, c0:c1].astype(np.float32))
        assert tuple(si.artist.get_extent()) == (c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5)
        assert c0 <= 101 and c1 >= 141 and r0 <= 201 and r1 >= 231
        # the limits the user set are kept
        assert ax.get_xlim() == (100.5, 140.5)
    finally:
        plt.close(fig)


