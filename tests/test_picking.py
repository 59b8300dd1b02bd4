"""The picking state without any canvas: proposals, refinement passed in, undo, unsaved
changes, autosave, bulk review of automatic points, file permissions on save."""

import os
import stat

import numpy as np
import pytest

import semlab
from semlab.errors import ExperimentError, GeometryError, ImageError
from semlab.picking import (AUTO_ACCEPTED, AUTO_PENDING, AUTO_REJECTED, CorrespondencePicker,
                            autosave_path, read_autosave, write_autosave)
from semlab.proposals import (WindowedRefine, clip_line_to_image, fundamental_from_points,
                              matching_refine)

H, W = 60, 80
F_AFFINE = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # x1ᵀ F x0 = 0  <=>  y1 = y0


def _images(n=2, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.random((H, W)) for _ in range(n)]


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


def test_default_proposal_same_position_then_median_offset_then_epipolar():
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


def test_multiple_undo_and_state_errors():
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


def test_table_and_to_correspondences():
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


def test_save_load_round_trip_and_select(tmp_path):
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


def test_injected_refine_gets_the_guess_and_is_bounded():
    calls = []

    def refine(images, guess, ref_view):
        calls.append((len(images), guess.copy(), ref_view))
        out = guess.copy()
        for k in range(guess.shape[1]):
            if k != ref_view:
                out[0, k] = guess[0, k] + [3.0, -2.0]
        return out

    picker = CorrespondencePicker(_images(3), refine=refine)
    picker.add(1, (10.0, 20.0))
    n_images, guess, ref_view = calls[-1]
    assert n_images == 3 and ref_view == 1 and guess.shape == (1, 3, 2)
    np.testing.assert_allclose(guess[0], [[10, 20]] * 3)  # nothing picked: same position
    np.testing.assert_allclose(picker.pts[0], [[13, 18], [10, 20], [13, 18]])
    # a second view clicked: refine is asked again from that view; the clicked views stay
    picker.add(2, (12.0, 19.0))
    _, guess, ref_view = calls[-1]
    assert ref_view == 2
    np.testing.assert_allclose(picker.pts[0], [[15, 17], [10, 20], [12, 19]])
    picker.accept()
    assert picker.complete().tolist() == [True]

    # answers outside the image or farther than max_refine_shift_px from the guess are not
    # used: the proposal is the guess
    for bad in (1e6, 25.0):
        picker = CorrespondencePicker(_images(), refine=lambda im, g, r, b=bad: g + b)
        picker.add(0, (5.0, 6.0))
        np.testing.assert_allclose(picker.pts[0, 1], [5, 6])
    with pytest.raises(GeometryError, match="shape"):
        CorrespondencePicker(_images(), refine=lambda im, g, r: g[0]).add(0, (1.0, 1.0))
    with pytest.raises(TypeError, match="callable"):
        CorrespondencePicker(_images(), refine="matching")


def test_refine_errors_are_kept_not_swallowed():
    """A SemlabError of the refinement falls back to the guess and is kept; any other error
    (a bug, a wrong signature) propagates."""
    def failing(images, guess, ref_view):
        raise GeometryError("texture too weak")

    picker = CorrespondencePicker(_images(), refine=failing)
    picker.add(0, (20.0, 30.0))
    np.testing.assert_allclose(picker.pts[0, 1], [20, 30])
    assert "texture" in str(picker.last_refine_error)

    picker = CorrespondencePicker(_images(), refine=lambda images, guess: guess)
    with pytest.raises(TypeError):
        picker.add(0, (20.0, 30.0))


def test_windowed_refine_passes_windows_and_shifts_back():
    seen = []

    def match(crops, guess, ref_view):
        seen.append(([c.shape for c in crops], guess.copy(), ref_view))
        out = guess.copy()
        out[0, 1] += [0.25, -0.5]
        return out

    imgs = [np.zeros((200, 300)), np.zeros((200, 300))]
    refine = WindowedRefine(match, window_px=10)
    guess = np.array([[[150.0, 100.0], [5.0, 195.0]]])
    out = refine(imgs, guess, 0)
    shapes, g, ref = seen[0]
    assert shapes == [(21, 21), (21, 21)] and ref == 0
    np.testing.assert_allclose(g[0], [[10, 10], [5, 16]])  # view 1: window shifted inside
    np.testing.assert_allclose(out[0], [[150, 100], [5.25, 194.5]])


def test_matching_refine_finds_a_known_shift_like_on_whole_views():
    """The widget's refinement (real sub-pixel matching) in windows around the guesses finds
    a known shift and agrees with matching on the whole views."""
    from scipy import ndimage

    rng = np.random.default_rng(7)
    a = ndimage.gaussian_filter(rng.random((300, 420)), 2.0)
    b = ndimage.shift(a, (-1.7, 3.3), order=3, mode="reflect")    # (rows, cols)
    picker = CorrespondencePicker([a, b], refine=matching_refine())
    picker.add(0, (150.0, 120.0))
    windowed = picker.pts[0, 1].copy()
    np.testing.assert_allclose(windowed, [153.3, 118.3], atol=0.02)
    whole = CorrespondencePicker([a, b], refine=matching_refine(window_px=10_000))
    whole.add(0, (150.0, 120.0))
    np.testing.assert_allclose(windowed, whole.pts[0, 1], atol=2e-3)
    # near the image corner the window is shifted inside the image, not cut
    picker.cancel()
    picker.add(0, (18.0, 16.0))
    np.testing.assert_allclose(picker.pts[0, 1], [21.3, 14.3], atol=0.05)


def test_fundamental_from_points():
    rng = np.random.default_rng(1)
    x0 = rng.uniform(0, 70, (6, 2))
    z = rng.uniform(-3, 3, 6)
    x1 = np.column_stack([x0[:, 0] * 0.99 + 0.1 * z, x0[:, 1]])   # parallax along x
    F, why = fundamental_from_points(np.stack([x0, x1], axis=1))
    assert why == "" and set(F) == {(0, 1)}
    r = np.einsum("ni,ij,nj->n", np.c_[x1, np.ones(6)], F[(0, 1)], np.c_[x0, np.ones(6)])
    assert np.abs(r).max() < 1e-9
    F, why = fundamental_from_points(np.stack([x0, x1], axis=1)[:3])
    assert F is None and "3 complete" in why


def test_status_says_the_next_step():
    picker = CorrespondencePicker(_images(), titles=["view_0", "view_1"])
    assert picker.status() == "click a feature in any view to start point 0"
    picker.add(0, (10.0, 10.0))
    assert picker.status().startswith("point 0: check the × in view_1 — click it or press a")
    picker.accept()
    assert picker.status().startswith("point 0 selected")
    assert "start point 1" in picker.status()


def test_unsaved_changes_count_against_the_saved_file(tmp_path):
    path = tmp_path / "c.csv"
    picker = CorrespondencePicker(_images())
    assert picker.unsaved_changes() == 0
    picker.add(0, (10.0, 10.0))
    assert picker.unsaved_changes() == 0          # the point being picked is not saved yet
    picker.accept()
    picker.add(0, (30.0, 20.0))
    picker.add(1, (31.0, 20.0))
    assert picker.unsaved_changes() == 2
    picker.save(path)
    assert picker.unsaved_changes() == 0
    picker.move(0, 1, (12.0, 10.5))
    picker.delete(1)
    assert picker.unsaved_changes() == 2          # one moved, one deleted
    picker.undo()
    picker.undo()
    assert picker.unsaved_changes() == 0          # undone back to what is on disk
    picker.undo()                                 # before the save: the second point unmade
    assert picker.unsaved_changes() == 1
    other = CorrespondencePicker(_images())
    other.load(path)
    assert other.unsaved_changes() == 0


def test_autosave_round_trip_restores_the_session(tmp_path):
    path = tmp_path / "correspondences.csv"
    picker = CorrespondencePicker(_images())
    picker.add(0, (10.0, 10.0))
    picker.add(1, (12.0, 11.0))
    picker.save(path)
    picker.add(0, (40.0, 30.0))
    picker.accept()
    picker.add(0, (60.0, 5.0))                    # still being picked
    side = write_autosave(picker, path)
    assert side == autosave_path(path) == tmp_path / "correspondences.autosave.json"

    again = CorrespondencePicker(_images())
    again.load(path)
    again.restore_state(read_autosave(path))
    np.testing.assert_allclose(again.pts, picker.pts)
    np.testing.assert_array_equal(again.confirmed, picker.confirmed)
    assert again.current == 2 and again.unsaved_changes() == 1
    assert again.undo() and again.n_points == 1   # the restore is undoable
    # an autosave of other views is refused with the file named
    bigger = CorrespondencePicker([np.zeros((H + 1, W))] * 2)
    with pytest.raises(ExperimentError, match="sizes differ"):
        bigger.restore_state(read_autosave(path), source=str(side))
    side.write_text("{not json")
    with pytest.raises(ExperimentError, match="autosave.json"):
        read_autosave(path)
    assert read_autosave(tmp_path / "none.csv") is None


def test_bulk_review_of_automatic_points():
    picker = CorrespondencePicker(_images())
    picker.add(0, (5.0, 5.0))
    picker.add(1, (6.0, 5.0))
    auto = np.array([[[10.0, 10.0], [11.0, 10.0]], [[20.0, 40.0], [21.0, 40.0]],
                     [[60.0, 40.0], [61.0, 40.0]], [[70.0, 50.0], [np.nan, 50.0]]])
    picker.set_auto(auto, sigma_px=[0.02, 0.3, 0.05, 0.01])
    assert len(picker.auto_pts) == 3              # the one with NaN is left out
    # accept the ones in the left half of view 0
    assert picker.review_region(0, (-0.5, 40.0), (-0.5, 59.5), accept=True) == 2
    assert picker.n_points == 3 and picker.point_id.tolist() == [0, 1, 2]
    np.testing.assert_allclose(picker.pts[1:], auto[:2])
    assert picker.unsaved_changes() == 3          # the clicked point and the two accepted
    assert picker.review_region(0, (-0.5, 40.0), (-0.5, 59.5), accept=False) == 0  # done
    # reject by sigma: the last one has 0.05 px
    assert picker.review_sigma(0.04) == (1, 0)
    assert picker.auto_state.tolist() == [AUTO_ACCEPTED, AUTO_ACCEPTED, AUTO_REJECTED]
    assert picker.auto_counts() == {"pending": 0, "accepted": 2, "rejected": 1}
    # deleting an accepted automatic point marks it rejected; undo brings both back
    picker.delete(2)
    assert picker.auto_state.tolist()[1] == AUTO_REJECTED
    picker.undo()
    assert picker.n_points == 3 and picker.auto_state.tolist()[1] == AUTO_ACCEPTED
    picker.undo()
    assert picker.auto_state.tolist()[2] == AUTO_PENDING
    with pytest.raises(GeometryError, match="shape"):
        picker.set_auto(np.zeros((3, 3, 2)))


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_save_keeps_the_file_mode_and_new_files_get_the_umask(tmp_path):
    path = tmp_path / "correspondences.csv"
    picker = CorrespondencePicker(_images())
    picker.add(0, (10.0, 10.0))
    picker.add(1, (12.0, 11.0))
    old = os.umask(0o027)
    try:
        picker.save(path)                         # a new file: 0o666 & ~umask
        assert stat.S_IMODE(path.stat().st_mode) == 0o640
        os.chmod(path, 0o664)                     # shared with the group
        picker.add(0, (30.0, 10.0))
        picker.add(1, (31.0, 10.0))
        bak = picker.save(path)
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o664
    assert stat.S_IMODE(bak.stat().st_mode) == 0o664
    assert path.stat().st_uid == os.getuid()
