"""The stereo pipeline end to end on synthetic experiments with truth."""


import numpy as np
import pytest

from semlab import experiment, pipeline, synth, validation
from semlab.errors import GeometryError


def _make(tmp_path, **kw):
    kw.setdefault("n_frames", 0)
    kw.setdefault("progress", False)
    return experiment.load(synth.make_experiment(tmp_path / "exp", **kw))


def test_three_views_unknown_tilts_are_estimated(tmp_path):
    """-5/0/+5° with no tilt anywhere: tilts estimated (differences within 0.1°), heights
    within 10 nm RMSE of the truth."""
    tilts = np.array([-5.0, 0.0, 5.0])
    exp = _make(tmp_path, seed=0, tilts_deg=tuple(tilts), tilt_in_toml=False,
                tilt_in_metadata=False, write_block=False)
    assert exp.stereo.tilt_deg is None
    assert "as increasing with the views' order" in exp.summary()
    # the tilts' test: the subset matches (stage 9's two variational maps cost 45 of this
    # test's 62 s; the test below and the notebooks run the stage in the pipeline)
    res = pipeline.run_stereo(exp, method="auto", n_boot=0, progress=False,
                              auto_kw=dict(variational_fusion=False))
    assert res.tilt_source == "estimated"
    rel = res.tilt_deg - res.tilt_deg[1]
    assert np.abs(rel - (tilts - tilts[1])).max() < 0.1
    assert np.all(np.asarray(res.tilt_sigma_deg) < 0.1)
    zt = validation.true_height_at(exp.truth_dir, res.pts[:, 0])
    full = res.n_views == 3               # the points matched in fewer views have larger σ
    err = validation.height_errors(res.z_um[full], zt[full], res.xyz_um[full, :2])
    assert err["n"] >= 1000 and err["rmse_um"] < 0.010
    # the automatic matcher's one parameter object is recorded
    assert res.calibration["auto_match_params"]["spacing_px"] == 8
    assert res.calibration["auto_match_params"]["min_zncc"] == 0.9
    # the error bars checked by the views themselves: the heights of each view pair alone
    # against all views' (validation.view_pair_consistency), in calibration.json and the notes
    pc = res.calibration["pair_consistency"]
    assert [c["views"] for c in pc] == [[0, 1]]     # three views: one residual per point
    assert all(c["n_points"] == full.sum() for c in pc)
    assert all(c["consistent"] and 0.6 < c["robust_sd"] < 1.3 for c in pc)
    assert any("error bars checked by the views" in n for n in res.notes), res.notes
    # the sign of estimated tilts is a convention, said in the notes with the key that flips
    # it; tilt_order = "decreasing" gives the same fit with θ → −θ (and z → −z)
    assert any('tilt_order = "decreasing"' in n for n in res.notes), res.notes
    from dataclasses import replace

    dec = replace(exp, stereo=replace(exp.stereo, tilt_order="decreasing"))
    t_inc = pipeline.choose_tilts(exp, None, progress=False, tilt_matches=res.pts[full])[0]
    t_dec, src, _ = pipeline.choose_tilts(dec, None, progress=False, tilt_matches=res.pts[full])
    assert src == "estimated" and t_dec[-1] < t_dec[0]
    np.testing.assert_allclose(t_dec, -t_inc, atol=1e-9)


def test_pair_consistency_summary_is_one_note_naming_the_pairs_that_fail():
    """Four views: the range over the six pair checks in one note; pairs whose bars do not
    hold are named (validation.view_pair_consistency on exact relief plus known noise)."""
    rng = np.random.default_rng(0)
    n, s = 1500, 0.03
    x, y = rng.uniform(0, 15, n), rng.uniform(0, 10, n)
    z = 0.3 * np.sin(x / 2.0)
    th = np.deg2rad([-6.0, -2.0, 2.0, 6.0])
    pts = np.stack([np.column_stack([(x * np.cos(t) + z * np.sin(t)) / s, y / s]) for t in th], 1)
    pts[:, 1:, 0] += rng.normal(0, 0.05, (n, 3))
    sig = np.full((n, 4), 0.05)
    sig[:, 0] = 1e-6
    rows, notes = pipeline.pair_consistency_summary(pts, np.rad2deg(th), sig, s, 90.0)
    # six pairs, less those whose check repeats another's (symmetric tilts: one)
    assert 4 <= len(rows) <= 6 and len(notes) == 1 and all(r["consistent"] for r in rows)
    assert ", ".join(f"({a}, {b})" for a, b in (r["views"] for r in rows)) in notes[0]
    assert "do not hold" not in notes[0] and "within 2σ" in notes[0]
    # view 3's matches more than twice as noisy as their σ says (every comparison holds view 3,
    # through the all-view heights): the pairs whose bars fail are named
    pts[:, 3, 0] += rng.normal(0, 0.1, n)
    rows, notes = pipeline.pair_consistency_summary(pts, np.rad2deg(th), sig, s, 90.0)
    bad = [r["views"] for r in rows if not r["consistent"]]
    assert bad and "do not hold" in notes[0], rows
    assert "for " + ", ".join(f"({a}, {b})" for a, b in bad) + " fewer than 90%" in notes[0]
    assert "u" not in rows[0]
    assert pipeline.pair_consistency_summary(pts[:, :2], np.rad2deg(th[:2]), sig[:, :2], s,
                                             90.0) == ([], [])


def test_two_views_without_tilt_or_lines_raise_bas_relief(tmp_path, monkeypatch):
    """Refused before any matching (a fresh-user run waited 7 min for it on 768×715 views)."""
    exp = _make(tmp_path, seed=1, size=(128, 160), tilt_in_toml=False, tilt_in_metadata=False,
                write_block=False, n_clicks=12)

    def no_matching(*a, **k):
        raise AssertionError("matched before refusing")

    monkeypatch.setattr(pipeline, "match_views", no_matching)
    for method in ("refined", "auto"):
        with pytest.raises(GeometryError, match="bas-relief"):
            pipeline.run_stereo(exp, method=method, n_boot=0, progress=False)


def test_empty_correspondences_file_means_automatic_matching(tmp_path):
    """A correspondences CSV with a header and no rows (a picker session that saved nothing)
    is treated as no clicks: automatic matching, not an error."""
    exp = _make(tmp_path, seed=2, size=(160, 200), write_block=False, n_clicks=12)
    csv = exp.stereo.correspondences_path
    csv.write_text(csv.read_text().splitlines()[0] + "\n")
    exp = experiment.load(exp.toml_path)
    assert len(exp.correspondences().pts) == 0
    res = pipeline.run_stereo(exp, n_boot=0, progress=False)
    assert res.method == "auto" and len(res.pts) > 50


def _perspective_experiment(tmp_path, noise_px=0.0, seed=0):
    """A synthetic experiment whose correspondences are exact perspective projections of a
    known surface with the block camera's K (which the lines.json recovers)."""
    import json

    from semlab.camera import project_perspective, rotation_about_axis

    exp = _make(tmp_path, seed=seed, size=(384, 512), block_size=(384, 512), line_noise_px=0.0,
                n_clicks=12)
    K = np.array(json.loads((exp.truth_dir / "block.json").read_text())["K"])
    s = exp.pixel_size_um
    f = K[0, 0]
    D = s * f                                       # working distance, µm
    rng = np.random.default_rng(seed)
    n = 300
    x = rng.uniform(-5.5, 5.5, n)
    y = rng.uniform(-4.0, 4.0, n)
    h = 0.2 * np.sin(x) * np.cos(0.7 * y) + 0.1 * (np.abs(x - y) < 1)   # µm, out of the surface
    world = np.column_stack([x, y, -h])            # camera z points into the surface
    cols = {"point_id": np.arange(n)}
    for i, t in enumerate((-5.0, 5.0)):
        R = rotation_about_axis([0, 1, 0], np.deg2rad(t))
        uv = project_perspective(world, K, R, np.array([0.0, 0.0, D]))
        uv = uv + rng.normal(0, noise_px, uv.shape)
        cols[f"x{i}_px"], cols[f"y{i}_px"] = uv[:, 0], uv[:, 1]
    header = ",".join(cols)
    rows = np.column_stack(list(cols.values()))
    np.savetxt(exp.stereo.correspondences_path, rows, delimiter=",", header=header,
               comments="", fmt=["%d"] + ["%.6f"] * (len(cols) - 1))
    toml = exp.toml_path.read_text().replace('camera = "affine"', 'camera = "perspective"')
    exp.toml_path.write_text(toml)
    return experiment.load(exp.toml_path), h


def test_perspective_camera_heights_from_vanishing_point_K(tmp_path):
    exp, h = _perspective_experiment(tmp_path)
    assert exp.stereo.camera == "perspective"
    res = pipeline.run_stereo(exp, method="raw", n_boot=0, progress=False)
    per = res.calibration["perspective"]
    assert abs(per["tilt_difference_deg"] - 10.0) < 0.05
    err = validation.height_errors(res.z_um, h, res.xyz_um[:, :2])
    assert err["rmse_um"] < 0.002                   # exact input: K from exact lines only
    # the affine model on the same strongly perspective clicks is far off
    toml = exp.toml_path.read_text().replace('camera = "perspective"', 'camera = "affine"')
    exp.toml_path.write_text(toml)
    res_a = pipeline.run_stereo(experiment.load(exp.toml_path), method="raw", n_boot=0,
                                progress=False)
    err_a = validation.height_errors(res_a.z_um, h, res_a.xyz_um[:, :2])
    assert err_a["rmse_um"] > 5 * err["rmse_um"]


def test_perspective_camera_needs_lines(tmp_path):
    exp, _ = _perspective_experiment(tmp_path)
    toml = "\n".join(ln for ln in exp.toml_path.read_text().splitlines()
                     if not ln.startswith("lines"))
    exp.toml_path.write_text(toml)
    with pytest.raises(GeometryError, match="perspective.*lines"):
        pipeline.run_stereo(experiment.load(exp.toml_path), method="raw", n_boot=0,
                            progress=False)


def test_perspective_height_errors_follow_the_click_noise(tmp_path):
    """With 0.1 px click noise the reported z_err (matching error through the triangulation)
    has the size of the actual height errors."""
    exp, h = _perspective_experiment(tmp_path, noise_px=0.1)
    corr = exp.correspondences()
    res = pipeline.run_stereo(exp, method="raw", n_boot=0, progress=False)
    err = validation.height_errors(res.z_um, h, res.xyz_um[:, :2])["rmse_um"]
    # raw clicks are assigned the hand-click sigma (0.5 px): scale to the true 0.1 px
    pred = np.sqrt(np.mean(res.z_err_um ** 2)) * 0.1 / pipeline.RAW_CLICK_SIGMA_PX
    assert len(corr.pts) == len(res.z_um)
    assert 0.5 < err / (np.sqrt(2) * pred) < 2.0


def _set_stereo_keys(exp, **keys):
    """Rewrite experiment.toml with [stereo] keys replaced or added (TOML literals)."""
    import re

    text = exp.toml_path.read_text()
    for k, v in keys.items():
        text = re.sub(rf"(?m)^{k} = .*\n", "", text)
        text = text.replace("[stereo]\n", f"[stereo]\n{k} = {v}\n", 1)
    exp.toml_path.write_text(text)
    return experiment.load(exp.toml_path)


def test_contradicting_tilts_refused_with_the_estimate(tmp_path):
    exp = _make(tmp_path, seed=4, size=(160, 200), write_block=False, n_clicks=0)
    # (85° would be refused at load already: |tilt| >= 80° is not a stage tilt)
    with pytest.warns(UserWarning, match="overrides the image metadata 5"):
        exp = _set_stereo_keys(exp, tilt_deg="[-5.0, 45.0]")
    with pytest.raises(GeometryError, match=r"tilt_deg = \[-5.0, 45.0\] contradicts") as e:
        pipeline.run_stereo(exp, method="auto", n_boot=0, progress=False)
    import re

    assert "experiment.toml" in str(e.value)
    sugg = re.search(r"fit the views: tilt_deg = \[-5.0, ([0-9.]+)\]", str(e.value))
    # the truth is ±5°; at ±5° the x-scale moves by only sin 5° per radian of tilt, so the
    # scene's own slope (a fraction of a degree) shifts the suggestion by a few degrees
    assert sugg and abs(float(sugg.group(1)) - 5.0) < 3.0


def test_reference_region_recorded_in_calibration(tmp_path):
    exp = _make(tmp_path, seed=5, size=(160, 200), write_block=False, n_clicks=0)
    res = pipeline.run_stereo(exp, method="auto", n_boot=0, progress=False)
    exp_r = _set_stereo_keys(exp, reference_region="[0, 0, 100, 160]")
    res_r = pipeline.run_stereo(exp_r, method="auto", n_boot=0, progress=False)
    rs = res.calibration["reference_surface"]
    assert rs["method"] == "dominant_plane" and rs["n_inliers"] >= 10
    assert res.calibration["tilt_check"]["consistent"]
    assert "tilt_axis_sigma_deg" in res.calibration  # NaN here: too little relief for F
    rr = res_r.calibration["reference_surface"]
    assert rr["method"] == "region" and rr["rectangle_px"] == [0.0, 0.0, 100.0, 160.0]
    assert rr["n_in_region"] == int(np.sum(res_r.pts[:, 0, 0] <= 100)) >= rr["n_inliers"]


def test_rows_in_views_needs_x_and_y_finite_in_every_view_asked():
    pts = np.zeros((4, 3, 2))
    pts[1, 2] = np.nan                   # not in view 2
    pts[2, 1, 1] = np.nan                # y lost in view 1
    pts[3, 0, 0] = np.nan                # x lost in the reference view
    assert pipeline.rows_in_views(pts, 0, 1).tolist() == [True, True, False, False]
    assert pipeline.rows_in_views(pts, 0, 2).tolist() == [True, False, True, False]
    assert pipeline.rows_in_views(pts.tolist(), 2).tolist() == [True, False, True, True]


def test_points_seen_in_fewer_views_get_heights_in_the_same_frame(tmp_path, monkeypatch):
    """Three views, the left third of view 2 unusable (replaced by an unrelated texture):
    the automatic points there are kept with views 0 and 1, their heights in the frame of
    the complete points (same offsets, same reference plane) and as accurate."""
    from scipy import ndimage

    tilts = (-5.0, 0.0, 5.0)
    exp = _make(tmp_path, seed=0, tilts_deg=tilts, write_block=False)
    ims = exp.views()
    w = ims[2].shape[1]
    noise = ndimage.gaussian_filter(np.random.default_rng(5).normal(size=ims[2].shape), 1.5)
    left_img = ims[2][:, : w // 3]
    ims[2][:, : w // 3] = left_img.mean() + noise[:, : w // 3] / noise.std() * left_img.std()
    monkeypatch.setattr(type(exp), "views", lambda self: [im.copy() for im in ims])
    res = pipeline.run_stereo(exp, method="auto", n_boot=0, progress=False)
    few = res.n_views < 3
    left = res.pts[:, 0, 0] < w // 3 - 30
    assert few.sum() > 100 and few[left].mean() > 0.9
    fl = few & left
    assert np.isnan(res.pts[fl, 2]).all() and res.in_views(0, 1)[fl].all()
    assert res.n_views.min() >= 2 and (res.n_views[~few] == 3).all()
    assert len(res.reference.inliers) == len(res.pts) and not res.reference.inliers[few].any()
    fv = res.calibration["fewer_views"]
    assert fv["n_points"] == few.sum() and (res.point_id[few] >= fv["first_point_id"]).all()
    assert (res.point_id[~few] < fv["first_point_id"]).all()
    assert np.all(np.isfinite(res.z_err_um)) and np.all(res.z_err_um > 0)
    zt = validation.true_height_at(exp.truth_dir, res.pts[:, 0])
    e = res.z_um - zt
    a = np.column_stack([res.xyz_um[:, :2], np.ones(len(e))])
    e = e - a @ np.linalg.lstsq(a[~few], e[~few], rcond=None)[0]   # the complete points' plane
    u = e / res.z_err_um                  # errors in units of each point's own 1σ
    # same frame: the 2-view points' median offset is small against their scatter (3.3 nm
    # against 12.9 nm RMS; with the isotropic prior 3.3 nm against 16.8 nm: the offset is
    # the frame's, and the band prior's smaller σ, 9.1 nm instead of 12.1, put it at 0.37σ)
    assert abs(np.median(e[few])) < 0.3 * np.sqrt(np.mean(e[few] ** 2))
    rms_few, rms_all = (float(np.sqrt(np.mean(u[s] ** 2))) for s in (few, ~few))
    assert rms_few < 1.3 * rms_all        # as accurate, relative to their (larger) σ
    # their error bars hold as well as the complete points' (2026-12-04, fixed grid
    # subsets: 89.4 against 92.4 % within 2σ; ±0.9 % is one binomial SD of 1102 points)
    assert np.mean(np.abs(u[few]) <= 2) > np.mean(np.abs(u[~few]) <= 2) - 0.05
    # points3d.csv says how many views each point was matched in (its last column)
    from semlab.surface import read_points3d_csv

    back = read_points3d_csv(pipeline.write_stereo_results(res, tmp_path / "out")[0])
    assert np.array_equal(back["point_id"], res.point_id)
    assert np.array_equal(back["n_views"], res.n_views) and (back["n_views"] == 2).sum() > 100
    assert np.array_equal(back["n_views"] < 3, back["point_id"] >= fv["first_point_id"])


def test_refinement_failures_are_summarised_once_per_reason():
    """The warning of clicks left out names each reason once, with the range of its numbers,
    not once per point and view (a three-view run printed the same sentence 18 times)."""
    why = ("its subset's parallax information is centred {} of the half size from the click: "
           "texture-free around the click; click on texture")
    reasons = [f"view 1: {why.format(0.68)}; view 2: {why.format(0.68)}",
               f"view 1: {why.format(0.81)}", "view 2: ZNCC 0.50 below 0.90"]
    s = pipeline.summarise_reasons(reasons)
    assert s == (f"3× view 1–2: {why.format('0.68–0.81')}; 1× view 2: ZNCC 0.50 below 0.90")
