"""Tests of semlab.registration: transforms, feature matching, frame registration, drift.csv,
and the stage drift of semlab.synth (known answers)."""

import cv2
import numpy as np
import pytest
from scipy import ndimage

from semlab.errors import GeometryError, SemlabError
from semlab.registration import (DRIFT_CSV_COLUMNS, Transform2D, estimate_transform,
                                 fit_transform, match_features, read_drift_csv, register_frames,
                                 register_pair, register_points, warp_to_reference,
                                 write_drift_csv)
from semlab.synth import drift_pixel_map, drifted_positions, stage_drift


def _texture(seed, shape, sigma=1.5):
    t = ndimage.gaussian_filter(np.random.default_rng(seed).standard_normal(shape), sigma)
    return (t - t.min()) / np.ptp(t) * 200


def _overlap_error(T, true, shape, margin=35):
    """Largest distance between two transforms over the part of the reference frame that a
    frame drifted by up to ``margin`` px still sees."""
    h, w = shape
    g = np.stack(np.meshgrid(np.linspace(margin, w - 1 - margin, 9),
                             np.linspace(margin, h - 1 - margin, 9)), -1).reshape(-1, 2)
    return float(np.linalg.norm(T(g) - true(g), axis=1).max())


def test_transform_params_inverse_compose_rigid():
    c = (99.5, 79.5)
    T = Transform2D.from_params(12.5, -7.25, 1.1, 1.003, center=c)
    p = T.params(c)
    assert np.allclose([p["dx_px"], p["dy_px"], p["rotation_deg"], p["scale"]],
                       [12.5, -7.25, 1.1, 1.003])
    pts = np.random.default_rng(0).uniform(0, 200, (20, 2))
    assert np.allclose(T.inverse()(T(pts)), pts)
    U = Transform2D.from_params(-3, 4, -0.5, 0.999, center=c)
    assert np.allclose((U @ T)(pts), U(T(pts)))
    R = T.rigid(c)
    pr = R.params(c)
    assert np.isclose(pr["scale"], 1.0) and np.isclose(pr["rotation_deg"], 1.1)
    assert np.allclose(R(np.array([c])), T(np.array([c])))
    # a point 100 px from the centre moves by scale - 1 = 0.3 px more under T than under R
    assert np.isclose(T.distance(R, (160, 200)), 0.003 * np.hypot(99.5, 79.5))
    assert Transform2D.identity().is_identity() and not T.is_identity()
    with pytest.raises(GeometryError):
        Transform2D(np.zeros((2, 3)))
    with pytest.raises(GeometryError):
        Transform2D(np.ones((2, 2)))


@pytest.mark.parametrize("model", ["translation", "similarity", "affine"])
def test_fit_and_estimate_transform_known_answer(model):
    rng = np.random.default_rng(1)
    p0 = rng.uniform(0, 300, (200, 2))
    true = {"translation": Transform2D.from_params(5.5, -2.0),
            "similarity": Transform2D.from_params(5.5, -2.0, 0.8, 1.002, (150, 150)),
            "affine": Transform2D(np.array([[1.01, 0.02, 3.0], [-0.015, 0.99, -4.0]]))}[model]
    p1 = true(p0)
    assert fit_transform(p0, p1, model).distance(true, (300, 300)) < 1e-9
    out = rng.random(200) < 0.3                        # 30 % gross outliers
    p1n = p1 + rng.normal(0, 0.05, p1.shape)
    p1n[out] += rng.uniform(-40, 40, (out.sum(), 2))
    T, inl = estimate_transform(p0, p1n, model)
    assert T.distance(true, (300, 300)) < 0.05
    assert not inl[out & (np.linalg.norm(p1n - p1, axis=1) > 3)].any() and inl[~out].mean() > 0.95
    with pytest.raises(GeometryError, match="RANSAC|matches"):
        estimate_transform(p0[:20], rng.uniform(0, 300, (20, 2)), model)


def test_fit_transform_refuses_degenerate_points():
    line = np.c_[np.arange(5.0), 2 * np.arange(5.0)]
    with pytest.raises(GeometryError, match="collinear"):
        fit_transform(line, line, "affine")
    with pytest.raises(GeometryError, match="coincident"):
        fit_transform(np.ones((4, 2)), np.ones((4, 2)), "similarity")
    with pytest.raises(GeometryError, match="model"):
        fit_transform(line, line, "projective")


def test_register_pair_recovers_a_similarity_and_refuses_a_blank_image():
    big = _texture(2, (340, 400))
    src = big[50:290, 50:350]
    c = (149.5, 119.5)
    true = Transform2D.from_params(17.3, -11.6, 1.2, 0.997, c)
    # img(T(p)) = src(p): a material point at p in src is seen at T(p) in img (both crops of
    # one larger texture, so that every pixel of img has content)
    crop = Transform2D.from_params(50, 50)
    M = (crop @ true.inverse() @ crop.inverse()).affine
    img = cv2.warpAffine(big.astype(np.float32), M, (400, 340),
                         flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)[50:290, 50:350]
    r = register_pair(src, img, model="similarity")
    assert _overlap_error(r["transform"], true, src.shape) < 0.05, r
    assert r["method"] in ("features", "features+ecc") and r["n_inliers"] >= 50
    assert r["residual_px"] < 0.5
    with pytest.raises(GeometryError, match="blank"):
        register_pair(src, np.zeros_like(src))
    p0, p1 = match_features(src, img)
    assert len(p0) == len(p1) > 50


def test_warp_to_reference_is_the_inverse_geometry():
    img = _texture(3, (120, 140))
    T = Transform2D.from_params(7.0, -4.0)             # integer shift: exact resampling
    w, foot = warp_to_reference(img, T, margin_px=2)
    # out(p) = img(T(p)) = img(p + (7, -4))
    assert np.allclose(w[10:-10, 5:-15], img[6:-14, 12:-8])
    assert foot[10, 5] and not foot[0, 70] and not foot[60, 135] and foot[60, 130]


def test_register_points_recovers_tilt_like_affine():
    rng = np.random.default_rng(3)
    src = _texture(4, (240, 280))
    A_true = np.array([[np.cos(np.deg2rad(10)), 0.0, 4.5], [0.0, 1.0, -3.0]])   # x-scaling + shift
    dst = cv2.warpAffine(src.astype(np.float32), A_true, (280, 240), flags=cv2.INTER_CUBIC)
    pts = rng.uniform(60, 180, (10, 2))
    mapped, A, res = register_points(src, dst, pts)
    assert np.abs(mapped - (pts @ A_true[:, :2].T + A_true[:, 2])).max() < 0.2
    assert res < 1.0 and A.shape == (2, 3)
    with pytest.raises(GeometryError):
        register_points(src, np.zeros_like(src), pts)


def test_synth_drift_maps_are_inverse_of_each_other():
    shape = (120, 160)
    d = stage_drift(3, 25.0, 1.2, 0.003, 4.0, np.random.default_rng(5))
    assert d[-1] == {"dx_px": 0.0, "dy_px": 0.0, "rotation_deg": 0.0, "scale": 1.0,
                     "scan_dx_px": 0.0, "scan_dy_px": 0.0}
    assert 12.5 <= np.hypot(d[0]["dx_px"], d[0]["dy_px"]) <= 25.0
    q = np.random.default_rng(6).uniform(30, 90, (50, 2))
    m = drift_pixel_map(d[0], shape)                   # drifted pixel -> undrifted position
    p = np.column_stack([ndimage.map_coordinates(m[i], [q[:, 1], q[:, 0]], order=1) for i in (0, 1)])
    assert np.abs(drifted_positions(d[0], p, shape) - q).max() < 1e-3   # map interpolated linearly


@pytest.fixture(scope="module")
def drifted_experiment(tmp_path_factory):
    from semlab.experiment import load
    from semlab.synth import make_experiment

    out = tmp_path_factory.mktemp("drift") / "exp"
    toml = make_experiment(out, seed=4, size=(192, 256), tilts_deg=(), n_frames=3, slip_um=0.0,
                           progress=False, drift_shift_px=30, drift_rotation_deg=1.2,
                           drift_scale=0.003)
    return load(toml).frames(), read_drift_csv(out / "truth" / "drift.csv"), out


def test_register_frames_recovers_synthetic_stage_drift(drifted_experiment, tmp_path):
    """Known answer: a series without material motion, frames drifted by up to 30 px, 1.2°
    and 0.3 %: the recovered transforms are within 0.1 px of the truth everywhere."""
    from semlab.synth import _stage_matrix

    frames, truth, _ = drifted_experiment
    shape = frames[0].shape
    reg = register_frames(frames, model="similarity")
    assert reg.method[-1] == "reference" and reg.transforms[-1].is_identity()
    for k in range(len(frames) - 1):
        d = {c: truth[c][k] for c in ("dx_px", "dy_px", "rotation_deg", "scale")}
        true = Transform2D(_stage_matrix({**d, "scan_dx_px": 0, "scan_dy_px": 0}, shape))
        assert true.distance(Transform2D.identity(), shape) > 10          # real drift
        assert _overlap_error(reg.transforms[k], true, shape) < 0.1, (k, reg.method[k])
        assert reg.method[k].startswith("features") and reg.residual_px[k] < 1.0
    path = write_drift_csv(tmp_path / "drift.csv", reg)
    back = read_drift_csv(path)
    assert list(back)[:len(DRIFT_CSV_COLUMNS)] == list(DRIFT_CSV_COLUMNS)
    assert np.allclose(back["dx_px"], [r["dx_px"] for r in reg.table()])
    assert np.allclose(back["dx_px"][:-1], truth["dx_px"][:-1], atol=0.1)
    assert np.allclose(back["rotation_deg"][:-1], truth["rotation_deg"][:-1], atol=0.03)
    with pytest.raises(SemlabError, match="exists"):
        write_drift_csv(path, reg)


def test_register_frames_without_features_says_so(drifted_experiment):
    frames, _, _ = drifted_experiment
    reg = register_frames(frames, model="similarity", min_inliers=10 ** 6)   # features never enough
    # no frame claims a feature registration it did not get
    assert all(m.startswith("chained") or m in ("reference", "none") for m in reg.method)
    assert np.isnan(reg.residual_px[:-1]).all() and (reg.n_inliers == 0).all()
    with pytest.raises(GeometryError, match="model"):
        register_frames(frames, model="projective")


def test_to_reference_removes_the_rigid_part_only():
    from semlab.registration import Registration

    c = (49.5, 39.5)
    T = Transform2D.from_params(10.0, 5.0, 1.0, 1.01, c)
    reg = Registration(transforms=[T, Transform2D.identity()], residual_px=np.zeros(2),
                       n_inliers=np.zeros(2, int), ecc=np.ones(2), method=np.array(["a", "b"]),
                       shape=(80, 100), reference=1)
    p = np.array([[49.5, 39.5], [89.5, 39.5]])
    back = reg.to_reference(T(p), np.array([0, 0]))
    assert np.allclose(back[0], p[0])                  # centre: shift removed exactly
    assert np.allclose(np.linalg.norm(back[1] - back[0]), 40 * 1.01)   # scale kept
    assert np.allclose(reg.to_reference(T(p), np.array([0, 0]), part="full"), p)


def test_plot_drift_draws_the_table_and_the_truth(drifted_experiment, tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    from semlab.plots import plot_drift

    frames, truth, _ = drifted_experiment
    reg = register_frames(frames, model="similarity")
    table = read_drift_csv(write_drift_csv(tmp_path / "drift.csv", reg))
    fig = plot_drift(table, truth=truth)
    ax_shift, ax_rot, ax_scale = fig.axes
    assert "px" in ax_shift.get_ylabel() and "°" in ax_rot.get_ylabel() and "%" in ax_scale.get_ylabel()
    lines = {ln.get_label(): ln for ln in ax_shift.lines}
    assert np.allclose(lines["dx"].get_ydata(), table["dx_px"])
    assert np.allclose(lines["dx truth"].get_ydata(), truth["dx_px"])
    assert np.allclose(ax_scale.lines[0].get_ydata(), (table["scale"] - 1) * 100)
    # the same figure from the Registration object itself
    fig2 = plot_drift(reg)
    assert np.allclose(fig2.axes[1].lines[0].get_ydata(), table["rotation_deg"])
    import matplotlib.pyplot as plt
    plt.close(fig)
    plt.close(fig2)


def test_between_and_carry_warps_compose_the_frame_transforms():
    from semlab.registration import Registration

    c = (49.5, 39.5)
    T0 = Transform2D.from_params(10.0, 5.0, 1.0, 1.01, c)
    T1 = Transform2D.from_params(-4.0, 2.0, -0.5, 0.998, c)
    reg = Registration(transforms=[T0, T1, Transform2D.identity()], residual_px=np.zeros(3),
                       n_inliers=np.zeros(3, int), ecc=np.ones(3), method=np.array(["a"] * 3),
                       shape=(80, 100), reference=2)
    p = np.random.default_rng(7).uniform(0, 100, (5, 2))
    assert np.allclose(reg.between(1, 0)(T1(p)), T0(p))
    # a subset warp from the reference into frame 1 (its gradient part) carried into frame 0
    w = np.zeros((1, 6))
    w[0, [1, 2, 4, 5]] = [0.01, -0.02, 0.005, 0.003]
    A1 = np.eye(2) + w[0, [1, 2, 4, 5]].reshape(2, 2)
    got = reg.carry_warps(w, 1, 0)
    L = T0.matrix[:2, :2] @ np.linalg.inv(T1.matrix[:2, :2])
    assert np.allclose(np.eye(2) + got[0, [1, 2, 4, 5]].reshape(2, 2), L @ A1)
    assert got[0, 0] == w[0, 0] and got[0, 3] == w[0, 3]
