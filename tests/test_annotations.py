"""The correspondences CSV format: round trip, backups, and every validation error."""

import csv

import numpy as np
import pytest

from semlab.annotations import (Correspondences, backup_path, correspondence_columns,
                                read_correspondences, write_correspondences)
from semlab.errors import ExperimentError


def _write(path, text):
    path.write_text(text, encoding="utf-8")
    return path


def _random_corr(rng, n=7, v=3, crack=True):
    pts = rng.uniform(0, 90, (n, v, 2))
    ids = rng.permutation(100)[:n]
    cracks = rng.integers(-1, 3, n) if crack else None
    return Correspondences(ids, pts, cracks)


@pytest.mark.parametrize("v,crack", [(2, False), (3, True)])
def test_round_trip(tmp_path, v, crack):
    rng = np.random.default_rng(v)
    corr = _random_corr(rng, v=v, crack=crack)
    path = tmp_path / "c.csv"
    assert write_correspondences(path, corr) is None
    back = read_correspondences(path, n_views=v, image_shapes=[(100, 100)] * v)
    np.testing.assert_array_equal(back.point_id, corr.point_id)
    np.testing.assert_allclose(back.pts, corr.pts, atol=5e-5)
    assert back.pts.shape == (7, v, 2) and back.n_views == v and len(back) == 7
    if crack:
        np.testing.assert_array_equal(back.crack_id, corr.crack_id)
    else:
        assert back.crack_id is None
    assert back.path == path
    header = path.read_text().splitlines()[0].split(",")
    assert header == correspondence_columns(v, crack_id=crack)


def test_write_accepts_arrays_and_tuples(tmp_path):
    pts = np.arange(12, dtype=float).reshape(3, 2, 2)
    write_correspondences(tmp_path / "a.csv", pts)
    a = read_correspondences(tmp_path / "a.csv")
    np.testing.assert_array_equal(a.point_id, [0, 1, 2])
    np.testing.assert_allclose(a.pts, pts)
    write_correspondences(tmp_path / "b.csv", ([5, 9, 7], pts, [-1, 2, -1]))
    b = read_correspondences(tmp_path / "b.csv", n_views=2)
    np.testing.assert_array_equal(b.point_id, [5, 9, 7])
    np.testing.assert_array_equal(b.crack_id, [-1, 2, -1])
    rows = list(csv.DictReader((tmp_path / "b.csv").read_text().splitlines()))
    assert rows[0]["crack_id"] == "" and rows[1]["crack_id"] == "2"


def test_backups_never_overwrite(tmp_path):
    path = tmp_path / "correspondences.csv"
    versions = [np.full((1, 2, 2), float(k)) for k in range(4)]
    baks = [write_correspondences(path, p) for p in versions]
    assert baks[0] is None
    assert [b.name for b in baks[1:]] == ["correspondences.bak.csv", "correspondences.bak1.csv",
                                          "correspondences.bak2.csv"]
    # each backup holds the version it replaced, the file the last one
    for k, bak in enumerate(baks[1:]):
        assert read_correspondences(bak).pts[0, 0, 0] == k
    assert read_correspondences(path).pts[0, 0, 0] == 3
    assert backup_path(path).name == "correspondences.bak3.csv"
    assert write_correspondences(path, versions[0], backup=False) is None
    assert not (tmp_path / "correspondences.bak3.csv").exists()


def test_extra_columns_blank_lines_and_empty_file_ok(tmp_path):
    p = _write(tmp_path / "c.csv", "point_id,x0_px,y0_px,x1_px,y1_px,note\n"
                                   "3,1.5,2,3,4,hello\n\n4, 5 ,6,7,8,\n")
    c = read_correspondences(p, n_views=2)
    np.testing.assert_array_equal(c.point_id, [3, 4])
    np.testing.assert_allclose(c.pts[1], [[5, 6], [7, 8]])
    p2 = _write(tmp_path / "h.csv", "point_id,x0_px,y0_px,x1_px,y1_px\n")
    assert read_correspondences(p2, n_views=2).pts.shape == (0, 2, 2)


def test_image_border_is_inclusive_half_pixel(tmp_path):
    p = _write(tmp_path / "c.csv", "point_id,x0_px,y0_px,x1_px,y1_px\n0,-0.5,-0.5,79.5,59.5\n")
    read_correspondences(p, image_shapes=[(60, 80), (60, 80)])
    p = _write(tmp_path / "d.csv", "point_id,x0_px,y0_px,x1_px,y1_px\n0,1,1,79.6,59\n")
    with pytest.raises(ExperimentError, match="outside"):
        read_correspondences(p, image_shapes=[(60, 80), (60, 80)])


HEAD = "point_id,x0_px,y0_px,x1_px,y1_px\n"


@pytest.mark.parametrize("text,kwargs,patterns", [
    # missing column: names it and the full expected header
    ("point_id,x0_px,y0_px,x1_px\n0,1,2,3\n", {},
     ["y1_px", "point_id,x0_px,y0_px,x1_px,y1_px"]),
    ("x0_px,y0_px,x1_px,y1_px\n1,2,3,4\n", {"n_views": 2}, ["point_id"]),
    # fewer view pairs than the experiment has
    (HEAD + "0,1,2,3,4\n", {"n_views": 3}, ["x2_px, y2_px", "3 view"]),
    # more view pairs than the experiment has
    ("point_id,x0_px,y0_px,x1_px,y1_px,x2_px,y2_px\n0,1,2,3,4,5,6\n", {"n_views": 2},
     ["3 view column pair", "2 view"]),
    (HEAD + "0,1,2,3,4\n1,1,abc,3,4\n", {}, ["line 3", "'y0_px'", "'abc'", "not a number"]),
    (HEAD + "0,1,2,3,4\n1,1,2,,4\n", {}, ["line 3", "point_id 1", "'x1_px'", "empty",
                                          "view 1"]),
    (HEAD + "0,1,2,3,nan\n", {}, ["line 2", "'y1_px'", "view 1"]),
    (HEAD + "0,1,2,3,inf\n", {}, ["line 2", "'y1_px'"]),
    (HEAD + "a,1,2,3,4\n", {}, ["line 2", "point_id", "not an integer"]),
    (HEAD + "1.5,1,2,3,4\n", {}, ["line 2", "point_id", "not an integer"]),
    (HEAD + "7,1,2,3,4\n8,1,2,3,4\n7,5,6,7,8\n", {}, ["point_id 7", "line 4", "line 2"]),
    (HEAD + "0,1,2,3,4\n5,1,2,300,4\n", {"image_shapes": [(50, 100), (50, 100)]},
     ["point_id 5", "view 1", "outside", "100x50"]),
    (HEAD + "0,1,2,3,4\n", {"image_shapes": [(50, 100)]}, ["1 image shape", "2 view"]),
    (HEAD.rstrip() + ",crack_id\n0,1,2,3,4,x\n", {}, ["crack_id", "not an integer"]),
    (HEAD.rstrip() + ",crack_id\n0,1,2,3,4,-2\n", {}, ["crack_id", ">= 0"]),
    ("point_id;x0_px;y0_px;x1_px;y1_px\n0;1;2;3;4\n", {}, ["';'", "comma"]),
    (HEAD + "0,1,2,3,4,5\n", {}, ["line 2", "extra"]),
    ("point_id,x0_px,x0_px,y0_px\n", {}, ["x0_px", "more than once"]),
    ("\n\n", {}, ["empty", "header"]),
])
def test_read_errors_name_file_place_and_fix(tmp_path, text, kwargs, patterns):
    p = _write(tmp_path / "bad.csv", text)
    with pytest.raises(ExperimentError) as info:
        read_correspondences(p, **kwargs)
    msg = str(info.value)
    assert str(p) in msg
    for pat in patterns:
        assert pat in msg, (pat, msg)


def test_missing_file(tmp_path):
    with pytest.raises(ExperimentError, match="not found"):
        read_correspondences(tmp_path / "nope.csv")


@pytest.mark.parametrize("data,pattern", [
    (np.zeros((3, 2)), "shape"),
    (np.array([[[np.nan, 1.0], [2.0, 3.0]]]), "NaN"),
    (([1, 1], np.zeros((2, 2, 2))), "more than once"),
    (([1, 2, 3], np.zeros((2, 2, 2))), "point_id must have shape"),
    (([1.5, 2], np.zeros((2, 2, 2))), "integers"),
    (([1, 2], np.zeros((2, 2, 2)), [0]), "crack_id must have shape"),
])
def test_write_errors(tmp_path, data, pattern):
    path = tmp_path / "c.csv"
    with pytest.raises(ExperimentError, match=pattern):
        write_correspondences(path, data)
    assert not path.exists()
