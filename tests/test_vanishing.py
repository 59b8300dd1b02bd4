"""Vanishing-point calibration on a synthetic perspective camera viewing a gridded box."""

import json

import numpy as np
import pytest

from semlab import vanishing as vn
from semlab.camera import project_perspective, rotation_about_axis
from semlab.errors import GeometryError, SemlabError

K_TRUE = np.array([[2000.0, 0.0, 1010.0], [0.0, 2000.0, 770.0], [0.0, 0.0, 1.0]])
R0 = rotation_about_axis([1, 0, 0], np.deg2rad(-30)) @ rotation_about_axis([0, 1, 0], np.deg2rad(40))
RY10 = rotation_about_axis([0, 1, 0], np.deg2rad(10))
CENTRE = np.array([0.5, 0.5, 0.5])


def camera(R, dist=2.5):
    """Camera looking at the unit box's centre from ``dist`` with world-to-camera rotation R."""
    return R, np.array([0.0, 0.0, dist]) - R @ CENTRE


def box_families(R, t, K=K_TRUE, n=11, noise_px=0.0, rng=None):
    """Grid lines on the three faces x=0, y=0, z=0 of the unit box, grouped by 3D direction."""
    fams = {"x": [], "y": [], "z": []}
    for face in range(3):
        a, b = [i for i in range(3) if i != face]
        for along, across in ((a, b), (b, a)):
            for s in np.linspace(0, 1, n)[1:]:
                p = np.zeros(3)
                p[across] = s
                q = p.copy()
                q[along] = 1.0
                fams["xyz"[along]].append((p, q))
    out = {}
    for name, segs in fams.items():
        P = np.array([p for p, _ in segs])
        Q = np.array([q for _, q in segs])
        S = np.hstack([project_perspective(P, K, R, t), project_perspective(Q, K, R, t)])
        if noise_px:
            S = S + rng.normal(0.0, noise_px, S.shape)
        out[name] = S
    return out


def same_up_to_axis_signs(R_est, R_true, tol):
    """R_est = R_true @ diag(s), s in {±1}³ with det +1 (a vp fixes an axis only up to sign)."""
    D = R_true.T @ R_est
    return np.allclose(np.abs(D), np.eye(3), atol=tol) and np.linalg.det(D) > 0


# ----------------------------------------------------------------------------- vanishing points

def test_vanishing_point_noise_free_is_the_true_direction():
    R, t = camera(R0)
    fams = box_families(R, t)
    for i, name in enumerate("xyz"):
        vp, res = vn.vanishing_point(fams[name])
        true = K_TRUE @ R[:, i]
        assert abs(abs(vp @ true) / np.linalg.norm(true) - 1) < 1e-12
        assert res.shape == (len(fams[name]),) and res.max() < 1e-6


def test_vanishing_point_at_infinity_is_legal():
    segs = np.array([[0, 0, 100, 0], [0, 10, 100, 10], [5, 30, 80, 30.0]])
    vp, res = vn.vanishing_point(segs)
    assert abs(vp[2]) < 1e-12 and abs(abs(vp[0]) - 1) < 1e-12
    assert res.max() < 1e-9


def test_vanishing_point_residuals_measure_click_error():
    segs = np.array([[0, y, 100, y] for y in np.arange(9) * 25.0])
    segs[4, 1] += 2.0  # tilt one segment: its end points are ~1 px off the line to the vp
    for refine in (False, True):
        _, res = vn.vanishing_point(segs, refine=refine)
        assert res.argmax() == 4 and 0.6 < res[4] < 1.01
        assert np.delete(res, 4).max() < 0.5 * res[4]


@pytest.mark.parametrize("segs, match", [
    ([[0, 0, 10, 10]], "at least 2"),
    ([[0, 0, 10, 10], [3, 3, 3, 3]], "zero length"),
    ([[0, 0, 10, 10], [np.nan, 0, 1, 1]], "NaN"),
    ([[0, 0, 10, 10], [20, 20, 30, 30]], "one image line"),
])
def test_vanishing_point_errors(segs, match):
    with pytest.raises(GeometryError, match=match):
        vn.vanishing_point(np.array(segs, float))


# ----------------------------------------------------------------------------- K and R

def test_noise_free_recovers_K_and_R():
    R, t = camera(R0)
    cal = vn.calibrate_views([box_families(R, t)])
    assert np.abs(cal.K - K_TRUE).max() < 1e-8 * K_TRUE[0, 0]
    assert same_up_to_axis_signs(cal.R[0], R, 1e-8)
    assert np.allclose(cal.R[0] @ cal.R[0].T, np.eye(3), atol=1e-12)
    assert cal.focal_px == pytest.approx(2000.0, rel=1e-10)


def test_known_principal_point_gives_f():
    R, t = camera(R0)
    K = vn.calibrate_k(np.array([vn.vanishing_point(v)[0] for v in box_families(R, t).values()]),
                       principal_point=(1010.0, 770.0))
    assert K[0, 0] == pytest.approx(2000.0, rel=1e-10) and K[1, 1] == K[0, 0]


def test_two_views_relative_rotation_noise_free():
    Ra, ta = camera(R0)
    Rb, tb = camera(RY10 @ R0)
    cal = vn.calibrate_views([box_families(Ra, ta), box_families(Rb, tb)])
    assert np.abs(cal.K - K_TRUE).max() < 1e-6
    assert cal.angle_deg[0] == pytest.approx(0.0, abs=1e-8)
    assert cal.angle_deg[1] == pytest.approx(10.0, abs=1e-8)
    assert abs(abs(cal.axis[1] @ [0, 1, 0]) - 1) < 1e-10
    assert np.allclose(cal.euler_zyx_deg[1], [0.0, 10.0, 0.0], atol=1e-8)
    # the view-1 axes carry the same signs as view 0: R1 R0ᵀ is the true relative rotation
    assert np.allclose(cal.relative_R[1], RY10, atol=1e-10)


def test_one_px_noise_accuracy():
    rng = np.random.default_rng(0)
    Ra, ta = camera(R0)
    Rb, tb = camera(RY10 @ R0)
    cal = vn.calibrate_views([box_families(Ra, ta, noise_px=1.0, rng=rng),
                              box_families(Rb, tb, noise_px=1.0, rng=rng)])
    assert abs(cal.focal_px / 2000.0 - 1) < 0.02
    err_deg = vn.axis_angle(cal.relative_R[1] @ RY10.T)[1]
    assert err_deg < 0.5
    res = np.concatenate([r for v in cal.residuals_px for r in v.values()])
    assert 0.3 < np.median(res) < 2.0  # residuals report the 1 px click noise


def test_joint_refinement_beats_the_linear_calibration():
    """Over 12 noisy trials the joint ML refinement of K and R has a smaller relative
    rotation error than the linear calibration, and a consistent model: each view's
    vanishing points are K times the columns of its R."""
    lin, ref = [], []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        Ra, ta = camera(R0)
        Rb, tb = camera(RY10 @ R0)
        views = [box_families(Ra, ta, noise_px=1.0, rng=rng),
                 box_families(Rb, tb, noise_px=1.0, rng=rng)]
        for refine, out in ((False, lin), (True, ref)):
            cal = vn.calibrate_views(views, refine=refine)
            out.append(vn.axis_angle(cal.relative_R[1] @ RY10.T)[1])
        for v in range(2):
            for k in range(3):
                d = np.linalg.solve(cal.K, cal.vps[v][k])
                assert abs(abs(d @ cal.R[v][:, k]) / np.linalg.norm(d) - 1) < 1e-9
    assert np.mean(ref) < 0.8 * np.mean(lin)


def test_parallel_families_raise():
    R, t = camera(R0)
    fams = box_families(R, t)
    # "y" edges actually clicked along a direction 0.6° from x
    bad = rotation_about_axis([0, 0, 1], np.deg2rad(0.6))
    fams["y"] = box_families(R @ bad, t)["x"]
    with pytest.raises(GeometryError, match="nearly parallel in 3D"):
        vn.calibrate_views([fams])


def test_two_vps_at_infinity_raise():
    vps = np.array([[1.0, 0, 0], [0, 1.0, 0], [1000.0, 700.0, 1.0]])
    with pytest.raises(GeometryError, match="focal length is undetermined"):
        vn.calibrate_k(vps)


def test_one_vp_at_infinity_is_rank_deficient():
    # camera with world x parallel to the image plane: its vp is at infinity, then the
    # principal point and f slide along the line of the two finite vps
    R = rotation_about_axis([1, 0, 0], np.deg2rad(-35))
    vps = (K_TRUE @ R).T
    with pytest.raises(GeometryError, match="do not determine K"):
        vn.calibrate_k(vps)


def test_non_orthogonal_families_raise_not_positive_definite():
    # three vps on the same side of the image as an acute triangle around no valid orthocentre
    vps = np.array([[0.0, 0.0, 1.0], [100.0, 0.0, 1.0], [40.0, 5.0, 1.0]])
    with pytest.raises(GeometryError, match="not positive definite|do not determine"):
        vn.calibrate_k(vps)


def test_calibrate_views_needs_three_families():
    R, t = camera(R0)
    fams = box_families(R, t)
    del fams["z"]
    with pytest.raises(GeometryError, match="three families"):
        vn.calibrate_views([fams])


# ----------------------------------------------------------------------------- rotations

def test_axis_angle_and_euler_roundtrip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        axis = rng.normal(size=3)
        angle = rng.uniform(1, 179)
        R = rotation_about_axis(axis, np.deg2rad(angle))
        a, g = vn.axis_angle(R)
        assert g == pytest.approx(angle, abs=1e-7)
        assert np.allclose(a, axis / np.linalg.norm(axis), atol=1e-7)
        z, y, x = np.deg2rad(vn.euler_zyx_deg(R))
        R2 = (rotation_about_axis([0, 0, 1], z) @ rotation_about_axis([0, 1, 0], y)
              @ rotation_about_axis([1, 0, 0], x))
        assert np.allclose(R, R2, atol=1e-12)


def test_axis_angle_at_180_degrees():
    R = rotation_about_axis([0, 1, 1], np.pi)
    a, g = vn.axis_angle(R)
    assert g == pytest.approx(180.0)
    assert abs(abs(a @ np.array([0, 1, 1]) / np.sqrt(2)) - 1) < 1e-9


def test_rotation_from_vps_is_proper_and_orthonormal_with_noise():
    rng = np.random.default_rng(2)
    R, t = camera(R0)
    fams = box_families(R, t, noise_px=1.0, rng=rng)
    vps = np.array([vn.vanishing_point(fams[k])[0] for k in "xyz"])
    Rest = vn.rotation_from_vps(K_TRUE, vps)
    assert np.allclose(Rest @ Rest.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rest) == pytest.approx(1.0)
    assert same_up_to_axis_signs(Rest, R, 0.02)


# ----------------------------------------------------------------------------- lines.json

def test_write_read_roundtrip_and_backups(tmp_path):
    R, t = camera(R0)
    views = [box_families(R, t), box_families(*camera(RY10 @ R0))]
    p = tmp_path / "lines.json"
    assert vn.write_lines(p, views, images=["calibration/block_0.png", "calibration/block_1.png"]) is None
    back = vn.read_lines(p)
    assert len(back) == 2 and set(back[0]) == {"x", "y", "z"}
    assert np.allclose(back[1]["z"], views[1]["z"])
    doc = json.loads(p.read_text())
    assert doc["schema"] == "semlab-lines/1" and doc["views"][1]["image"] == "calibration/block_1.png"
    first = p.read_text()
    bak = vn.write_lines(p, views[:1])
    assert bak == tmp_path / "lines.bak.json" and bak.read_text() == first
    bak2 = vn.write_lines(p, views)
    assert bak2 == tmp_path / "lines.bak1.json" and len(vn.read_lines(bak2)) == 1
    assert len(vn.read_lines(p)) == 2


def test_write_lines_accepts_a_whole_document(tmp_path):
    doc = {"schema": "semlab-lines/1",
           "views": [{"view": 0, "image": "a.png", "families": {"x": [[0, 0, 1, 1], [0, 1, 1, 2]]}}]}
    p = tmp_path / "l.json"
    vn.write_lines(p, doc)
    assert json.loads(p.read_text())["views"][0]["image"] == "a.png"


def test_write_lines_rejects_bad_data_without_touching_the_file(tmp_path):
    p = tmp_path / "lines.json"
    p.write_text("keep me")
    with pytest.raises(SemlabError, match="at least 2"):
        vn.write_lines(p, [{"x": [[0, 0, 1, 1]]}])
    assert p.read_text() == "keep me" and not (tmp_path / "lines.bak.json").exists()


@pytest.mark.parametrize("content, match", [
    ("{not json", "invalid JSON"),
    (json.dumps({"views": []}), "schema"),
    (json.dumps({"schema": "semlab-lines/1"}), "views"),
    (json.dumps({"schema": "semlab-lines/1", "views": [{"view": 0}]}), "families"),
    (json.dumps({"schema": "semlab-lines/1", "views": [{"families": {"x": [[0, 0, 1, 1]]}}]}),
     r"view 0, family 'x'.*at least 2"),
    (json.dumps({"schema": "semlab-lines/1", "views": [
        {"families": {"x": [[0, 0, 1, 1], [0, 1, 1, 2]]}},
        {"families": {"y": [[0, 0, 1, 1], [2, 2, 2, 2]]}}]}), r"view 1, family 'y'.*zero length"),
    (json.dumps({"schema": "semlab-lines/1", "views": [
        {"families": {"x": [[0, 0, 1, 1], [0, 1, 1]]}}]}), r"\[x1, y1, x2, y2\]"),
    ('{"schema": "semlab-lines/1", "views": [{"families": {"x": [[0, 0, 1, 1], [0, NaN, 1, 2]]}}]}',
     "NaN"),
])
def test_read_lines_errors_name_file_view_family(tmp_path, content, match):
    p = tmp_path / "lines.json"
    p.write_text(content)
    with pytest.raises(SemlabError, match=match) as info:
        vn.read_lines(p)
    assert str(p) in str(info.value)


def test_read_lines_missing_file(tmp_path):
    with pytest.raises(SemlabError, match="cannot read"):
        vn.read_lines(tmp_path / "nope.json")
