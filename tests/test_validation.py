import numpy as np
import pytest

from semlab import synth, validation
from semlab.errors import SemlabError


def test_height_errors_remove_plane_only():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (200, 2))
    zt = rng.normal(0, 0.1, 200)
    noise = rng.normal(0, 0.004, 200)
    ze = zt + 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + 0.3 + noise
    r = validation.height_errors(ze, zt, xy)
    assert r["rmse_um"] == pytest.approx(np.std(noise), rel=0.1)
    # a wrong relief (scaled heights) is not removed by the plane
    r2 = validation.height_errors(1.2 * zt, zt, xy)
    assert r2["rmse_um"] > 0.015
    with pytest.raises(SemlabError):
        validation.height_errors([1, 2], [1, 2])


def test_true_heights_and_tracks_match_truth_points(small_experiment_master):
    root = small_experiment_master
    t = synth.read_truth_points(root / "truth")
    grid = t["is_particle"] == 0
    p0 = np.column_stack([t["v0_x_px"], t["v0_y_px"]])[grid]
    z = validation.true_height_at(root, p0)
    assert np.median(np.abs(z - t["z_um"][grid])) < 0.005
    n_last = max(int(k[1:].split("_")[0]) for k in t if k.startswith("f") and k.endswith("_x_px"))
    last = np.column_stack([t[f"f{n_last}_x_px"], t[f"f{n_last}_y_px"]])[grid]
    pos = validation.true_track_positions(root, last)
    assert pos.shape == (n_last + 1, grid.sum(), 2)
    for n in range(n_last + 1):
        true_n = np.column_stack([t[f"f{n}_x_px"], t[f"f{n}_y_px"]])[grid]
        assert np.median(np.hypot(*(pos[n] - true_n).T)) < 0.01
    with pytest.raises(SemlabError, match="no truth"):
        validation.true_height_at(root / "end_state", p0)


def test_true_tracks_of_a_drifted_series_are_in_each_frames_own_pixels(tmp_path):
    """With stage and scan drift (synth --drift) every frame but the last is moved: the
    true track positions are where the material points appear in each drifted frame, as
    truth/points.csv has them (before, the undrifted positions: 'errors' of ~15 px on
    tracks that were right)."""
    root = tmp_path / "exp"
    synth.make_experiment(root, seed=0, size=(96, 128), tilts_deg=(), n_frames=3, n_clicks=0,
                          drift_shift_px=12.0, drift_rotation_deg=1.0, drift_scale=0.003,
                          scan_drift_px=0.5, progress=False)
    t = synth.read_truth_points(root / "truth")
    grid = t["is_particle"] == 0
    last = np.column_stack([t["f2_x_px"], t["f2_y_px"]])[grid]
    pos = validation.true_track_positions(root, last)
    moved = []
    for n in range(3):
        true_n = np.column_stack([t[f"f{n}_x_px"], t[f"f{n}_y_px"]])[grid]
        assert np.median(np.hypot(*(pos[n] - true_n).T)) < 0.01
        moved.append(np.median(np.hypot(*(true_n - last).T)))
    assert min(moved[:2]) > 5            # the drift is there to be got right


def test_robust_gauge_plane_ignores_gross_errors():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, (200, 2))
    zt = rng.normal(0, 0.1, 200)
    sd = 0.004
    ze = zt + 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + 0.3 + rng.normal(0, sd, 200)
    bad = np.argsort(xy[:, 0])[-4:]  # 4 gross errors at one edge: they tilt an lsq plane
    zb = ze.copy()
    zb[bad] += 1.0
    inl = np.ones(200, bool)
    inl[bad] = False
    # the right answer: the plane of the inliers alone
    ref = validation.height_errors(ze[inl], zt[inl], xy[inl])["err_um"]
    lsq = validation.height_errors(zb, zt, xy)["err_um"][inl]
    rob = validation.height_errors(zb, zt, xy, plane="robust")["err_um"][inl]
    assert np.max(np.abs(rob - ref)) < 0.25 * sd
    assert np.max(np.abs(lsq - ref)) > 10 * sd
    # without gross errors the robust plane is the lsq plane up to a fraction of the noise
    c_lsq = validation.height_errors(ze, zt, xy)
    c_rob = validation.height_errors(ze, zt, xy, plane="robust")
    assert np.max(np.abs(c_rob["err_um"] - c_lsq["err_um"])) < 0.1 * sd
    assert c_lsq["rmse_um"] <= c_rob["rmse_um"] < 1.001 * c_lsq["rmse_um"]
    # without positions the robust gauge is a robust mean
    m = validation.height_errors(zb, zt, plane="robust")["err_um"]
    assert abs(np.median(m[inl])) < 0.1 * np.std(ze - zt)
    with pytest.raises(SemlabError, match="plane"):
        validation.height_errors(ze, zt, xy, plane="median")


def test_subset_model_bias_known_answers():
    """The first-order bias of a subset on a known field: none where the shape function
    spans the field, the mean of the quadratic term for a curved one, none for a half
    subset that does not reach a step, and less information in a half than in a square."""
    yy, xx = np.mgrid[0:80, 0:100].astype(float)
    rng = np.random.default_rng(3)
    w = rng.uniform(0.1, 2.0, xx.shape)
    pts = np.array([[50.0, 40.0], [30.3, 25.6], [70.0, 55.0]])
    lin = 0.3 + 0.01 * xx - 0.02 * yy
    b, _ = validation.subset_model_bias(lin, pts, 10, weight=w)
    assert np.max(np.abs(b)) < 1e-9                      # any weights: affine spans it
    a, h = 2e-3, 7
    quad = lin + a * (xx - 50) ** 2
    b, _ = validation.subset_model_bias(quad, pts[:1], h)
    assert b[0] == pytest.approx(a * h * (h + 1) / 3, rel=1e-9)
    bq, _ = validation.subset_model_bias(quad, pts, h, weight=w, quadratic=True)
    assert np.max(np.abs(bq)) < 1e-9                     # a second-order shape spans it
    step = lin + 0.5 * (xx >= 53)                        # a step 3 px right of the centre
    b_full, v_full = validation.subset_model_bias(step, pts[:1], 10)
    b_left, v_left = validation.subset_model_bias(step, pts[:1], 10, part="left")
    b_right, _ = validation.subset_model_bias(step, pts[:1], 10, part="right")
    assert abs(b_full[0]) > 0.05 and abs(b_right[0]) > 0.05
    assert abs(b_left[0]) < 1e-9
    assert v_left[0] > v_full[0]
    # subsets that leave the grid are NaN; wrong inputs are refused
    b, _ = validation.subset_model_bias(lin, [[3.0, 40.0]], 10)
    assert np.isnan(b[0])
    with pytest.raises(SemlabError, match="part"):
        validation.subset_model_bias(lin, pts, 5, part="middle")
    with pytest.raises(SemlabError, match="weight"):
        validation.subset_model_bias(lin, pts, 5, weight=w[:10])


def test_heightmap_errors_known_answers(tmp_path):
    """A map = truth + a plane + white noise of known σ, on a window: the plane is removed, the
    border and the unmeasured pixels are left out, the RMSE and the σ coverage are the noise's."""
    rng = np.random.default_rng(1)
    (tmp_path / "truth").mkdir()
    hgt, wid = 120, 160
    zt = rng.normal(0, 0.2, (hgt, wid))
    np.save(tmp_path / "truth" / "height_view0.npy", zt)
    roi = (10, 20, 150, 110)                       # (x0, y0, x1, y1): 90 rows, 140 columns
    yy, xx = np.mgrid[roi[1]:roi[3], roi[0]:roi[2]]
    noise = rng.normal(0, 0.01, xx.shape)
    z = zt[roi[1]:roi[3], roi[0]:roi[2]] + 0.3 + 0.002 * xx - 0.001 * yy + noise
    valid = np.ones(z.shape, bool)
    valid[:, :30] = False                          # view columns 10..39 not measured
    r = validation.heightmap_errors(z, np.full(z.shape, 0.01), valid, tmp_path, roi=roi,
                                    border_px=20)
    # interior of the view: x 20..139, y 20..99; of the window: x 20..139 (120), y 20..99 (80)
    measured = (xx >= 40) & (xx < 140) & (yy < 100)
    assert r["n"] == measured.sum() and r["mask"].sum() == measured.sum()
    assert r["measured"] == pytest.approx(measured.sum() / (120 * 80))
    assert r["rmse_um"] == pytest.approx(0.01, rel=0.05)
    assert r["within_1sigma"] == pytest.approx(0.683, abs=0.03)
    assert r["within_2sigma"] == pytest.approx(0.954, abs=0.02)
    with pytest.raises(SemlabError, match="roi"):
        validation.heightmap_errors(z, z, valid, tmp_path, roi=(0, 0, 140, 90 + 1))
    with pytest.raises(SemlabError, match="one"):
        validation.heightmap_errors(z, z[:-1], valid, tmp_path, roi=roi)


def _three_view_points(n=2000, tilts=(-5.0, 0.0, 5.0), s=0.03, noise_px=0.05, seed=0):
    """Points of a relief seen at ``tilts`` (affine, axis along y), matched from view 0
    (exact) with Gaussian x errors of ``noise_px`` in the other views."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 15, n)
    y = rng.uniform(0, 10, n)
    z = 0.3 * np.sin(x / 2.0) * np.cos(y / 3.0)
    th = np.deg2rad(tilts)
    pts = np.stack([np.column_stack([(x * np.cos(t) + z * np.sin(t)) / s, y / s]) for t in th], 1)
    pts[:, 1:, 0] += rng.normal(0, noise_px, (n, len(tilts) - 1))
    return pts


def test_view_pair_consistency_tells_right_error_bars_from_too_small_ones():
    tilts = (-5.0, 0.0, 5.0)
    pts = _three_view_points(noise_px=0.05)
    sig = np.full(pts.shape[:2], 0.05)
    sig[:, 0] = 1e-6
    right = validation.view_pair_consistency(pts, tilts, sig, 0.03)
    # three views: one redundant coordinate per point, so one check
    assert [r["views"] for r in right] == [[0, 1]]
    for r in right:
        assert r["n_points"] == 2000 and r["consistent"], r
        assert 0.9 < r["robust_sd"] < 1.1 and 0.93 < r["within_2sigma"] <= 0.975
        assert 0.63 < r["within_1sigma"] < 0.73
    # the same matches with error bars half the size: said so
    small = validation.view_pair_consistency(pts, tilts, np.where(sig > 1e-3, 0.025, sig), 0.03)
    for r in small:
        assert 1.8 < r["robust_sd"] < 2.2 and r["within_2sigma"] < 0.75 and not r["consistent"]
    # an error common to both matches of a point (the reference subset's own), three times
    # their own and left out of σ: the residual of the all-view fit holds it as an error of
    # the reference view, so it stands out (sqrt(1 + 9 · 0.2) = 1.67 for these tilts)
    rng = np.random.default_rng(1)
    common = pts.copy()
    common[:, 1:, 0] += rng.normal(0, 0.15, len(pts))[:, None]
    c = {tuple(r["views"]): r for r in validation.view_pair_consistency(common, tilts, sig, 0.03)}
    assert 1.5 < c[(0, 1)]["robust_sd"] < 1.85 and not c[(0, 1)]["consistent"]
    # a plane between the pairs (their own offsets) is a gauge, not an error
    tilted = pts.copy()
    tilted[:, 2, 0] += 0.5 + 1e-3 * pts[:, 0, 0] - 2e-3 * pts[:, 0, 1]
    again = validation.view_pair_consistency(tilted, tilts, sig, 0.03)
    assert max(abs(x["robust_sd"] - r["robust_sd"]) for x, r in zip(again, right)) < 0.05


def test_pair_height_differences_holds_right_bars_and_flags_small_ones():
    """Pairs (0,1) and (0,2) share only the exact reference view, so with right σ their
    height difference over its predicted σ is a standard normal."""
    tilts = (-5.0, 0.0, 5.0)
    pts = _three_view_points(noise_px=0.05)
    exact = validation.pair_height_differences(_three_view_points(noise_px=0.0), tilts,
                                               np.full(2000, 0.05), ((0, 1), (0, 2)), 0.03)
    assert len(exact) == 1 and np.max(np.abs(exact[0]["diff_um"])) < 1e-9
    right = validation.pair_height_differences(pts, tilts, np.full(2000, 0.05),
                                               ((0, 1), (0, 2)), 0.03)
    r = right[0]
    assert r["pairs"] == [(0, 1), (0, 2)]
    assert 0.63 < r["within_1sigma"] < 0.73 and 0.93 < r["within_2sigma"] < 0.975
    # σ in µm: 0.05 px × cos(−5°) through 5° and 10° of tilt difference at 0.03 µm/px
    s1 = 0.03 * 0.05 * np.cos(np.deg2rad(5.0)) / np.sin(np.deg2rad(5.0))
    s2 = 0.03 * 0.05 * np.cos(np.deg2rad(5.0)) / np.sin(np.deg2rad(10.0))
    assert np.allclose(r["sigma_um"], np.hypot(s1, s2))
    assert 0.9 < r["robust_sd_um"] / np.hypot(s1, s2) < 1.1
    small = validation.pair_height_differences(pts, tilts, np.full(2000, 0.025),
                                               ((0, 1), (0, 2)), 0.03)
    assert small[0]["within_2sigma"] < 0.75
    # a plane between the pairs (their own offsets and tilt errors) is a gauge
    tilted = pts.copy()
    tilted[:, 2, 0] += 0.5 + 1e-3 * pts[:, 0, 0] - 2e-3 * pts[:, 0, 1]
    again = validation.pair_height_differences(tilted, tilts, np.full(2000, 0.05),
                                               ((0, 1), (0, 2)), 0.03)
    assert abs(again[0]["robust_sd_um"] - r["robust_sd_um"]) < 0.05 * r["robust_sd_um"]
    with pytest.raises(SemlabError, match="pair_height_differences"):
        validation.pair_height_differences(pts, tilts, np.full(10, 0.05), ((0, 1), (0, 2)))


def test_view_pair_consistency_needs_three_views_and_checks_shapes():
    pts = _three_view_points(n=50)
    sig = np.full(pts.shape[:2], 0.05)
    assert validation.view_pair_consistency(pts[:, :2], (-5.0, 0.0), sig[:, :2], 0.03) == []
    four = np.concatenate([pts, pts[:, 2:] + 0.01], axis=1)
    out = validation.view_pair_consistency(four, (-5.0, 0.0, 5.0, 7.0), np.full((50, 4), 0.05),
                                           0.03)
    assert [r["views"] for r in out] == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    with pytest.raises(SemlabError, match="sigma_px must be"):
        validation.view_pair_consistency(pts, (-5.0, 0.0, 5.0), sig[:, :2], 0.03)
    with pytest.raises(SemlabError, match="tilt_deg has 2 values"):
        validation.view_pair_consistency(pts, (-5.0, 0.0), sig, 0.03)
