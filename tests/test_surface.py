"""Tests of semlab.surface on synthetic points made here."""

import numpy as np
import pytest

from semlab.camera import project_affine
from semlab.errors import GeometryError, SemlabError
from semlab.reconstruct import heights_from_tilts, parallax_height
from semlab.surface import (POINTS3D_COLUMNS, bootstrap_heights, fit_reference_plane,
                            height_sigma, height_trend, heights_above_plane, profile_along_line,
                            ransac_plane, read_points3d_csv, reference_surface, region_mask,
                            write_points3d_csv)

S = 0.03
PLANE = np.array([0.02, -0.01, 0.3])


def plane_with_bands(n=300, seed=0, frac=0.3, noise_um=0.0, one_sided=True):
    """Points on PLANE plus a fraction of extrusions (+0.05..0.3 µm), or +/- if not one_sided."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 15, n)
    y = rng.uniform(0, 11, n)
    h = np.zeros(n)
    out = rng.permutation(n)[: int(frac * n)]
    sign = 1.0 if one_sided else rng.choice([-1.0, 1.0], out.size)
    h[out] = sign * rng.uniform(0.05, 0.3, out.size)
    z = PLANE[0] * x + PLANE[1] * y + PLANE[2] + h + rng.normal(0, noise_um, n)
    return np.column_stack([x, y, z]), h


# ----------------------------------------------------------------------------- plane

def test_plane_recovery_with_30_percent_extrusions_noise_free():
    xyz, h = plane_with_bands()
    plane = fit_reference_plane(xyz)
    assert np.abs(plane - PLANE).max() < 1e-9
    assert np.abs(heights_above_plane(xyz, plane) - h).max() < 1e-9


def test_robust_plane_beats_least_squares_with_noise():
    xyz, h = plane_with_bands(n=400, seed=1, noise_um=0.005)
    robust = fit_reference_plane(xyz)
    lsq = fit_reference_plane(xyz, robust=False)
    z_r = heights_above_plane(xyz, robust)
    z_l = heights_above_plane(xyz, lsq)
    inl = h == 0
    assert abs(np.median(z_r[inl])) < 0.002  # robust plane sits on the flat surface
    assert abs(np.median(z_l[inl])) > 0.02  # least squares is lifted by the extrusions
    assert np.abs(robust[:2] - PLANE[:2]).max() < 5e-4


def test_height_sign_extrusion_positive_intrusion_negative():
    xyz, h = plane_with_bands(seed=2, frac=0.2, one_sided=False)
    z = heights_above_plane(xyz, fit_reference_plane(xyz))
    assert np.all(z[h > 0] > 0.04) and np.all(z[h < 0] < -0.04)
    assert np.allclose(z, h, atol=1e-9)


def test_plane_errors():
    xyz, _ = plane_with_bands(n=20)
    with pytest.raises(GeometryError, match="at least 3"):
        fit_reference_plane(xyz[:2])
    with pytest.raises(GeometryError, match=r"\(N, 3\)"):
        fit_reference_plane(xyz[:, :2])
    bad = xyz.copy()
    bad[0, 2] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        fit_reference_plane(bad)
    line = xyz.copy()
    line[:, 1] = 2 * line[:, 0]
    with pytest.raises(GeometryError, match="collinear"):
        fit_reference_plane(line)


# ----------------------------------------------------------------------------- reference surface

#: 5-95 % range of a normal sample in σ: the floor of any substrate spread.
NORMAL_5_95 = 2 * 1.6449


def tall_object_on_substrate(seed=0, n=900, sigma_px=0.05, tilts=(-9.0, 9.0), amp_um=20.0):
    """Matches of a Gaussian dome (``amp_um`` tall, σ 12 µm) on a tilted flat substrate.

    100 × 100 µm at 0.1 µm/px; 60 % of the points are on the dome. Returns pts (N, 2, 2),
    the true heights above the substrate (N,), the substrate mask, tilts and the z σ.
    """
    rng = np.random.default_rng(seed)
    s = 0.1
    n_dome = int(0.6 * n)
    r = 30 * np.sqrt(rng.uniform(0, 1, n_dome))
    a = rng.uniform(0, 2 * np.pi, n_dome)
    dome_xy = np.column_stack([50 + r * np.cos(a), 50 + r * np.sin(a)])
    sub_xy = rng.uniform(0, 100, (4 * (n - n_dome), 2))
    sub_xy = sub_xy[np.hypot(*(sub_xy - 50).T) > 32][: n - n_dome]
    xy = np.vstack([dome_xy, sub_xy])
    h = amp_um * np.exp(-np.sum((xy - 50) ** 2, axis=1) / (2 * 12.0 ** 2))
    h[n_dome:] = 0.0
    z = 0.03 * xy[:, 0] - 0.02 * xy[:, 1] + h  # substrate tilted on the stage
    xyz = np.column_stack([xy, z])
    pts = np.stack([project_affine(xyz, t, s, (500.0 + 7 * i, 500.0))
                    for i, t in enumerate(tilts)], 1)
    pts = pts + rng.normal(0, sigma_px, pts.shape)
    z_sig = height_sigma(sigma_px, tilts, s)
    return pts, h, np.arange(len(xy)) >= n_dome, tilts, s, z_sig


def test_dominant_plane_leaves_the_substrate_under_a_tall_object_flat():
    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate()
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    ref = reference_surface(xyz, z_sig)
    z = ref.heights(xyz)
    spread = np.ptp(np.percentile(z[sub], [5, 95]))
    assert ref.method == "dominant_plane"
    assert spread <= 1.1 * NORMAL_5_95 * z_sig  # the noise floor (3.29 σ), no plane left
    assert np.mean(ref.inliers[sub]) > 0.95 and np.mean(ref.inliers[~sub]) < 0.15
    assert abs(np.median(z[~sub] - h[~sub])) < 3 * z_sig  # the dome measured, not levelled
    # a robust fit through everything is tilted by the dome: many σ of spread
    z_all = heights_above_plane(xyz, fit_reference_plane(xyz))
    assert np.ptp(np.percentile(z_all[sub], [5, 95])) > 10 * z_sig


def test_dominant_plane_estimates_sigma_from_the_points():
    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate(seed=1)
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    ref = reference_surface(xyz)  # no σ given: least-median-of-squares scale
    z = ref.heights(xyz)
    assert 0.5 * z_sig < ref.threshold_um / 3 < 2 * z_sig
    assert np.ptp(np.percentile(z[sub], [5, 95])) <= 1.15 * NORMAL_5_95 * z_sig


def test_reference_region_rectangle_polygon_mask(tmp_path):
    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate(seed=2)
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    xy0 = pts[:, 0]
    rect = [xy0[:, 0].min(), xy0[:, 1].min(), xy0[:, 0].min() + 150, xy0[:, 1].max()]  # left band
    poly = [[rect[0], rect[1]], [rect[2], rect[1]], [rect[2], rect[3]], [rect[0], rect[3]]]
    m = np.zeros((1600, 1600), bool)
    m[int(rect[1]):int(rect[3]) + 1, int(np.ceil(rect[0])):int(rect[2]) + 1] = True
    inside = region_mask(rect, xy0)
    assert inside.sum() > 30 and np.all(sub[inside])
    assert np.array_equal(region_mask(poly, xy0), inside)
    assert np.mean(region_mask(m, xy0) == inside) > 0.99
    for region in (rect, poly, m):
        ref = reference_surface(xyz, z_sig, xy_px=xy0, region=region)
        assert ref.method == "region"
        z = ref.heights(xyz)
        assert np.ptp(np.percentile(z[sub], [5, 95])) <= 1.2 * NORMAL_5_95 * z_sig
    d = reference_surface(xyz, z_sig, xy_px=xy0, region=rect).to_dict()
    assert d["region"] == "rectangle" and d["n_in_region"] == inside.sum()
    assert 0.95 * inside.sum() <= d["n_inliers"] <= inside.sum()
    with pytest.raises(GeometryError, match="3 or more"):
        reference_surface(xyz, z_sig, xy_px=xy0, region=[0, 0, 1, 1])
    with pytest.raises(GeometryError, match="rectangle"):
        reference_surface(xyz, z_sig, xy_px=xy0, region=[[0, 0], [1, 1]])


def test_three_point_reference_plane():
    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate(seed=3)
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    xy0 = pts[:, 0]
    corners = xy0[sub][[np.argmin(xy0[sub, 0] + xy0[sub, 1]), np.argmax(xy0[sub, 0]),
                        np.argmax(xy0[sub, 1])]]
    ref = reference_surface(xyz, z_sig, xy_px=xy0, three_points_px=corners)
    assert ref.method == "three_points" and ref.n_inliers == 15
    z = ref.heights(xyz)
    # three picked points (5 matches each) are noisier than a fit to the whole substrate
    assert abs(np.median(z[sub])) < 2 * z_sig
    assert np.ptp(np.percentile(z[sub], [5, 95])) <= 1.5 * NORMAL_5_95 * z_sig
    with pytest.raises(GeometryError, match="not both"):
        reference_surface(xyz, z_sig, xy_px=xy0, region=[0, 0, 9, 9], three_points_px=corners)
    with pytest.raises(GeometryError, match="collinear"):
        reference_surface(xyz, z_sig, xy_px=xy0, three_points_px=[[0, 0], [1, 1], [2, 2]])


def test_ransac_plane_exact_and_errors():
    xyz, h = plane_with_bands(n=200, frac=0.6)  # 60 % extrusions: more than a robust fit takes
    plane, inl, _ = ransac_plane(xyz, 1e-6)
    assert np.abs(plane - PLANE).max() < 1e-9 and np.array_equal(inl, h == 0)
    with pytest.raises(GeometryError, match="common plane"):
        ransac_plane(xyz[:10], 1e-6, min_inliers=10)


def test_bootstrap_with_the_reference_choice():
    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate(seed=4, n=300)
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    ref = reference_surface(xyz, z_sig)
    sig_ref = bootstrap_heights(pts, tilts, s, n_boot=50, progress=False, reference=ref)
    sig_all = bootstrap_heights(pts, tilts, s, n_boot=50, progress=False)
    # resampling the substrate only moves its plane by ~σ/sqrt(N); the robust fit through the
    # dome moves by far more
    assert np.median(sig_ref[sub]) < 0.5 * z_sig < np.median(sig_all)


# ----------------------------------------------------------------------------- errors

@pytest.mark.parametrize("tilts, s0, s1", [((-5.0, 5.0), 0.05, 0.05), ((0.0, 8.0), 0.03, 0.1)])
def test_height_sigma_two_views_monte_carlo(tilts, s0, s1):
    rng = np.random.default_rng(0)
    m = 20000
    x, z = 4.0, 0.2
    u = [(x * np.cos(np.deg2rad(t)) + z * np.sin(np.deg2rad(t))) / S for t in tilts]
    zs = parallax_height(u[0] + rng.normal(0, s0, m), u[1] + rng.normal(0, s1, m),
                         tilts[0], tilts[1], S)
    pred = height_sigma(np.array([[s0, s1]]), tilts, S)[0]
    assert abs(np.std(zs) / pred - 1) < 0.03
    # the documented closed form
    t0, t1 = np.deg2rad(tilts)
    closed = (S * np.sqrt(s0 ** 2 * np.cos(t1) ** 2 + s1 ** 2 * np.cos(t0) ** 2)
              / abs(np.sin(t1 - t0)))
    assert abs(pred - closed) < 1e-12


def test_height_sigma_three_views_monte_carlo():
    rng = np.random.default_rng(1)
    tilts = (-5.0, 0.0, 5.0)
    n = 4000
    xyz = np.column_stack([rng.uniform(0, 15, n), rng.uniform(0, 11, n), rng.uniform(0, 0.3, n)])
    c = np.array([[256.0, 192.0]] * 3)
    pts = np.stack([project_affine(xyz, t, S, c[0]) for t in tilts], 1)
    noisy = pts + np.concatenate([rng.normal(0, 0.05, (n, 3, 1)), np.zeros((n, 3, 1))], 2)
    z = heights_from_tilts(noisy, tilts, S, center_px=c).xyz_um[:, 2]
    pred = height_sigma(0.05, tilts, S)
    assert isinstance(pred, float)
    assert abs(np.std(z - xyz[:, 2]) / pred - 1) < 0.05
    per_point = height_sigma(np.full(n, 0.05), tilts, S)
    assert per_point.shape == (n,) and np.allclose(per_point, pred)


def test_height_sigma_errors():
    with pytest.raises(GeometryError, match="two different tilts"):
        height_sigma(0.1, (5.0, 5.0), S)
    with pytest.raises(GeometryError, match="sigma_px"):
        height_sigma(np.ones((4, 3)), (-5.0, 5.0), S)
    with pytest.raises(GeometryError, match="positive"):
        height_sigma(-0.1, (-5.0, 5.0), S)
    with pytest.raises(GeometryError, match="pixel_size_um"):
        height_sigma(0.1, (-5.0, 5.0), -1.0)


def _views(xyz, tilts):
    return np.stack([project_affine(xyz, t, S, (256.0 + 5 * i, 192.0))
                     for i, t in enumerate(tilts)], 1)


def test_bootstrap_heights_noise_free_is_zero():
    xyz, _ = plane_with_bands(n=120, seed=3)
    sd = bootstrap_heights(_views(xyz, (-5.0, 5.0)), (-5.0, 5.0), S, n_boot=30, progress=False)
    assert sd.shape == (120,)
    assert sd.max() < 1e-9


def test_bootstrap_heights_with_matching_noise_matches_propagation():
    xyz, _ = plane_with_bands(n=150, seed=4)
    tilts = (-5.0, 5.0)
    sd = bootstrap_heights(_views(xyz, tilts), tilts, S, n_boot=200, sigma_px=0.05, seed=1,
                           progress=False)
    pred = height_sigma(0.05, tilts, S)
    assert 0.85 < np.median(sd) / pred < 1.25


def test_bootstrap_heights_plane_resampling_grows_with_noise():
    """Points-only resampling: noisy inliers make the plane, hence all heights, uncertain."""
    xyz, _ = plane_with_bands(n=150, seed=5, noise_um=0.01)
    tilts = (-5.0, 5.0)
    sd = bootstrap_heights(_views(xyz, tilts), tilts, S, n_boot=100, progress=False)
    assert 1e-4 < np.median(sd) < 0.01  # ~ 0.01 µm / sqrt(N) scale


def test_bootstrap_heights_errors():
    xyz, _ = plane_with_bands(n=20)
    pts = _views(xyz, (-5.0, 5.0))
    with pytest.raises(GeometryError, match="n_boot"):
        bootstrap_heights(pts, (-5.0, 5.0), S, n_boot=1, progress=False)
    with pytest.raises(GeometryError, match="sigma_px"):
        bootstrap_heights(pts, (-5.0, 5.0), S, sigma_px=np.ones(7), progress=False)


# ----------------------------------------------------------------------------- profile

def test_profile_picks_points_and_distances():
    g = np.arange(0.0, 6.01, 0.1)
    xx, yy = np.meshgrid(g, g)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    z = np.sin(xy[:, 0]) + 0.1 * xy[:, 1]
    p0, p1 = np.array([1.0, 1.0]), np.array([4.0, 5.0])  # length 5, direction (0.6, 0.8)
    prof = profile_along_line(xy, z, p0, p1, width_um=0.5, n_bins=5)
    d = np.array([0.6, 0.8])
    along = (xy - p0) @ d
    across = (xy - p0) @ np.array([0.8, -0.6])
    expect = np.nonzero((along >= 0) & (along <= 5) & (np.abs(across) <= 0.25))[0]
    assert set(prof["index"].tolist()) == set(expect.tolist())
    assert np.all(np.diff(prof["distance_um"]) >= 0)
    assert np.allclose(prof["distance_um"], along[prof["index"]])
    assert np.allclose(prof["z_um"], z[prof["index"]])
    assert np.all(np.abs(prof["offset_um"]) <= 0.25)
    # binned means agree with a direct computation
    assert prof["bin_count"].sum() == len(expect)
    k = 2
    sel = (prof["distance_um"] >= 2.0) & (prof["distance_um"] < 3.0)
    assert prof["bin_count"][k] == sel.sum()
    assert np.isclose(prof["bin_mean_um"][k], prof["z_um"][sel].mean())
    assert np.isclose(prof["bin_std_um"][k], prof["z_um"][sel].std())
    assert np.allclose(prof["bin_center_um"], [0.5, 1.5, 2.5, 3.5, 4.5])


def test_profile_errors():
    xy = np.zeros((5, 2))
    z = np.zeros(5)
    with pytest.raises(GeometryError, match="same point"):
        profile_along_line(xy, z, (1, 1), (1, 1), 0.5)
    with pytest.raises(GeometryError, match="width_um"):
        profile_along_line(xy, z, (0, 0), (1, 1), 0.0)
    with pytest.raises(GeometryError, match=r"\(N, 2\)"):
        profile_along_line(xy, z[:3], (0, 0), (1, 1), 0.5)
    with pytest.raises(GeometryError, match="n_bins"):
        profile_along_line(xy, z, (0, 0), (1, 1), 0.5, n_bins=0)
    with pytest.raises(GeometryError, match="finite"):
        profile_along_line(xy, z, (0, np.nan), (1, 1), 0.5)


# ----------------------------------------------------------------------------- trend

def test_height_trend_more_extrusion_at_high_y():
    rng = np.random.default_rng(6)
    n = 400
    x = rng.uniform(0, 15, n)
    y = rng.uniform(0, 11, n)
    base = 0.004 * x - 0.002 * y + rng.normal(0, 0.002, n)  # 2 nm noise
    ext = np.where(rng.random(n) < 0.6 * y / 11, rng.uniform(0.05, 0.3, n), 0.0)
    tr = height_trend(np.column_stack([x, y, base + ext]))
    assert abs(tr["dz_dx"] - 0.004) < 1e-3 and abs(tr["dz_dy"] + 0.002) < 1e-3
    assert tr["n"] == n
    # correlations on heights above the plane show where the extrusions are
    raw = np.column_stack([x, y, base + ext])
    h = heights_above_plane(raw, fit_reference_plane(raw))
    th = height_trend(np.column_stack([x, y, h]))
    assert abs(th["dz_dx"]) < 1e-3 and abs(th["dz_dy"]) < 1e-3
    assert th["spearman_r_y"] > 0.1 and th["spearman_p_y"] < 0.01
    assert th["pearson_r_y"] > 0.1
    trx = height_trend(np.column_stack([x, y, ext]))  # no x dependence
    assert abs(trx["spearman_r_x"]) < 0.15


def test_height_trend_constant_raises():
    xyz = np.column_stack([np.arange(5.0), np.arange(5.0) ** 2, np.ones(5)])
    with pytest.raises(GeometryError, match="equal"):
        height_trend(xyz)


# ----------------------------------------------------------------------------- CSV

def _table(n=6, seed=0):
    rng = np.random.default_rng(seed)
    return (np.arange(10, 10 + n), rng.uniform(0, 500, (n, 2, 2)), rng.normal(size=(n, 3)),
            rng.uniform(0, 0.01, n))


def _nv(n=6):
    """(n,) views per point: 3, 2, 3, 2, ..."""
    return np.where(np.arange(n) % 2, 2, 3)


def test_points3d_csv_round_trip(tmp_path):
    ids, pts, xyz, err = _table()
    err[2] = np.nan
    path = write_points3d_csv(tmp_path / "out" / "points3d.csv", ids, pts, xyz, err,
                              n_views=_nv())
    assert path.read_text().splitlines()[0] == ",".join(POINTS3D_COLUMNS)
    assert POINTS3D_COLUMNS[-1] == "n_views"      # added last: readers by position still work
    back = read_points3d_csv(path)
    assert list(back) == list(POINTS3D_COLUMNS)
    assert back["n_views"].dtype.kind == "i" and np.array_equal(back["n_views"], _nv())
    assert path.read_text().splitlines()[2].endswith(",2")
    assert back["point_id"].dtype.kind == "i" and np.array_equal(back["point_id"], ids)
    assert np.allclose(back["x_px"], pts[:, 0, 0], rtol=1e-9)  # view 0
    assert np.allclose(back["y_px"], pts[:, 0, 1], rtol=1e-9)
    got = np.column_stack([back["x_um"], back["y_um"], back["z_um"]])
    assert np.allclose(got, xyz, rtol=1e-9, atol=1e-12)
    assert np.allclose(back["z_err_um"], err, rtol=1e-9, equal_nan=True)


def test_points3d_csv_refuses_overwrite(tmp_path):
    ids, pts, xyz, err = _table()
    path = tmp_path / "points3d.csv"
    write_points3d_csv(path, ids, pts, xyz, err, n_views=_nv())
    before = path.read_text()
    with pytest.raises(SemlabError, match="overwrite=True"):
        write_points3d_csv(path, ids, pts, xyz * 2, err, n_views=_nv())
    assert path.read_text() == before
    write_points3d_csv(path, ids, pts, xyz * 2, err, overwrite=True, n_views=_nv())
    assert np.allclose(read_points3d_csv(path)["x_um"], 2 * xyz[:, 0])


def test_points3d_csv_errors(tmp_path):
    ids, pts, xyz, err = _table()
    with pytest.raises(SemlabError, match="duplicates"):
        write_points3d_csv(tmp_path / "a.csv", np.zeros(6, int), pts, xyz, err, n_views=_nv())
    with pytest.raises(SemlabError, match="inconsistent"):
        write_points3d_csv(tmp_path / "b.csv", ids, pts, xyz[:4], err, n_views=_nv())
    with pytest.raises(SemlabError, match="inconsistent"):
        write_points3d_csv(tmp_path / "b.csv", ids, pts, xyz, err, n_views=_nv(4))
    with pytest.raises(SemlabError, match="n_views is required"):
        write_points3d_csv(tmp_path / "b.csv", ids, pts, xyz, err)
    with pytest.raises(SemlabError, match="integers >= 1"):
        write_points3d_csv(tmp_path / "b.csv", ids, pts, xyz, err, n_views=_nv() - 2)
    with pytest.raises(SemlabError, match="integers >= 1"):
        write_points3d_csv(tmp_path / "b.csv", ids, pts, xyz, err, n_views=_nv() + 0.5)
    bad = tmp_path / "bad.csv"
    bad.write_text("id,x,y\n1,2,3\n")
    with pytest.raises(SemlabError, match="header"):
        read_points3d_csv(bad)
    with pytest.raises(SemlabError, match="does not exist"):
        read_points3d_csv(tmp_path / "missing.csv")
    with pytest.raises(SemlabError, match="commas"):
        write_points3d_csv(tmp_path / "c.csv", np.array(["a,b", "c"]), pts[:2], xyz[:2], err[:2],
                           n_views=_nv(2))
    header = ",".join(POINTS3D_COLUMNS)
    short = tmp_path / "short.csv"
    short.write_text(header + "\n1,2,3,4,5,6,7\n")
    with pytest.raises(SemlabError, match="8 fields"):
        read_points3d_csv(short)
    text = tmp_path / "text.csv"
    text.write_text(header + "\n1,2,3,4,5,six,7,2\n")
    with pytest.raises(SemlabError, match="non-numeric"):
        read_points3d_csv(text)
    text.write_text(header + "\n1,2,3,4,5,6,7,2.5\n")
    with pytest.raises(SemlabError, match="non-numeric"):
        read_points3d_csv(text)


def test_points3d_csv_without_n_views_is_still_read(tmp_path):
    """A file from before the n_views column: the other columns, no n_views entry."""
    old = tmp_path / "old.csv"
    old.write_text(",".join(POINTS3D_COLUMNS[:-1]) + "\n4,1,2,3,4,5,6\n")
    back = read_points3d_csv(old)
    assert "n_views" not in back and back["point_id"].tolist() == [4]
    assert back["z_err_um"].tolist() == [6.0]


def test_points3d_csv_string_ids(tmp_path):
    _, pts, xyz, err = _table(n=3)
    ids = np.array(["p1", "p2", "crack7_a"])
    back = read_points3d_csv(write_points3d_csv(tmp_path / "s.csv", ids, pts, xyz, err,
                                                n_views=_nv(3)))
    assert back["point_id"].tolist() == ids.tolist()


def test_show_reference_surface_draws_points_and_reference():
    import matplotlib.pyplot as plt

    from semlab.plots import show_reference_surface

    pts, h, sub, tilts, s, z_sig = tall_object_on_substrate(seed=5, n=200)
    xyz = heights_from_tilts(pts, tilts, s).xyz_um
    ref = reference_surface(xyz, z_sig)
    img = np.random.default_rng(0).random((1600, 1600))
    ax = show_reference_surface(img, pts[:, 0], ref.heights(xyz), ref.inliers)
    points, outlines = ax.collections[:2]
    assert len(points.get_offsets()) == 200 and len(outlines.get_offsets()) == ref.n_inliers
    lo, hi = points.get_clim()
    assert lo == -hi and 0 < hi < 20 * z_sig  # the reference's scatter sets the scale
    plt.close(ax.figure)


def test_crack_profiles_follow_each_crack_and_skip_those_without_a_direction():
    """One profile per crack with two or more distinct points, along its own line; a crack
    left with one point (its other clicks not refined) or with coincident points gives none
    instead of an error (notebook 04 on a three-view synthetic run stopped there)."""
    from semlab.surface import crack_profiles

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (300, 2))
    z = np.where(np.abs(xy[:, 1] - xy[:, 0]) < 0.3, 0.1, 0.0)      # a ridge along y = x
    xyz = np.column_stack([xy, z])
    cid = np.full(len(xy), -1)
    on = np.flatnonzero(np.abs(xy[:, 1] - xy[:, 0]) < 0.05)[:6]
    cid[on] = 0                                                      # crack 0 along y = x
    cid[np.flatnonzero(cid < 0)[0]] = 1                              # crack 1: a single point
    two = np.flatnonzero(cid < 0)[:2]
    xyz[two[1], :2] = xyz[two[0], :2]
    cid[two] = 2                                                     # crack 2: coincident
    out = crack_profiles(xyz, z, cid, width_um=0.3)
    assert [c for c, _ in out] == [0]
    prof = out[0][1]
    assert np.all(np.abs(prof["offset_um"]) <= 0.15) and np.all(z[prof["index"]] > 0)
    assert crack_profiles(xyz, z, None) == [] and crack_profiles(xyz, z, np.full(len(z), -1)) == []
