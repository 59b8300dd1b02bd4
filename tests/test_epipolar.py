"""Epipolar geometry on synthetic perspective and affine (SEM) stereo pairs."""

import numpy as np
import pytest

from semlab import epipolar as ep
from semlab.camera import project_affine, project_perspective, rotation_about_axis
from semlab.errors import GeometryError

K = np.array([[1500.0, 0.0, 640.0], [0.0, 1500.0, 480.0], [0.0, 0.0, 1.0]])
R = rotation_about_axis([0.2, 1.0, 0.1], np.deg2rad(8.0))
T = np.array([-0.6, 0.05, 0.1])
CENTER = (255.5, 191.5)


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def true_F():
    Ki = np.linalg.inv(K)
    F = Ki.T @ skew(T) @ R @ Ki
    return F / np.linalg.norm(F)


def perspective_pair(n=60, noise_px=0.0, seed=0):
    """Points with depth relief (z 4..7) seen by K[I|0] and K[R|t]."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1, -1, 4], [1, 1, 7], (n, 3))
    x0 = project_perspective(X, K, np.eye(3), np.zeros(3))
    x1 = project_perspective(X, K, R, T)
    return x0 + rng.normal(0, noise_px, x0.shape), x1 + rng.normal(0, noise_px, x1.shape)


def affine_pair(n=50, noise_px=0.0, seed=0, relief_um=0.3, planar=False):
    """SEM views at -5° and +5°, 0.03 µm/px, heights within ±relief_um (or on a tilted plane)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform([-7, -5], [7, 5], (n, 2))
    z = 0.02 * xy[:, 0] - 0.01 * xy[:, 1] if planar else rng.uniform(-relief_um, relief_um, n)
    X = np.column_stack([xy, z])
    x0 = project_affine(X, -5.0, 0.03, CENTER)
    x1 = project_affine(X, 5.0, 0.03, CENTER)
    return x0 + rng.normal(0, noise_px, x0.shape), x1 + rng.normal(0, noise_px, x1.shape)


def algebraic(F, x0, x1):
    h0 = np.column_stack([x0, np.ones(len(x0))])
    h1 = np.column_stack([x1, np.ones(len(x1))])
    return np.sum(h1 * (h0 @ F.T), axis=1)


def same_up_to_scale(A, B):
    A = A / np.linalg.norm(A)
    B = B / np.linalg.norm(B)
    return min(np.linalg.norm(A - B), np.linalg.norm(A + B))


# ----------------------------------------------------------------------------- eight-point

def test_8point_noise_free_is_exact():
    x0, x1 = perspective_pair()
    F = ep.fundamental_8point(x0, x1)
    assert np.abs(algebraic(F, x0, x1)).max() < 1e-10
    assert same_up_to_scale(F, true_F()) < 1e-10
    assert np.linalg.norm(F) == pytest.approx(1.0)
    assert np.linalg.svd(F, compute_uv=False)[2] < 1e-12


def test_8point_with_exactly_eight_points():
    x0, x1 = perspective_pair(n=8)
    F = ep.fundamental_8point(x0, x1)
    assert same_up_to_scale(F, true_F()) < 1e-8


def test_8point_noisy_is_close():
    x0, x1 = perspective_pair(n=100, noise_px=0.5, seed=3)
    F = ep.fundamental_8point(x0, x1)
    d = ep.sampson_distance(F, x0, x1)
    assert 0.1 < np.sqrt(np.mean(d ** 2)) < 0.6   # ≈ noise·√2·(fraction of free dims)
    # the true F fits the noisy points about as well: the estimate is consistent
    assert np.median(d) <= np.median(ep.sampson_distance(true_F(), x0, x1)) * 1.05


def test_8point_on_affine_general_scene_gives_the_affine_F():
    x0, x1 = affine_pair()
    F8 = ep.fundamental_8point(x0, x1)
    assert same_up_to_scale(F8, ep.fundamental_affine(x0, x1)) < 1e-8


@pytest.mark.parametrize("fit", [ep.fundamental_8point, ep.fundamental_affine])
def test_too_few_points(fit):
    x0, x1 = perspective_pair(n=3)
    with pytest.raises(GeometryError, match="at least"):
        fit(x0, x1)


@pytest.mark.parametrize("fit", [ep.fundamental_8point, ep.fundamental_affine])
def test_nan_duplicates_shapes_collinear(fit):
    x0, x1 = perspective_pair(n=20)
    bad = x0.copy()
    bad[3, 1] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        fit(bad, x1)
    dup = x1.copy()
    dup[5] = dup[2]
    with pytest.raises(GeometryError, match="duplicate"):
        fit(x0, dup)
    with pytest.raises(GeometryError, match="same number"):
        fit(x0, x1[:-1])
    with pytest.raises(GeometryError, match=r"\(N, 2\)"):
        fit(x0.ravel(), x1.ravel())
    line = np.column_stack([np.linspace(0, 100, 20), np.linspace(5, 60, 20)])
    with pytest.raises(GeometryError, match="collinear"):
        fit(line, x1)


def test_affine_planar_is_degenerate_for_8point_and_says_so():
    x0, x1 = affine_pair(planar=True)
    with pytest.raises(GeometryError, match=r"rank < 8.*fundamental_affine"):
        ep.fundamental_8point(x0, x1)
    # with click noise the null space is still two-dimensional
    x0n, x1n = affine_pair(planar=True, noise_px=0.5, seed=1)
    with pytest.raises(GeometryError, match="rank < 8"):
        ep.fundamental_8point(x0n, x1n)


def test_affine_planar_is_degenerate_for_affine_too():
    x0, x1 = affine_pair(planar=True)
    with pytest.raises(GeometryError, match="height relief is not above their position"):
        ep.fundamental_affine(x0, x1)


def test_perspective_planar_scene_raises():
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-1, 1, (30, 2)), np.full(30, 5.0)])
    x0 = project_perspective(X, K, np.eye(3), np.zeros(3))
    x1 = project_perspective(X, K, R, T)
    with pytest.raises(GeometryError, match="coplanar"):
        ep.fundamental_8point(x0, x1)


# ----------------------------------------------------------------------------- affine

def test_affine_F_exact_noise_free_and_has_affine_form():
    x0, x1 = affine_pair()
    F = ep.fundamental_affine(x0, x1)
    assert np.abs(F[:2, :2]).max() == 0.0
    assert np.abs(algebraic(F, x0, x1)).max() < 1e-10
    # tilt about the image y axis: corresponding points share their row, F ∝ [[0,0,0],[0,0,1],[0,-1,0]]
    expected = np.array([[0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    assert same_up_to_scale(F, expected) < 1e-10
    assert ep.sampson_distance(F, x0, x1).max() < 1e-9


def test_affine_tilt_axis_horizontal_lines_and_rotated_axis():
    x0, x1 = affine_pair()
    axis, line = ep.affine_tilt_axis(ep.fundamental_affine(x0, x1))
    assert np.allclose(axis, 90.0, atol=1e-8) and np.allclose(line % 180, 0.0, atol=1e-8)
    # rotate both images by 25° (tilt axis no longer parallel to the image y axis)
    a = np.deg2rad(25.0)
    Q = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    axis, line = ep.affine_tilt_axis(ep.fundamental_affine(x0 @ Q.T, x1 @ Q.T))
    assert np.allclose(axis, 115.0, atol=1e-8) and np.allclose(line, 25.0, atol=1e-8)


def test_affine_tilt_axis_rejects_perspective_F():
    with pytest.raises(GeometryError, match="affine"):
        ep.affine_tilt_axis(true_F())


# ----------------------------------------------------------------------------- geometry

def test_epipoles_lie_on_all_epipolar_lines():
    x0, x1 = perspective_pair()
    F = ep.fundamental_8point(x0, x1)
    e0, e1 = ep.epipoles(F)
    assert np.abs(F @ e0).max() < 1e-12 and np.abs(F.T @ e1).max() < 1e-12
    L1 = ep.epipolar_lines(F, x0, from_view=0)
    L0 = ep.epipolar_lines(F, x1, from_view=1)
    assert np.allclose(np.hypot(L1[:, 0], L1[:, 1]), 1.0)
    assert np.abs(L1 @ e1).max() < 1e-10 and np.abs(L0 @ e0).max() < 1e-10
    # true epipole in view 1 is the image of camera 0's centre: K t
    e1_true = K @ T
    assert abs(abs(e1 @ e1_true) / np.linalg.norm(e1_true) - 1) < 1e-10
    # points lie on their epipolar lines, distances in px
    h1 = np.column_stack([x1, np.ones(len(x1))])
    assert np.abs(np.sum(L1 * h1, axis=1)).max() < 1e-8


def test_affine_epipoles_at_infinity():
    x0, x1 = affine_pair()
    e0, e1 = ep.epipoles(ep.fundamental_affine(x0, x1))
    assert abs(e0[2]) < 1e-12 and abs(e1[2]) < 1e-12
    assert abs(abs(e0[0]) - 1) < 1e-10   # along x: horizontal epipolar lines


def test_distances_in_pixels():
    x0, x1 = affine_pair()
    F = ep.fundamental_affine(x0, x1)
    shifted = x1 + np.array([0.0, 2.0])          # 2 px across the horizontal epipolar lines
    assert np.allclose(ep.symmetric_epipolar_distance(F, x0, shifted), 2.0)
    assert np.allclose(ep.sampson_distance(F, x0, shifted), 2.0 / np.sqrt(2))
    along = x1 + np.array([3.0, 0.0])            # along the lines: no epipolar error
    assert ep.symmetric_epipolar_distance(F, x0, along).max() < 1e-9


def test_epipolar_lines_bad_view():
    with pytest.raises(GeometryError, match="from_view"):
        ep.epipolar_lines(true_F(), np.zeros((2, 2)), from_view=2)


# ----------------------------------------------------------------------------- RANSAC

@pytest.mark.parametrize("model", ["8point", "affine"])
def test_ransac_rejects_20_percent_outliers(model):
    rng = np.random.default_rng(7)
    if model == "8point":
        x0, x1 = perspective_pair(n=150, noise_px=0.3, seed=7)
    else:
        x0, x1 = affine_pair(n=150, noise_px=0.3, seed=7, relief_um=3.0)
    out = rng.random(len(x0)) < 0.2
    x1 = x1.copy()
    x1[out] += rng.uniform(8, 60, (out.sum(), 2)) * rng.choice([-1, 1], (out.sum(), 2))
    F, inl = ep.ransac_fundamental(x0, x1, model=model, threshold_px=1.5, n_iter=1000)
    assert inl.dtype == bool and inl.shape == (len(x0),)
    assert not inl[out].any()
    assert inl[~out].mean() > 0.95
    assert ep.sampson_distance(F, x0[~out], x1[~out]).max() < 1.5
    fit = ep.fundamental_8point if model == "8point" else ep.fundamental_affine
    # plain least squares on everything is ruined by the outliers (or cannot even tell the
    # best epipolar geometry from the next one)
    try:
        assert np.median(ep.sampson_distance(fit(x0, x1), x0[~out], x1[~out])) > 1.5
    except GeometryError as exc:
        assert "undetermined" in str(exc)


def test_ransac_reproducible_and_errors():
    x0, x1 = perspective_pair(n=40, noise_px=0.2)
    a = ep.ransac_fundamental(x0, x1, n_iter=200, seed=4)
    b = ep.ransac_fundamental(x0, x1, n_iter=200, seed=4)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    with pytest.raises(GeometryError, match="model"):
        ep.ransac_fundamental(x0, x1, model="homography")
    with pytest.raises(GeometryError, match="threshold_px"):
        ep.ransac_fundamental(x0, x1, threshold_px=0)
    rng = np.random.default_rng(0)
    with pytest.raises(GeometryError, match="no consensus"):
        ep.ransac_fundamental(rng.uniform(0, 500, (40, 2)), rng.uniform(0, 500, (40, 2)),
                              threshold_px=1e-6, n_iter=50)


# ----------------------------------------------------------------------------- stability

def test_stability_shapes_and_trend():
    x0, x1 = perspective_pair(n=120, noise_px=0.5, seed=11)
    sizes = [10, 30, 100]
    st = ep.stability(x0, x1, sizes, n_resamples=20, progress=False)
    for key in ("f_angle_deg_median", "f_angle_deg_iqr", "epipole_angle_deg_median",
                "epipole_angle_deg_iqr", "sampson_px_median", "n_failed"):
        assert st[key].shape == (3,)
    assert np.array_equal(st["sizes"], sizes)
    f = st["f_angle_deg_median"]
    assert f[0] > f[1] > f[2] > 0
    assert st["sampson_px_median"][0] > st["sampson_px_median"][2]
    # noise-free: every subset gives F(all) exactly
    c0, c1 = perspective_pair(n=60)
    st0 = ep.stability(c0, c1, [8, 30], n_resamples=5, progress=False)
    assert st0["f_angle_deg_median"].max() < 1e-6
    # more noise, larger disagreement
    n0, n1 = perspective_pair(n=120, noise_px=2.0, seed=11)
    assert ep.stability(n0, n1, [30], n_resamples=20, progress=False)["f_angle_deg_median"][0] > f[1]


def test_stability_affine_and_bad_sizes():
    x0, x1 = affine_pair(n=80, noise_px=0.2, relief_um=3.0)
    st = ep.stability(x0, x1, [6, 40], n_resamples=10, model="affine", progress=False)
    assert st["epipole_angle_deg_median"][0] > st["epipole_angle_deg_median"][1]
    with pytest.raises(GeometryError, match="sizes"):
        ep.stability(x0, x1, [3], model="affine", progress=False)
    with pytest.raises(GeometryError, match="sizes"):
        ep.stability(x0, x1, [500], progress=False)
