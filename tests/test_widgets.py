"""Pickers driven by real matplotlib events through the canvas callbacks (Agg, no browser)."""

import csv
import json
import sys
import types

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from matplotlib.backend_bases import KeyEvent, MouseEvent, NavigationToolbar2  # noqa: E402

import semlab  # noqa: E402
from semlab.annotations import read_correspondences  # noqa: E402
from semlab.errors import GeometryError, ImageError  # noqa: E402
from semlab.widgets import (CorrespondencePicker, LinePicker, LinePickerFigure,  # noqa: E402
                            PickerFigure, clip_line_to_image, line_picker_widget,
                            picker_widget)

H, W = 60, 80
F_AFFINE = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # x1ᵀ F x0 = 0  <=>  y1 = y0


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


@pytest.fixture
def no_matching(monkeypatch):
    """Hide semlab.matching so that the default proposal is the plain geometric guess."""
    monkeypatch.delattr(semlab, "matching", raising=False)
    monkeypatch.setitem(sys.modules, "semlab.matching", None)


def _vanishing_read_lines():
    try:
        from semlab.vanishing import read_lines
    except ImportError:
        return None
    return read_lines


def _images(n=2, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random((H, W)) for _ in range(n)]


def _send(fig, ax, name, xy, button=1):
    x, y = ax.transData.transform(xy)
    event = MouseEvent(name, fig.canvas, x, y, button=button)
    fig.canvas.callbacks.process(name, event)


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

def test_figure_events_pick_accept_drag_undo_delete_save(tmp_path, no_matching):
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

    # save: CSV rows are the two points
    path = tmp_path / "correspondences.csv"
    assert picker.save(path) is None
    rows = list(csv.DictReader(open(path)))
    assert [r["point_id"] for r in rows] == ["0", "1"]
    assert [float(rows[0][c]) for c in ("x0_px", "y0_px", "x1_px", "y1_px")] == \
        pytest.approx([20, 30, 26, 31], abs=1e-3)

    # select point 1 with a right click in view 1, delete with the 'delete' key
    click(fig, a1, tuple(picker.pts[1, 1] + 1.0), button=3)
    assert picker.selected == 1
    key(fig, "delete")
    assert picker.point_id.tolist() == [0]
    assert set(view._labels[1]) == {0}  # the deleted point's label is gone
    assert view._labels[1][0].get_position() == pytest.approx((26 + 4, 31 - 4))
    # second save keeps the first file as the backup
    bak = picker.save(path)
    assert bak == tmp_path / "correspondences.bak.csv"
    assert len(list(csv.DictReader(open(bak)))) == 2
    assert read_correspondences(path, n_views=2).point_id.tolist() == [0]
    # undo the deletion with ctrl+z
    key(fig, "ctrl+z")
    assert picker.point_id.tolist() == [0, 1]


def test_drag_redraws_only_the_markers_and_matches_a_full_draw(no_matching):
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
    # a full draw of the same state gives the same pixels, except where the epipolar line
    # meets the axes frame (blitted lines are drawn over the frame, a full draw puts the
    # frame on top)
    for a in view._dynamic_artists():
        a.set_animated(False)
    real_draw()
    diff = np.any(blitted != np.asarray(fig.canvas.buffer_rgba()), axis=-1)
    assert diff.sum() < 50
    # every differing pixel lies on an axes frame line
    h = diff.shape[0]
    r, c = np.nonzero(diff)
    on_frame = np.zeros(len(r), bool)
    for ax in view.axes:
        x0, y0, w, hh = ax.get_window_extent().bounds
        on_frame |= (np.abs(c[:, None] - np.array([x0, x0 + w])).min(1) <= 1.5)
        on_frame |= (np.abs((h - r)[:, None] - np.array([y0, y0 + hh])).min(1) <= 1.5)
    assert on_frame.all()
    _send(fig, a1, "button_release_event", (40.0, 44.0))
    assert view._bg is None and not any(a.get_animated() for a in view._dynamic_artists())
    np.testing.assert_allclose(picker.pts[0, 1], [40, 44], atol=1e-6)


def test_click_on_proposal_confirms_and_escape_drops(no_matching):
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, (a0, a1) = view.fig, view.axes
    click(fig, a0, (30.0, 20.0))
    prop = tuple(picker.pts[0, 1])
    click(fig, a1, prop)
    assert picker.current is None and picker.confirmed[0].all()
    click(fig, a0, (60.0, 40.0))
    assert picker.current == 1
    key(fig, "escape")
    assert picker.n_points == 1 and picker.current is None


def test_clicks_ignored_in_zoom_mode_and_outside_axes(no_matching):
    picker = CorrespondencePicker(_images())
    view = PickerFigure(picker)
    fig, a0 = view.fig, view.axes[0]
    toolbar = NavigationToolbar2(fig.canvas)
    toolbar.zoom()  # zoom mode: clicks belong to the toolbar
    click(fig, a0, (20.0, 30.0))
    assert picker.n_points == 0
    toolbar.zoom()  # zoom mode off
    event = MouseEvent("button_press_event", fig.canvas, 1, 1, button=1)  # figure corner
    fig.canvas.callbacks.process("button_press_event", event)
    assert picker.n_points == 0
    click(fig, a0, (20.0, 30.0))
    assert picker.n_points == 1


def test_figure_shows_epipolar_line_of_active_point(no_matching):
    picker = CorrespondencePicker(_images(), F=F_AFFINE)
    view = PickerFigure(picker)
    click(view.fig, view.axes[0], (20.0, 30.0))
    xs, ys = view._epi[1].get_data()
    np.testing.assert_allclose(xs, [-0.5, W - 0.5])
    np.testing.assert_allclose(ys, [30.0, 30.0], atol=1e-9)
    # the proposal in view 1 lies on that line
    assert picker.pts[0, 1, 1] == pytest.approx(30.0)


# --------------------------------------------------------------------------- picker state

def test_epipolar_line_geometry():
    picker = CorrespondencePicker(_images(), F=F_AFFINE)
    seg = picker.epipolar_line(0, (12.3, 17.0))
    np.testing.assert_allclose(seg[:, 1], [17.0, 17.0])
    np.testing.assert_allclose(sorted(seg[:, 0]), [-0.5, W - 0.5])
    seg = picker.epipolar_line(1, (3.0, 41.5))  # other direction uses Fᵀ
    np.testing.assert_allclose(seg[:, 1], [41.5, 41.5])
    assert picker.epipolar_line(0, (5.0, 70.0)) is None  # y = 70 is below the image

    # a general affine F (H&Z 2nd ed. sec. 14.2), not (anti)symmetric: both directions
    # give end points on the image border that satisfy x1ᵀ F x0 = 0
    F = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, -1.0], [-0.05, 1.0, 3.0]])
    picker = CorrespondencePicker(_images(), F=F)
    x0, x1 = np.array([40.0, 25.0]), np.array([30.0, 20.0])
    for view_from, xy in ((0, x0), (1, x1)):
        seg = picker.epipolar_line(view_from, xy)
        assert seg is not None and np.linalg.norm(seg[0] - seg[1]) > 10
        for p in seg:
            a, b = (xy, p) if view_from == 0 else (p, xy)  # a in view 0, b in view 1
            assert abs(np.r_[b, 1] @ F @ np.r_[a, 1]) < 1e-9
            assert (np.isclose(p[0], -0.5) or np.isclose(p[0], W - 0.5)
                    or np.isclose(p[1], -0.5) or np.isclose(p[1], H - 0.5))


def test_clip_line_to_image():
    seg = clip_line_to_image([1.0, -1.0, 0.0], (10, 10))  # y = x, the diagonal
    np.testing.assert_allclose(sorted(seg[:, 0]), [-0.5, 9.5])
    np.testing.assert_allclose(seg[:, 0], seg[:, 1])
    assert clip_line_to_image([0.0, 0.0, 1.0], (10, 10)) is None


def test_epipolar_errors():
    picker = CorrespondencePicker(_images(3))
    with pytest.raises(GeometryError, match="F="):
        picker.epipolar_line(0, (1, 1), 1)
    picker = CorrespondencePicker(_images(3), F={(0, 1): F_AFFINE})
    with pytest.raises(GeometryError, match="view_to"):
        picker.epipolar_line(0, (1, 1))
    with pytest.raises(GeometryError, match="views 0 and 2"):
        picker.epipolar_line(0, (1, 1), 2)
    np.testing.assert_allclose(picker.epipolar_line(1, (3, 7), 0)[:, 1], [7, 7])
    with pytest.raises(GeometryError, match="3x3"):
        CorrespondencePicker(_images(), F=np.eye(2))


def test_default_proposal_same_position_then_median_offset_then_epipolar(no_matching):
    picker = CorrespondencePicker(_images())
    picker.add(0, (20.0, 30.0))
    np.testing.assert_allclose(picker.pts[0, 1], [20, 30])  # nothing known: same pixel
    picker.add(1, (25.0, 28.0))  # the true match: offset (+5, -2)
    picker.add(0, (40.0, 10.0))
    np.testing.assert_allclose(picker.pts[1, 1], [45, 8])  # median offset of picked points
    picker.accept()
    # with F the guess is moved onto the epipolar line y1 = y0
    picker.F = {(0, 1): F_AFFINE}
    picker.add(0, (60.0, 50.0))
    np.testing.assert_allclose(picker.pts[2, 1], [65, 50])
    # a proposal near the border is clipped into the image
    picker.cancel()
    picker.add(0, (79.0, 1.0))
    np.testing.assert_allclose(picker.pts[-1, 1], [W - 0.5, 1.0])


def test_default_proposal_uses_matching_refine_when_meaningful(monkeypatch):
    calls = []

    def refine_correspondences(images, pts, ref_view=0):
        calls.append((pts.copy(), ref_view))
        out = pts.copy()
        out[:, 1 - ref_view] += shift
        return out

    fake = types.ModuleType("semlab.matching")
    fake.refine_correspondences = refine_correspondences
    monkeypatch.setitem(sys.modules, "semlab.matching", fake)
    monkeypatch.setattr(semlab, "matching", fake, raising=False)

    shift = np.array([1.5, -0.5])
    picker = CorrespondencePicker(_images())
    picker.add(0, (20.0, 30.0))
    np.testing.assert_allclose(picker.pts[0, 1], [21.5, 29.5])
    guess, ref_view = calls[0]
    assert ref_view == 0 and np.all(np.isfinite(guess))  # the guess, not NaN, is refined
    np.testing.assert_allclose(guess[0, 1], [20, 30])
    picker.cancel()
    shift = np.array([50.0, 0.0])  # too far from the guess: not meaningful, ignored
    picker.add(0, (20.0, 30.0))
    np.testing.assert_allclose(picker.pts[0, 1], [20, 30])


def test_injected_refine_is_used(no_matching):
    calls = []

    def refine(images, pts, ref_view):
        calls.append((len(images), pts.copy(), ref_view))
        out = pts.copy()
        for k in range(pts.shape[1]):
            if np.isnan(out[0, k]).any():
                out[0, k] = pts[0, ref_view] + [3.0, -2.0]
        return out

    picker = CorrespondencePicker(_images(3), refine=refine)
    picker.add(1, (10.0, 20.0))
    n_images, pts, ref_view = calls[-1]
    assert n_images == 3 and ref_view == 1 and pts.shape == (1, 3, 2)
    assert np.isnan(pts[0, 0]).all() and np.isnan(pts[0, 2]).all()
    np.testing.assert_allclose(pts[0, 1], [10, 20])
    np.testing.assert_allclose(picker.pts[0], [[13, 18], [10, 20], [13, 18]])
    # a second view clicked: refine is asked again, from that view, for the last one
    picker.add(2, (12.0, 19.0))
    n_images, pts, ref_view = calls[-1]
    assert ref_view == 2 and np.isnan(pts[0, 0]).all() and not np.isnan(pts[0, 2]).any()
    picker.accept()
    assert picker.complete().tolist() == [True]

    # a refine that answers outside the image falls back to the same pixel position
    picker = CorrespondencePicker(_images(), refine=lambda im, p, r: np.full_like(p, 1e6))
    picker.add(0, (5.0, 6.0))
    np.testing.assert_allclose(picker.pts[0, 1], [5, 6])
    with pytest.raises(GeometryError, match="shape"):
        CorrespondencePicker(_images(), refine=lambda im, p, r: p[0]).add(0, (1.0, 1.0))


def test_multiple_undo_and_state_errors(no_matching):
    picker = CorrespondencePicker(_images())
    picker.add(0, (10.0, 10.0))
    picker.add(1, (12.0, 10.0))
    picker.add(0, (30.0, 30.0))
    picker.accept()
    picker.move(0, 0, (11.0, 11.0))
    assert picker.n_points == 2
    assert picker.undo() and picker.pts[0, 0].tolist() == [10.0, 10.0]
    assert picker.undo() and picker.current == 1  # accept undone
    assert picker.undo() and picker.n_points == 1
    assert picker.undo() and picker.current == 0 and not picker.confirmed[0, 1]
    assert picker.undo() and picker.n_points == 0
    assert not picker.undo()

    with pytest.raises(GeometryError, match="outside"):
        picker.add(0, (W + 3.0, 1.0))
    with pytest.raises(GeometryError, match="view"):
        picker.add(2, (1.0, 1.0))
    assert picker.accept() is None and picker.delete() is None
    picker.add(0, (1.0, 1.0))
    picker.pts[0, 1] = np.nan
    with pytest.raises(GeometryError, match="view"):
        picker.accept()
    with pytest.raises(ImageError, match="at least 2"):
        CorrespondencePicker(_images(1))
    with pytest.raises(GeometryError, match="shape"):
        CorrespondencePicker(_images(), pts=np.zeros((3, 3, 2)))


def test_table_and_to_correspondences(no_matching):
    picker = CorrespondencePicker(_images())
    picker.add(0, (10.0, 10.0))
    picker.add(1, (12.0, 11.0))
    picker.add(0, (30.0, 30.0))
    rows = picker.table()
    assert [r["status"] for r in rows] == ["picked", "picking"]
    assert rows[0] == {"point_id": 0, "x0_px": 10.0, "y0_px": 10.0, "x1_px": 12.0,
                       "y1_px": 11.0, "crack_id": None, "status": "picked"}
    corr = picker.to_correspondences()
    assert corr.point_id.tolist() == [0] and corr.crack_id is None  # current not included
    picker.accept()
    picker.set_crack(1, 4)
    corr = picker.to_correspondences()
    assert corr.point_id.tolist() == [0, 1] and corr.crack_id.tolist() == [-1, 4]


def test_save_load_round_trip_and_select(tmp_path, no_matching):
    picker = CorrespondencePicker(_images())
    for x in (10.0, 30.0, 50.0):
        picker.add(0, (x, 20.0))
        picker.add(1, (x + 2, 21.0))
    picker.delete(1)
    path = tmp_path / "c.csv"
    picker.save(path)
    other = CorrespondencePicker(_images())
    corr = other.load(path)
    assert corr.point_id.tolist() == [0, 2]
    np.testing.assert_allclose(other.pts, picker.pts)
    assert other.select_nearest(1, (51.0, 22.0), 3.0) == 1
    assert other.select_nearest(1, (51.0, 40.0), 3.0) is None
    other.add(0, (70.0, 5.0))
    assert other.point_id[-1] == 3  # new ids never reuse an existing one
    # a file for the wrong number of views is refused
    three = CorrespondencePicker(_images(3))
    with pytest.raises(semlab.errors.ExperimentError, match="3 view"):
        three.load(path)


# --------------------------------------------------------------------------- widget panels

def test_picker_widget_buttons_save_with_backup(tmp_path, no_matching):
    path = tmp_path / "correspondences.csv"
    first = CorrespondencePicker(_images())
    first.add(0, (10.0, 10.0))
    first.add(1, (11.0, 10.0))
    first.save(path)

    box = picker_widget(_images(), path, F=F_AFFINE)
    picker, view = box.picker, box.figure
    assert picker.n_points == 1  # the existing file was loaded
    click(view.fig, view.axes[0], (40.0, 25.0))
    box.buttons["Accept"].click()
    assert picker.current is None and picker.n_points == 2
    table_html = box.children[-1].value
    assert "<td>1</td>" in table_html and "40.00" in table_html
    box.buttons["Save"].click()
    status = box.children[1].value
    assert "correspondences.bak.csv" in status and "saved 2 point(s)" in status
    assert read_correspondences(tmp_path / "correspondences.bak.csv").n_points == 1
    assert read_correspondences(path).n_points == 2
    picker.selected = 0
    box.buttons["Delete"].click()
    assert picker.point_id.tolist() == [1]
    box.buttons["Undo"].click()
    assert picker.point_id.tolist() == [0, 1]


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

    from semlab.widgets import _ScreenImage

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


def test_click_proposal_matches_in_windows_like_on_whole_views():
    """The default proposal (real sub-pixel matching) is computed in windows around the
    guesses; it finds a known shift and agrees with matching on the whole views."""
    from scipy import ndimage

    rng = np.random.default_rng(7)
    a = ndimage.gaussian_filter(rng.random((300, 420)), 2.0)
    b = ndimage.shift(a, (-1.7, 3.3), order=3, mode="reflect")    # (rows, cols)
    picker = CorrespondencePicker([a, b])
    picker.add(0, (150.0, 120.0))
    windowed = picker.pts[0, 1].copy()
    np.testing.assert_allclose(windowed, [153.3, 118.3], atol=0.02)
    whole = CorrespondencePicker([a, b])
    whole.refine_window_px = 10_000
    whole.add(0, (150.0, 120.0))
    np.testing.assert_allclose(windowed, whole.pts[0, 1], atol=2e-3)
    # near the image corner the window is shifted inside the image, not cut
    picker.cancel()
    picker.add(0, (18.0, 16.0))
    np.testing.assert_allclose(picker.pts[0, 1], [21.3, 14.3], atol=0.05)
