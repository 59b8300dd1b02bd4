"""Tests of semlab.reconstruct on synthetic scenes made here (known heights, tilts, cameras)."""

import numpy as np
import pytest

from semlab.camera import affine_camera_matrix, project_affine, project_perspective, \
    rotation_about_axis
from semlab.errors import GeometryError
from semlab.reconstruct import (TWO_VIEW_MESSAGE, estimate_tilts, factorize_affine,
                                heights_from_tilts, parallax_height, tilt_from_rotation,
                                triangulate_perspective)
from semlab.surface import fit_reference_plane, heights_above_plane

S = 0.03  # µm/px


def make_scene(n=200, seed=0, y_slope=0.01):
    """Fatigued-surface-like points: a plane level in x, 30 % slip-band extrusions/intrusions."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 512, n) * S
    y = rng.uniform(0, 384, n) * S
    band = rng.random(n) < 0.3
    z = 0.2 + y_slope * y + np.where(band, rng.uniform(0.05, 0.3, n) * rng.choice([-1, 1], n), 0)
    return np.column_stack([x, y, z])


def centers(v):
    """Per-view tilt-axis positions that differ (a stage shift between views)."""
    return np.array([(256.0 + 7 * i, 192.0 - 3 * i) for i in range(v)])


def project(xyz, tilts, c=None):
    c = centers(len(tilts)) if c is None else c
    return np.stack([project_affine(xyz, t, S, c[i]) for i, t in enumerate(tilts)], axis=1)


def rel_heights(xyz):
    return heights_above_plane(xyz, fit_reference_plane(xyz))


# ----------------------------------------------------------------------------- heights

@pytest.mark.parametrize("tilts", [(-5.0, 5.0), (-5.0, 0.0, 5.0), (0.0, 8.0)])
def test_heights_unknown_offsets_noise_free(tilts):
    xyz = make_scene()
    res = heights_from_tilts(project(xyz, tilts), tilts, S)
    assert res.xyz_um.shape == (len(xyz), 3)
    assert not res.offsets_known
    # heights above the robust plane are exact; z itself is exact up to one constant
    assert np.abs(rel_heights(res.xyz_um) - rel_heights(xyz)).max() < 1e-9
    dz = res.xyz_um[:, 2] - xyz[:, 2]
    assert np.ptp(dz) < 1e-9
    assert np.ptp(res.xyz_um[:, 1] - xyz[:, 1]) < 1e-9
    assert res.residual_px.max() < 1e-9


@pytest.mark.parametrize("tilts", [(-5.0, 5.0), (-5.0, 0.0, 5.0), (0.0, 8.0)])
def test_heights_known_offsets_absolute(tilts):
    xyz = make_scene(seed=1)
    c = centers(len(tilts))
    res = heights_from_tilts(project(xyz, tilts), tilts, S, center_px=c)
    assert res.offsets_known
    assert np.abs(res.xyz_um - xyz).max() < 1e-9


def test_estimated_offsets_are_consistent():
    """The estimated offsets + xyz reproduce the observed pixels (residual zero, 3 views)."""
    xyz = make_scene(seed=2)
    tilts = (-5.0, 0.0, 5.0)
    pts = project(xyz, tilts)
    res = heights_from_tilts(pts, tilts, S)
    re = project(res.xyz_um, tilts, res.offsets_px)
    assert np.abs(re - pts).max() < 1e-8


def test_parallax_height_closed_form():
    xyz = make_scene(seed=3)
    c = centers(2)
    pts = project(xyz, (-5.0, 5.0), c)
    z = parallax_height(pts[:, 0, 0], pts[:, 1, 0], -5.0, 5.0, S, c[0, 0], c[1, 0])
    assert np.abs(z - xyz[:, 2]).max() < 1e-9
    # equals the general least-squares solution
    res = heights_from_tilts(pts, (-5.0, 5.0), S, center_px=c)
    assert np.abs(res.xyz_um[:, 2] - z).max() < 1e-12


def test_parallax_height_equal_tilts_raises():
    with pytest.raises(GeometryError, match="equal"):
        parallax_height(1.0, 2.0, 5.0, 5.0, S)


@pytest.mark.parametrize("axis_deg", [60.0, 100.0, -30.0])
def test_heights_rotated_tilt_axis(axis_deg):
    """Image rotated so the tilt axis points along axis_deg: same heights after un-rotation."""
    xyz = make_scene(seed=4)
    tilts = (-5.0, 0.0, 5.0)
    pts = project(xyz, tilts)
    a = np.deg2rad(axis_deg - 90.0)  # maps image y (0, 1) to (cos axis, sin axis)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rotated = pts @ r.T
    d = r @ np.array([0.0, 1.0])
    assert np.allclose(d, [np.cos(np.deg2rad(axis_deg)), np.sin(np.deg2rad(axis_deg))])
    res = heights_from_tilts(rotated, tilts, S, tilt_axis_deg=axis_deg)
    assert np.abs(rel_heights(res.xyz_um) - rel_heights(xyz)).max() < 1e-9
    # without telling the axis the heights are wrong
    bad = heights_from_tilts(rotated, tilts, S)
    assert np.abs(rel_heights(bad.xyz_um) - rel_heights(xyz)).max() > 1e-3


def test_heights_noise_matches_prediction():
    """0.02 px matching noise at ±5°, 0.03 µm/px: RMS height error ≈ propagated σ (≈ 5 nm)."""
    from semlab.surface import height_sigma
    xyz = make_scene(n=400, seed=5)
    tilts = (-5.0, 5.0)
    pts = project(xyz, tilts) + np.random.default_rng(5).normal(0, 0.02, (400, 2, 2))
    res = heights_from_tilts(pts, tilts, S)
    err = rel_heights(res.xyz_um) - rel_heights(xyz)
    rms = np.sqrt(np.mean(err ** 2))
    pred = height_sigma(0.02, tilts, S)
    assert 0.8 * pred < rms < 1.2 * pred
    assert rms < 0.008


def test_residual_flags_a_bad_match():
    xyz = make_scene(seed=6)
    tilts = (-5.0, 0.0, 5.0)
    pts = project(xyz, tilts)
    pts[17, 1, 0] += 2.0
    res = heights_from_tilts(pts, tilts, S)
    assert np.argmax(res.residual_px) == 17


def test_heights_errors():
    xyz = make_scene(n=20)
    pts = project(xyz, (-5.0, 5.0))
    with pytest.raises(GeometryError, match="different stage tilts"):
        heights_from_tilts(pts, (5.0, 5.0), S)
    with pytest.raises(GeometryError, match="3 value"):
        heights_from_tilts(pts, (-5.0, 0.0, 5.0), S)
    with pytest.raises(GeometryError, match="pixel_size_um"):
        heights_from_tilts(pts, (-5.0, 5.0), 0.0)
    with pytest.raises(GeometryError, match="center_px"):
        heights_from_tilts(pts, (-5.0, 5.0), S, center_px=[1.0, 2.0, 3.0])
    bad = pts.copy()
    bad[3, 1, 0] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        heights_from_tilts(bad, (-5.0, 5.0), S)
    with pytest.raises(GeometryError, match=r"\(N, V, 2\)"):
        heights_from_tilts(pts[:, :, 0], (-5.0, 5.0), S)
    with pytest.raises(GeometryError, match="at least 2 views"):
        heights_from_tilts(pts[:, :1], (-5.0,), S)


# ----------------------------------------------------------------------------- factorization

def test_factorize_affine_noise_free():
    xyz = make_scene(seed=7)
    tilts = (-5.0, 0.0, 5.0)
    pts = project(xyz, tilts)
    m, x, t = factorize_affine(pts)
    assert m.shape == (6, 3) and x.shape == (3, len(xyz)) and t.shape == (6,)
    w = pts.transpose(1, 2, 0).reshape(6, -1)
    assert np.abs(m @ x + t[:, None] - w).max() < 1e-8
    assert factorize_affine(pts).residual_px < 1e-9
    # the true cameras are an affine transform of the recovered ones: M_true = M A
    m_true = np.vstack([affine_camera_matrix(tt, S)[:, :3] for tt in tilts])
    a, *_ = np.linalg.lstsq(m, m_true, rcond=None)
    assert np.abs(m @ a - m_true).max() < 1e-9


def test_factorize_affine_residual_reports_noise():
    xyz = make_scene(n=500, seed=8)
    tilts = (-5.0, 0.0, 5.0)
    sigma = 0.1
    pts = project(xyz, tilts) + np.random.default_rng(8).normal(0, sigma, (500, 3, 2))
    res = factorize_affine(pts)
    n = 500
    expected = sigma * np.sqrt((6 - 3) * (n - 1 - 3) / (6 * n))  # noise left outside rank 3
    assert 0.85 * expected < res.residual_px < 1.15 * expected


def test_factorize_affine_errors():
    xyz = make_scene(n=20)
    pts = project(xyz, (-5.0, 5.0))
    with pytest.raises(GeometryError, match="at least 4"):
        factorize_affine(pts[:3])
    line = pts.copy()
    line[:, :, 1] = 2.0 * line[:, :, 0] + 1.0
    with pytest.raises(GeometryError, match="collinear"):
        factorize_affine(line)
    with pytest.raises(GeometryError, match="transpose"):
        factorize_affine(pts.transpose(1, 0, 2))


# ----------------------------------------------------------------------------- tilt recovery

def test_estimate_tilts_noise_free():
    xyz = make_scene(seed=9)
    tilts = np.array([-5.0, 0.0, 5.0])
    est = estimate_tilts(project(xyz, tilts), pixel_size_um=S, n_boot=20, progress=False)
    assert np.abs(est.tilt_deg - tilts).max() < 1e-6
    assert est.unit == "um"
    assert np.abs(rel_heights(est.xyz) - rel_heights(xyz)).max() < 1e-7
    assert np.all(est.tilt_sigma_deg < 1e-6)


def test_estimate_tilts_reference_view_and_pixels():
    """A known tilt for one view fixes the offset even if the surface is not level in x."""
    xyz = make_scene(seed=10)
    xyz[:, 2] += 0.03 * xyz[:, 0]  # sample surface inclined: level-plane convention would shift
    tilts = np.array([-3.0, 0.0, 4.0, 7.0])
    pts = project(xyz, tilts)
    est = estimate_tilts(pts, reference_view=1, reference_tilt_deg=0.0, n_boot=0, progress=False)
    assert np.abs(est.tilt_deg - tilts).max() < 1e-6
    assert est.unit == "px"
    assert np.abs(rel_heights(est.xyz * S) - rel_heights(xyz)).max() < 1e-7
    level = estimate_tilts(pts, n_boot=0, progress=False)
    slope_deg = np.rad2deg(np.arctan(0.03))
    assert np.abs(level.tilt_deg - (tilts - slope_deg)).max() < 1e-6


def test_estimate_tilts_sign_convention():
    """Reversed view order: tilts still increase with view order and z flips (Necker)."""
    xyz = make_scene(seed=11)
    tilts = np.array([-5.0, 0.0, 5.0])
    pts = project(xyz, tilts)[:, ::-1]
    est = estimate_tilts(pts, pixel_size_um=S, n_boot=0, progress=False)
    assert np.abs(est.tilt_deg - tilts).max() < 1e-6
    assert np.abs(rel_heights(est.xyz) + rel_heights(xyz)).max() < 1e-7


def test_estimate_tilts_noisy_within_0p1_deg():
    xyz = make_scene(n=200, seed=12)
    tilts = np.array([-5.0, 0.0, 5.0])
    pts = project(xyz, tilts) + np.random.default_rng(12).normal(0, 0.02, (200, 3, 2))
    est = estimate_tilts(pts, pixel_size_um=S, n_boot=100, seed=1, progress=False)
    err = np.abs(est.tilt_deg - tilts)
    assert err.max() < 0.1
    assert np.all(np.isfinite(est.tilt_sigma_deg))
    assert np.all(est.tilt_sigma_deg > 0) and np.all(est.tilt_sigma_deg < 0.1)
    assert np.all(err < 5 * est.tilt_sigma_deg)


def test_estimate_tilts_two_views_raises():
    pts = project(make_scene(n=30), (-5.0, 5.0))
    with pytest.raises(GeometryError) as info:
        estimate_tilts(pts, progress=False)
    assert str(info.value) == TWO_VIEW_MESSAGE


def test_estimate_tilts_flat_surface_raises():
    xyz = make_scene(n=50, seed=13)
    xyz[:, 2] = 0.2
    with pytest.raises(GeometryError, match="coplanar"):
        estimate_tilts(project(xyz, (-5.0, 0.0, 5.0)), n_boot=0, progress=False)


def test_estimate_tilts_inconsistent_constraints_raise():
    """Noise far larger than the tilt signal makes Q indefinite: refuse, don't guess."""
    xyz = make_scene(n=40, seed=14)
    rng = np.random.default_rng(0)
    raised = 0
    for _ in range(10):
        pts = project(xyz, (-0.2, 0.0, 0.2)) + rng.normal(0, 3.0, (40, 3, 2))
        try:
            estimate_tilts(pts, n_boot=0, progress=False)
        except GeometryError as exc:
            assert "positive definite" in str(exc)
            raised += 1
    assert raised > 0


def test_estimate_tilts_bad_reference_view():
    pts = project(make_scene(n=30), (-5.0, 0.0, 5.0))
    with pytest.raises(GeometryError, match="reference_view"):
        estimate_tilts(pts, reference_view=3, progress=False)


# ----------------------------------------------------------------------------- rotations

def test_rotation_convention_matches_affine_camera():
    r = rotation_about_axis((0, 1, 0), np.deg2rad(7.0))
    assert np.allclose(r[:2] / S, affine_camera_matrix(7.0, S)[:, :3])


@pytest.mark.parametrize("t0, t1", [(-5.0, 5.0), (0.0, 8.0), (10.0, -20.0)])
def test_tilt_from_rotation(t0, t1):
    r0 = rotation_about_axis((0, 1, 0), np.deg2rad(t0))
    r1 = rotation_about_axis((0, 1, 0), np.deg2rad(t1))
    assert abs(tilt_from_rotation(r1 @ r0.T) - (t1 - t0)) < 1e-10


def test_tilt_from_rotation_errors():
    with pytest.raises(GeometryError, match="not a rotation"):
        tilt_from_rotation(2 * np.eye(3))
    with pytest.raises(GeometryError, match="not a rotation"):
        tilt_from_rotation(np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(GeometryError, match="3x3"):
        tilt_from_rotation(np.eye(2))


# ----------------------------------------------------------------------------- perspective

def _cross(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def perspective_scene(n=60, seed=0):
    rng = np.random.default_rng(seed)
    k = np.array([[2000.0, 0, 256], [0, 2000.0, 192], [0, 0, 1]])
    m = np.array([0.0, 0.0, 50.0])
    x = m + np.column_stack([rng.uniform(-5, 5, n), rng.uniform(-4, 4, n), rng.uniform(-1, 1, n)])
    r1 = rotation_about_axis((0, 1, 0), np.deg2rad(8.0))
    t1 = m - r1 @ m  # eucentric: rotate about the scene centre
    x0 = project_perspective(x, k, np.eye(3), np.zeros(3))
    x1 = project_perspective(x, k, r1, t1)
    f = np.linalg.inv(k).T @ _cross(t1) @ r1 @ np.linalg.inv(k)
    return k, x, r1, t1, x0, x1, f


@pytest.mark.parametrize("essential", [False, True])
def test_triangulate_perspective_recovers_scene_up_to_scale(essential):
    k, x, r1, t1, x0, x1, f = perspective_scene()
    g = k.T @ f @ k if essential else f * 3.7  # any scale of F/E
    xr, r, t = triangulate_perspective(k, g, x0, x1, essential=essential)
    assert np.abs(r - r1).max() < 1e-9
    assert np.abs(t - t1 / np.linalg.norm(t1)).max() < 1e-9
    assert np.abs(xr * np.linalg.norm(t1) - x).max() < 1e-6


def test_triangulate_perspective_with_estimated_f():
    import cv2
    k, x, r1, t1, x0, x1, _ = perspective_scene(n=100, seed=1)
    f, _ = cv2.findFundamentalMat(x0, x1, cv2.FM_8POINT)
    xr, r, t = triangulate_perspective(k, f, x0, x1)
    assert np.abs(r - r1).max() < 1e-5
    scale = np.linalg.norm(t1)
    assert np.abs(xr * scale - x).max() / np.ptp(x[:, 2]) < 1e-3


def test_triangulate_perspective_errors():
    k, x, r1, t1, x0, x1, f = perspective_scene()
    with pytest.raises(GeometryError, match="rank < 2"):
        triangulate_perspective(k, np.zeros((3, 3)), x0, x1)
    with pytest.raises(GeometryError, match="singular"):
        triangulate_perspective(np.zeros((3, 3)), f, x0, x1)
    with pytest.raises(GeometryError, match=r"\(N, 2\)"):
        triangulate_perspective(k, f, x0, x1[:-1])
    bad = x0.copy()
    bad[0, 0] = np.nan
    with pytest.raises(GeometryError, match="finite"):
        triangulate_perspective(k, f, bad, x1)
    # half the points in front of camera 0 but behind camera 1: no pose puts a majority of
    # them in front of both cameras (the true one and its twisted pair tie at N/2)
    rng = np.random.default_rng(2)
    n = len(x)
    xb = np.column_stack([rng.uniform(55, 70, n), rng.uniform(-4, 4, n), rng.uniform(2, 4, n)])
    assert np.all(xb @ r1[2] + t1[2] < 0)
    mixed = np.vstack([x[: n // 2], xb[: n // 2]])
    h0 = mixed @ k.T
    h1 = (mixed @ r1.T + t1) @ k.T
    with pytest.raises(GeometryError, match="in front"):
        triangulate_perspective(k, f, h0[:, :2] / h0[:, 2:], h1[:, :2] / h1[:, 2:])


# ----------------------------------------------------------------------------- with synth

def test_consistent_with_synth_truth(tmp_path):
    """True pixel positions written by semlab.synth give back its true heights and tilts."""
    from semlab.synth import make_experiment, read_truth_points

    tilts = (-5.0, 0.0, 5.0)
    make_experiment(tmp_path / "exp", seed=1, size=(96, 128), tilts_deg=tilts, n_frames=0,
                    n_clicks=10, write_block=False, progress=False)
    tp = read_truth_points(tmp_path / "exp")
    pts = np.stack([np.column_stack([tp[f"v{i}_x_px"], tp[f"v{i}_y_px"]]) for i in range(3)], 1)
    xyz = np.column_stack([tp["x_um"], tp["y_um"], tp["z_um"]])
    ok = np.all(np.isfinite(pts), axis=(1, 2)) & np.all(np.isfinite(xyz), axis=1)
    pts, xyz = pts[ok], xyz[ok]
    res = heights_from_tilts(pts, tilts, S)
    assert np.ptp(res.xyz_um[:, 2] - xyz[:, 2]) < 1e-6
    est = estimate_tilts(pts, reference_view=1, n_boot=0, progress=False)
    assert np.abs(est.tilt_deg - tilts).max() < 1e-4


def test_estimate_tilts_noise_free_view_removes_the_bias():
    """Matching noise only outside the reference view (view 0) biases the plain rank-2 fit;
    the errors-in-variables correction (noise_free_view=0) removes the bias."""
    xyz = make_scene(n=2000, seed=5)
    tilts = np.array([-5.0, 0.0, 5.0])
    clean = project(xyz, tilts)
    rng = np.random.default_rng(5)
    plain, fixed = [], []
    for _ in range(4):
        pts = clean.copy()
        pts[:, 1:] += rng.normal(0, 0.2, pts[:, 1:].shape)
        for nf, out in ((None, plain), (0, fixed)):
            t = estimate_tilts(pts, pixel_size_um=S, n_boot=0, progress=False,
                               noise_free_view=nf).tilt_deg
            out.append(np.abs(np.diff(t) - np.diff(tilts)).max())
    assert np.mean(plain) > 0.3 and np.mean(fixed) < 0.25 * np.mean(plain)
    # noise-free input: the correction changes nothing
    t = estimate_tilts(clean, pixel_size_um=S, n_boot=0, progress=False, noise_free_view=0)
    assert np.allclose(np.diff(t.tilt_deg), np.diff(tilts), atol=1e-6)
    with pytest.raises(GeometryError, match="noise_free_view"):
        estimate_tilts(clean, pixel_size_um=S, n_boot=0, progress=False, noise_free_view=3)


# ----------------------------------------------------------------------------- tilt checks

from semlab.tiltcheck import axis_is_significant, check_tilts, tilt_axis_sigma, x_scales  # noqa: E402


def noisy(pts, sigma_px, seed=0):
    return pts + np.random.default_rng(seed).normal(0, sigma_px, pts.shape)


def test_x_scale_of_the_flat_surface_is_the_cosine_ratio():
    xyz = make_scene(n=400, seed=3)
    tilts = (0.0, 10.0, 20.0)
    xs = x_scales(noisy(project(xyz, tilts), 0.03), sigma_px=0.03)
    want = np.cos(np.deg2rad(tilts)) / np.cos(0.0)
    assert np.all(np.abs(xs["A"] - want) < 4 * xs["A_sigma"] + 1e-12)
    assert np.all(xs["A_sigma"][1:] < 2e-4)
    assert 0.6 < xs["inliers"].mean() < 0.75  # the plane, not the 30 % of bands


def test_given_tilts_that_agree_pass_and_report_the_surface_tilt():
    xyz = make_scene(n=400, seed=4)
    pre = np.deg2rad(3.0)  # the sample sits 3° tilted on the stage
    xyz_t = xyz.copy()
    xyz_t[:, 0] = xyz[:, 0] * np.cos(pre) - xyz[:, 2] * np.sin(pre)
    xyz_t[:, 2] = xyz[:, 0] * np.sin(pre) + xyz[:, 2] * np.cos(pre)
    for scene, beta in ((xyz, 0.0), (xyz_t, 3.0)):
        chk = check_tilts(noisy(project(scene, (-5.0, 5.0)), 0.03), (-5.0, 5.0), sigma_px=0.03,
                          pixel_size_um=S)
        assert chk.consistent and chk.relief_detected
        assert abs(abs(chk.pretilt_deg) - beta) < 0.6


def test_contradicting_tilts_are_refused_with_the_tilts_to_use():
    xyz = make_scene(n=400, seed=5)
    pts = noisy(project(xyz, (-5.0, 5.0)), 0.03)
    with pytest.raises(GeometryError, match=r"tilt_deg = \[-5.0, 85.0\] contradicts") as e:
        check_tilts(pts, (-5.0, 85.0), sigma_px=0.03)
    msg = str(e.value)
    assert "measured 1.00" in msg and "predict 0." in msg
    assert "tilt_deg = [-5.0, 5.0" in msg  # the estimate to use instead
    chk = check_tilts(pts, (-5.0, 85.0), sigma_px=0.03, strict=False)
    assert not chk.consistent and np.allclose(chk.suggested_tilt_deg, (-5.0, 5.0), atol=0.3)
    # 3 views, one tilt wrong by 20°
    pts3 = noisy(project(xyz, (-5.0, 0.0, 5.0)), 0.03)
    with pytest.raises(GeometryError, match="contradicts"):
        check_tilts(pts3, (-5.0, 0.0, 25.0), sigma_px=0.03)
    chk = check_tilts(pts3, (-5.0, 0.0, 25.0), sigma_px=0.03, strict=False)
    assert np.allclose(chk.suggested_tilt_deg, (-5.0, 0.0, 5.0), atol=0.5)
    # views at 13° and 0° given as 3° and 0°: view 1's x-scale (1/cos 13°) is more than a
    # level surface allows from 3°; the tilts to use put it at 0°, not the given ones again
    pts = noisy(project(xyz, (13.0, 0.0)), 0.03)
    with pytest.raises(GeometryError, match=r"tilt_deg = \[3.0, 0.0\] contradicts") as e:
        check_tilts(pts, (3.0, 0.0), sigma_px=0.03)
    assert "Tilts that fit the views: tilt_deg = [13.0, 0.0]" in str(e.value)


def test_too_few_points_leave_the_tilts_unchecked():
    pts = project(make_scene(n=5, seed=10), (-5.0, 5.0))
    chk = check_tilts(pts, (-5.0, 85.0))
    assert chk.consistent is None and "not checked" in chk.message
    assert np.all(np.isnan(chk.x_scale))


def test_identical_views_refused_flat_sample_reported_flat():
    xyz = make_scene(n=300, seed=6)
    pts = project(xyz, (0.0, 0.0))
    with pytest.raises(GeometryError, match="no parallax at all"):
        check_tilts(pts, (-5.0, 5.0))
    flat = xyz.copy()
    flat[:, 2] = 0.2 + 0.01 * flat[:, 1]
    chk = check_tilts(noisy(project(flat, (-5.0, 5.0)), 0.03), (-5.0, 5.0), sigma_px=0.03,
                      pixel_size_um=S)
    assert chk.consistent and not chk.relief_detected
    assert "flat within" in chk.message
    # 3σ of the parallax noise sqrt(2)·0.03 px turned into height at 10° of tilt
    assert chk.detection_limit_um == pytest.approx(3 * np.sqrt(2) * 0.03 * S / np.sin(
        np.deg2rad(10.0)), rel=0.05)


def test_a_band_on_a_flat_surface_is_relief():
    """A narrow band on an otherwise flat surface (the demo's kind: a few per cent of the
    points, their parallax 6σ) leaves the parallax RMS within 1.5× the noise, but 20 points
    beyond 3σ where noise gives ~1: relief, not "flat within"; noise alone is still flat."""
    xyz = make_scene(n=1000, seed=11)
    xyz[:, 2] = 0.2 + 0.01 * xyz[:, 1]
    band = np.random.default_rng(1).random(len(xyz)) < 0.02
    # parallax of a height z at ±5°: z · 2 sin 5° / S; here 6 × its noise sqrt(2) · 0.03 px
    xyz[band, 2] += 6 * np.sqrt(2) * 0.03 * S / (2 * np.sin(np.deg2rad(5.0)))
    for sigma in (0.03, np.full(len(xyz), 0.03), None):
        chk = check_tilts(noisy(project(xyz, (-5.0, 5.0)), 0.03), (-5.0, 5.0), sigma_px=sigma,
                          pixel_size_um=S)
        assert chk.parallax_rms_px[1] < 1.5 * chk.noise_px[1]    # the RMS alone: flat
        assert chk.consistent and chk.relief_detected and "flat within" not in chk.message
    xyz[band, 2] = 0.2 + 0.01 * xyz[band, 1]
    for seed in range(5):
        chk = check_tilts(noisy(project(xyz, (-5.0, 5.0)), 0.03, seed=seed), (-5.0, 5.0),
                          sigma_px=0.03, pixel_size_um=S)
        assert not chk.relief_detected and "flat within" in chk.message


def test_tilt_axis_rotated_only_when_significant():
    xyz = make_scene(n=300, seed=7)
    pts = noisy(project(xyz, (-5.0, 5.0)), 0.05)
    axis, sig = tilt_axis_sigma(pts[:, 0], pts[:, 1], n_boot=100)
    assert 0 < sig < 2.0
    assert abs(axis - 90.0) < 4 * sig and not axis_is_significant(axis, sig)
    a = np.deg2rad(3.0)  # scan rotation: the tilt axis at 93° in both views
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    rot = pts @ r.T
    axis_r, sig_r = tilt_axis_sigma(rot[:, 0], rot[:, 1], n_boot=100)
    assert abs(axis_r - 93.0) < 4 * sig_r and axis_is_significant(axis_r, sig_r)
    # a y-error of the matches that follows the relief's parallax (0.05 px at its largest,
    # the matching σ here) turns the axis; the half-samples call it significant, the shared
    # error's term does not. A 30° scan rotation stays significant with that term.
    par = pts[:, 1, 0] - pts[:, 0, 0]
    rel = par - np.polyval(np.polyfit(pts[:, 0, 0], par, 1), pts[:, 0, 0])
    biased = pts.copy()
    biased[:, 1, 1] += 0.05 * rel / np.abs(rel).max()
    axis_b, sig_b = tilt_axis_sigma(biased[:, 0], biased[:, 1], n_boot=100)
    assert axis_is_significant(axis_b, sig_b)                  # the false rotation
    axis_b, sig_b = tilt_axis_sigma(biased[:, 0], biased[:, 1], n_boot=100, bias_px=0.05)
    assert not axis_is_significant(axis_b, sig_b)
    a = np.deg2rad(30.0)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    axis_30, sig_30 = tilt_axis_sigma(pts[:, 0] @ r.T, pts[:, 1] @ r.T, n_boot=100, bias_px=0.05)
    assert abs(axis_30 - 120.0) < 3 * sig_30 and axis_is_significant(axis_30, sig_30)


def test_estimated_tilt_differences_agree_with_the_x_scales():
    xyz = make_scene(n=600, seed=8)
    tilts = np.array([-5.0, 0.0, 5.0])
    pts = noisy(project(xyz, tilts), 0.02)
    est = estimate_tilts(pts, S, n_boot=50, progress=False)
    d_err = np.abs(np.diff(est.tilt_deg) - np.diff(tilts))
    assert d_err.max() <= 0.05, d_err
    assert np.all(est.tilt_sigma_deg > 0)
    chk = check_tilts(pts, est.tilt_deg, sigma_px=0.02, ref_view=1)
    assert chk.consistent and abs(chk.pretilt_deg) < 1.0
    # the outer views' tilts from their x-scales alone agree with the estimate within 3σ
    for j in (0, 2):
        dev = abs(chk.x_scale_tilt_deg[j] - est.tilt_deg[j])
        assert dev < 3 * chk.x_scale_tilt_sigma_deg[j] + 0.05, (j, dev)


def test_level_tilts_removes_the_common_rotation():
    from semlab.tiltcheck import level_tilts

    xyz = make_scene(n=300, seed=9, y_slope=0.0)
    tilts = np.array([-5.0, 0.0, 5.0])
    pts = project(xyz, tilts)
    wrong = tilts + 3.0  # the same differences, another absolute tilt
    plane = fit_reference_plane(heights_from_tilts(pts, wrong, S).xyz_um)
    assert abs(plane[0]) > 0.05
    assert np.allclose(level_tilts(wrong, plane), tilts, atol=1e-9)


def test_real_pollen_substrate_x_scale_checks_the_tilts():
    """pollen_pot1 views 2 and 3 (real, tilts unknown): the grooved substrate around the grain
    is foreshortened differently in the two views (x-scale ~1.02), which a 3° step near 0°
    cannot give (it needs the surface tilted ~22° on the stage) but the levelled 4-view
    estimate of benchmarks/reference_surface.py (-20.2°, -17.0°) does."""
    from conftest import shared_path

    from semlab.io import read_image
    from semlab.matching import auto_match

    d = shared_path("real_sem", "pollen_pot1")
    ims = [read_image(d / f"pot1_0{i}.jpg").data for i in (2, 3)]
    # the tilts' test: the subset matches (stage 9's variational map of these views would
    # double the test's time and move the points by a fraction of their σ)
    m = auto_match(ims, progress=False, variational_fusion=False).only_valid()
    sub = np.hypot(m.pts[:, 0, 0] - 395.0, m.pts[:, 0, 1] - 355.0) > 405.0  # outside the grain
    assert sub.sum() >= 10
    # the substrate's x matching σ from the 4-view residuals (benchmarks/reference_surface.py);
    # the matcher's own 0.03 px leaves one land of the grooves as the "flat" set
    sig = 0.07
    xs = x_scales(m.pts, sigma_px=sig, region=sub)
    assert 1.01 < xs["A"][1] < 1.03 and xs["A_sigma"][1] < 2e-3
    with pytest.raises(GeometryError, match="contradicts"):
        check_tilts(m.pts, (0.0, 3.0), sigma_px=sig, region=sub)
    chk = check_tilts(m.pts, (-20.2, -17.0), sigma_px=sig, region=sub)
    assert chk.consistent and abs(chk.pretilt_deg) < 3.0


def test_heights_from_tilts_with_view_valid_solve_each_point_over_its_views():
    """Points missing a view: the same heights (up to the common gauge constant) as with
    every view, exactly for exact projections; the missing entries may be NaN."""
    rng = np.random.default_rng(4)
    tilts = np.array([-6.0, -2.0, 2.0, 6.0])
    th = np.deg2rad(tilts)
    s = 0.05
    xyz = np.column_stack([rng.uniform(-10, 10, 60), rng.uniform(-8, 8, 60),
                           rng.uniform(-1, 1, 60)])
    pts = np.stack([np.column_stack([(xyz[:, 0] * np.cos(t) + xyz[:, 2] * np.sin(t)) / s + 300,
                                     xyz[:, 1] / s + 200]) for t in th], axis=1)
    mask = np.ones((60, 4), bool)
    mask[:20, 3] = False
    mask[20:30, 1:3] = False
    holed = np.where(mask[..., None], pts, np.nan)
    full = heights_from_tilts(pts, tilts, s)
    part = heights_from_tilts(holed, tilts, s, view_valid=mask)
    dz = part.xyz_um[:, 2] - full.xyz_um[:, 2]
    assert np.ptp(dz) < 1e-9 and np.ptp(part.xyz_um[:, 0] - full.xyz_um[:, 0]) < 1e-9
    assert np.allclose(part.xyz_um[:, 1], full.xyz_um[:, 1]) and part.residual_px.max() < 1e-9
    same = heights_from_tilts(pts, tilts, s, view_valid=np.ones((60, 4), bool))
    assert np.array_equal(same.xyz_um, full.xyz_um)
    one = mask.copy()
    one[0, :3] = False                        # a point left with a single view
    with pytest.raises(GeometryError, match="fewer than two valid views"):
        heights_from_tilts(holed, tilts, s, view_valid=one)
    with pytest.raises(GeometryError, match="valid in every view"):
        heights_from_tilts(pts, tilts, s, view_valid=np.tile([True, True, True, False], (60, 1)))


def test_estimate_tilts_sign_convention_is_a_parameter():
    """The Necker reversal is not observable: ``increasing=False`` returns the same fit with
    θ → −θ and z → −z, so a stage that tilted the other way gets its relief the right way up."""
    xyz = make_scene(seed=2)
    pts = project(xyz, (-5.0, 0.0, 5.0))
    inc = estimate_tilts(pts, pixel_size_um=S, n_boot=0, progress=False)
    dec = estimate_tilts(pts, pixel_size_um=S, n_boot=0, progress=False, increasing=False)
    assert inc.tilt_deg[-1] > inc.tilt_deg[0] and dec.tilt_deg[-1] < dec.tilt_deg[0]
    np.testing.assert_allclose(dec.tilt_deg, -inc.tilt_deg, atol=1e-9)
    np.testing.assert_allclose(dec.xyz[:, 2], -inc.xyz[:, 2], atol=1e-9)
    np.testing.assert_allclose(inc.xyz[:, 2] - inc.xyz[:, 2].mean(),
                               xyz[:, 2] - xyz[:, 2].mean(), atol=1e-6)
