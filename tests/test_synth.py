"""The synthetic generator is exact under the affine camera model."""

import dataclasses
import json

import numpy as np
import pytest
from scipy import ndimage

from semlab import synth
from semlab.camera import image_center, project_affine
from semlab.errors import SemlabError

SHAPE = (96, 128)


def _centroids(img, guesses, r=5):
    out = []
    for x, y in guesses:
        c0, r0 = int(round(x)), int(round(y))
        win = img[r0 - r:r0 + r + 1, c0 - r:c0 + r + 1]
        win = win - np.median(img)
        win = np.clip(win, 0, None)
        yy, xx = np.mgrid[r0 - r:r0 + r + 1, c0 - r:c0 + r + 1]
        out.append([(win * xx).sum() / win.sum(), (win * yy).sum() / win.sum()])
    return np.array(out)


def _isolated(points_px, min_sep, shape, border):
    d = np.hypot(*(points_px[:, None, :] - points_px[None, :, :]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    h, w = shape
    ok = (d.min(axis=1) > min_sep)
    ok &= (points_px[:, 0] > border) & (points_px[:, 0] < w - 1 - border)
    ok &= (points_px[:, 1] > border) & (points_px[:, 1] < h - 1 - border)
    return ok


@pytest.mark.parametrize("tilt", [0.0, 8.0, -5.0])
def test_truth_point_projects_onto_its_rendered_feature_flat(tilt):
    scene = synth.make_scene(seed=1, size=SHAPE, flat=True, texture="particles")
    img, _, _ = synth.render(scene, SHAPE, tilt, blur_px=0, noise=0)
    proj = synth.project_points(scene, scene.particles_um, tilt, SHAPE)
    ok = _isolated(proj, 14, SHAPE, 8)
    assert ok.sum() >= 5
    c = _centroids(img, proj[ok])
    err = np.hypot(*(c - proj[ok]).T)
    assert np.max(err) < 0.03, err


def test_truth_point_projects_onto_its_rendered_feature_with_relief():
    scene = synth.make_scene(seed=2, size=SHAPE, texture="particles")
    tilt = 10.0
    img, _, _ = synth.render(scene, SHAPE, tilt, blur_px=0, noise=0, shading=False)
    proj = synth.project_points(scene, scene.particles_um, tilt, SHAPE)
    flat = synth.project_points(scene, scene.particles_um * 0 + scene.particles_um, 0.0, SHAPE)
    ok = _isolated(proj, 14, SHAPE, 8)
    c = _centroids(img, proj[ok])
    err = np.hypot(*(c - proj[ok]).T)
    # relief shifts features by up to z sin(10°)/s ≈ 1.7 px; the rendered blobs follow it
    parallax = np.abs(proj[ok, 0] - flat[ok, 0] * np.cos(np.deg2rad(tilt)) -
                      image_center(SHAPE)[0] * (1 - np.cos(np.deg2rad(tilt))))
    assert np.median(err) < 0.03 and np.max(err) < 0.25, err
    assert parallax.max() > 0.3  # the test would notice a missing parallax term


def test_flat_surface_views_differ_by_pure_x_scaling():
    scene = synth.make_scene(seed=4, size=SHAPE, flat=True)
    a0, a1 = 0.0, 8.0
    i0, _, _ = synth.render(scene, SHAPE, a0, blur_px=0, noise=0)
    i1, _, _ = synth.render(scene, SHAPE, a1, blur_px=0, noise=0)
    cx, _ = image_center(SHAPE)
    vv, uu = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(float)
    # a feature at u0 in view 0 is at cx + (u0 - cx) cos(a1)/cos(a0) in view 1, so view 1 at
    # (u, v) shows what view 0 shows at cx + (u - cx) cos(a0)/cos(a1)
    u0 = cx + (uu - cx) * np.cos(np.deg2rad(a0)) / np.cos(np.deg2rad(a1))
    pred = ndimage.map_coordinates(i0, [vv, u0], order=5, mode="nearest")
    inner = np.s_[4:-4, 8:-8]
    diff = np.abs(pred - i1)[inner]
    assert diff.max() < 0.01 * np.ptp(i1)
    # and a different (wrong) scaling does not fit: the test can fail
    wrong = ndimage.map_coordinates(i0, [vv, cx + (uu - cx) * np.cos(np.deg2rad(a1))], order=5,
                                    mode="nearest")
    assert np.abs(wrong - i1)[inner].max() > 5 * diff.max()


def test_projection_matches_camera_module():
    scene = synth.make_scene(seed=5, size=SHAPE)
    xy = np.array([[0.3, -0.4], [-1.0, 0.8], [1.2, 1.1]])
    z = scene.height(xy[:, 0], xy[:, 1])
    for t in (-5.0, 5.0):
        a = synth.project_points(scene, xy, t, SHAPE)
        b = project_affine(np.column_stack([xy, z]), t, scene.pixel_size_um, image_center(SHAPE))
        np.testing.assert_allclose(a, b, atol=1e-12)


def test_render_solves_the_projection_per_pixel():
    scene = synth.make_scene(seed=6, size=SHAPE)
    _, x, y = synth.render(scene, SHAPE, 7.0, blur_px=0, noise=0)
    back = synth.project_points(scene, np.column_stack([x.ravel(), y.ravel()]), 7.0, SHAPE)
    vv, uu = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    np.testing.assert_allclose(back[:, 0], uu.ravel(), atol=1e-8)
    np.testing.assert_allclose(back[:, 1], vv.ravel(), atol=1e-8)


def test_uniform_strain_field():
    scene = synth.make_scene(seed=0, size=SHAPE, slip_um=0.0, uniform_strain=(0.01, -0.004, 0.002))
    x, y = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 4))
    f = synth.strain_fields(scene, x, y)
    E = np.array([[0.01, 0.002], [0.002, -0.004]])
    Fm = np.linalg.inv(np.eye(2) - E)  # X = (I - E) x
    np.testing.assert_allclose(f["exx"], Fm[0, 0] - 1, atol=1e-8)
    np.testing.assert_allclose(f["eyy"], Fm[1, 1] - 1, atol=1e-8)
    np.testing.assert_allclose(f["exy"], 0.5 * (Fm[0, 1] + Fm[1, 0]), atol=1e-8)
    C = Fm.T @ Fm
    np.testing.assert_allclose(f["Exx"], 0.5 * (C[0, 0] - 1), atol=1e-8)


def test_make_experiment_truth_is_consistent(small_experiment_master):
    root = small_experiment_master
    t = synth.read_truth_points(root / "truth")
    info = json.loads((root / "truth" / "scene.json").read_text())
    scene = synth.make_scene(seed=info["seed"], size=tuple(info["size"]))
    xy = np.column_stack([t["x_um"], t["y_um"]])
    np.testing.assert_allclose(scene.height(xy[:, 0], xy[:, 1]), t["z_um"], atol=1e-9)
    for i, tilt in enumerate(info["tilts_deg"]):
        p = synth.project_points(scene, xy, tilt, tuple(info["size"]))
        np.testing.assert_allclose(p[:, 0], t[f"v{i}_x_px"], atol=1e-9)
    # the last frame is the end state seen frontally
    n_last = len(info["f"]) - 1
    c = image_center(tuple(info["size"]))
    np.testing.assert_allclose(t[f"f{n_last}_x_px"], c[0] + xy[:, 0] / info["pixel_size_um"], atol=1e-9)
    # frame 0 is displaced by the full U
    d = np.hypot(t["f0_x_px"] - t[f"f{n_last}_x_px"], t["f0_y_px"] - t[f"f{n_last}_y_px"])
    assert d.max() > 0.5
    # height map on the view-0 grid agrees with the truth points
    zmap = np.load(root / "truth" / "height_view0.npy")
    zi = ndimage.map_coordinates(zmap.astype(float), [t["v0_y_px"], t["v0_x_px"]], order=1)
    inside = t["is_particle"] == 0
    assert np.median(np.abs(zi - t["z_um"])[inside]) < 0.01
    f = np.load(root / "truth" / "fields.npz")
    assert f["ux_um"].shape == (len(f["y_px"]), len(f["x_px"]))
    assert np.all(np.diff(f["f"]) > 0) and f["f"][-1] == pytest.approx(1.0)


def test_clicks_are_near_truth(small_experiment_master):
    root = small_experiment_master
    rows = np.genfromtxt(root / "annotations" / "correspondences.csv", delimiter=",", names=True)
    assert len(rows) >= 8
    assert {"x0_px", "y0_px", "x1_px", "y1_px", "crack_id"} <= set(rows.dtype.names)


def test_block_lines_converge_to_true_vanishing_points():
    img, fam, K, R, t = synth.render_block(4.0, (384, 512), line_noise_px=0.0,
                                           rng=np.random.default_rng(0))
    assert img.shape == (384, 512)
    for k, name in enumerate("xyz"):
        segs = fam[name]
        assert len(segs) >= 2
        vp = K @ R[:, k]  # homogeneous image of the direction
        for x1, y1, x2, y2 in segs:
            line = np.cross([x1, y1, 1.0], [x2, y2, 1.0])
            line /= np.hypot(line[0], line[1])
            assert abs(line @ vp) / np.linalg.norm(vp) < 1e-9


def test_make_experiment_refuses_nonempty(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("user data")
    with pytest.raises(SemlabError, match="not empty"):
        synth.make_experiment(tmp_path / "x", progress=False)
    with pytest.raises(SemlabError, match="2 or more"):
        synth.make_experiment(tmp_path / "y", tilts_deg=(5.0,), progress=False)


# --- texture regimes and the secondary-electron detector ---------------------------------------


def _flat_texture_energy(scene, shape=SHAPE):
    """Mean squared x-gradient of a noise-free, flat-lit rendering (texture information)."""
    img, _, _ = synth.render(scene, shape, 0.0, blur_px=0.7, noise=0, shading=False)
    return float(np.mean(ndimage.sobel(img, 1) ** 2)), img


def test_texture_regimes_share_the_surface_and_order_the_information():
    scenes = {k: synth.make_scene(seed=3, size=SHAPE, texture=k) for k in synth.TEXTURES}
    xy = np.random.default_rng(0).uniform(-1.4, 1.4, (50, 2))
    z = {k: sc.height(xy[:, 0], xy[:, 1]) for k, sc in scenes.items()}
    np.testing.assert_array_equal(z["speckle"], z["polished"])
    np.testing.assert_array_equal(z["speckle"], z["featureless"])
    energy = {k: _flat_texture_energy(sc)[0] for k, sc in scenes.items()}
    # polished: a few times less gradient energy than speckle; featureless: none at all
    assert 3 * energy["polished"] < energy["speckle"]
    assert energy["featureless"] < 1e-12 < energy["polished"]
    assert len(scenes["featureless"].particles_um) == 0
    assert 5 * len(scenes["polished"].particles_um) < len(scenes["speckle"].particles_um)
    assert scenes["polished"].texture_kind == "polished"


def test_speckle_is_the_old_sem_texture_and_unknown_regimes_are_refused():
    a = synth.make_scene(seed=1, size=SHAPE, texture="sem")
    b = synth.make_scene(seed=1, size=SHAPE)
    np.testing.assert_array_equal(a.texture, b.texture)
    assert b.texture_kind == "speckle"
    with pytest.raises(SemlabError, match="texture must be one of"):
        synth.make_scene(seed=1, size=SHAPE, texture="glossy")


def test_regimes_render_the_same_geometry():
    sp = synth.make_scene(seed=5, size=SHAPE, texture="speckle")
    po = synth.make_scene(seed=5, size=SHAPE, texture="polished")
    _, x0, y0 = synth.render(sp, SHAPE, 8.0, noise=0)
    _, x1, y1 = synth.render(po, SHAPE, 8.0, noise=0)
    np.testing.assert_array_equal(x0, x1)
    np.testing.assert_array_equal(y0, y1)


def test_polished_slip_lines_lie_inside_the_bands(monkeypatch):
    sc = synth.make_scene(seed=2, size=(192, 256), texture="polished")
    monkeypatch.setitem(synth._TEXTURE_PARAMS["polished"], "slip_line_amp", 0.0)
    bare = synth.make_scene(seed=2, size=(192, 256), texture="polished")
    x, y = np.meshgrid(np.linspace(-3, 3, 300), np.linspace(-2, 2, 200))
    lines = sc.texture_at(x, y) - bare.texture_at(x, y)  # the slip lines alone
    _, n = sc._band_coords(x, y)
    near = np.zeros(x.shape, bool)
    for c, w in zip(sc.band_offsets_um, sc.band_widths_um):
        near |= np.abs(n - c) < w / 2 + 3 * 0.5 * sc.pixel_size_um
    assert near.any() and (~near).any()
    assert np.abs(lines[near]).max() > 0.03
    assert np.abs(lines[~near]).max() < 0.01 * np.abs(lines[near]).max()


def test_detector_shot_noise_follows_poisson_statistics():
    det = synth.Detector(dose_e_per_px=400.0, bits=16, gain_sd=0, offset_sd=0)
    img = np.full((200, 200), 0.45)
    c = synth.detect(img, det, np.random.default_rng(0)).astype(float) / 65535
    assert c.mean() == pytest.approx(0.45, abs=2e-3)
    assert c.std() == pytest.approx(np.sqrt(0.45 / 400.0), rel=0.03)
    # four times the dose halves the noise
    c4 = synth.detect(img, dataclasses.replace(det, dose_e_per_px=1600.0),
                      np.random.default_rng(1)).astype(float) / 65535
    assert c4.std() == pytest.approx(c.std() / 2, rel=0.05)


def test_detector_quantises_to_8_bits_and_saturates():
    det = synth.Detector(dose_e_per_px=1e6, gain_sd=0, offset_sd=0)
    img = np.tile(np.linspace(-0.2, 1.3, 301), (4, 1))
    c = synth.detect(img, det, np.random.default_rng(0))
    assert c.dtype == np.uint8
    assert np.all(c[:, img[0] < -0.01] == 0) and np.all(c[:, img[0] > 1.01] == 255)
    mid = (img[0] > 0.1) & (img[0] < 0.9)
    np.testing.assert_allclose(c[:, mid], np.round(img[:, mid] * 255), atol=1)
    # per-image gain and offset
    g = synth.detect(img, det, np.random.default_rng(0), gain=1.1, offset=0.05)
    np.testing.assert_allclose(g[:, mid].astype(float),
                               np.clip(np.round((1.1 * img[:, mid] + 0.05) * 255), 0, 255), atol=1.5)
    with pytest.raises(SemlabError, match="dose_e_per_px"):
        synth.Detector(dose_e_per_px=0)
    with pytest.raises(SemlabError, match="NOISE_LEVELS|detector must be"):
        synth.detect(img, "loud")


def _edge_positions(img):
    """Sub-pixel x of the half-maximum crossing of a dark-to-bright edge, per row."""
    lo, hi = img[:, :5].mean(), img[:, -5:].mean()
    half = (lo + hi) / 2
    out = []
    for row in img.astype(float):
        k = int(np.argmax(row > half))
        out.append(k - 1 + (half - row[k - 1]) / (row[k] - row[k - 1]))
    return np.array(out)


def test_scan_line_jitter_shifts_rows():
    h, w = 300, 40
    uu = np.arange(w, dtype=float)
    img = np.tile(0.2 + 0.6 / (1 + np.exp(-(uu - 20.3) / 1.5)), (h, 1))
    calm = synth.Detector(dose_e_per_px=1e7, bits=16, gain_sd=0, offset_sd=0)
    shaky = dataclasses.replace(calm, jitter_px=0.3)
    e0 = _edge_positions(synth.detect(img, calm, np.random.default_rng(0)))
    e1 = _edge_positions(synth.detect(img, shaky, np.random.default_rng(0)))
    assert np.std(e0) < 0.02
    assert np.std(e1) == pytest.approx(0.3, rel=0.2)


@pytest.mark.parametrize("texture", ["polished", "featureless"])
def test_make_experiment_with_regime_and_detector(tmp_path, texture):
    from semlab.io import read_image

    out = tmp_path / "exp"
    synth.make_experiment(out, seed=3, size=(96, 128), n_frames=2, n_clicks=10, texture=texture,
                          detector="realistic", write_block=False, progress=False)
    info = json.loads((out / "truth" / "scene.json").read_text())
    assert info["texture"] == texture
    assert info["detector"]["dose_e_per_px"] == synth.NOISE_LEVELS["realistic"].dose_e_per_px
    im = read_image(out / "end_state" / "view_0.tif")
    assert im.bit_depth == 8 and im.pixel_size_um == pytest.approx(0.03)
    assert 60 < im.data.mean() < 180
    f0 = read_image(out / "series" / "frame_000.tif")
    assert f0.bit_depth == 8
    rows = np.genfromtxt(out / "annotations" / "correspondences.csv", delimiter=",", names=True)
    assert len(rows) >= 8  # band-edge clicks make up for the missing particles
    # the clicks sit near the truth projections of their material points (0.5 px click noise)
    scene = synth.make_scene(seed=3, size=(96, 128), texture=texture)
    assert scene.texture_kind == texture
    t = synth.read_truth_points(out / "truth")
    np.testing.assert_allclose(scene.height(t["x_um"], t["y_um"]), t["z_um"], atol=1e-9)


def test_make_experiment_refuses_a_scene_of_another_pixel_size(tmp_path):
    scene = synth.make_scene(seed=0, size=SHAPE, pixel_size_um=0.05)
    with pytest.raises(SemlabError, match="pixel size"):
        synth.make_experiment(tmp_path / "e", size=SHAPE, scene=scene, progress=False)


def test_cli_synth_texture_and_noise(tmp_path, capsys):
    from semlab.cli import main
    from semlab.io import read_image

    out = tmp_path / "s"
    assert main(["synth", str(out), "--size", "64x96", "--frames", "0", "--clicks", "0",
                 "--texture", "polished", "--noise", "realistic", "--dose", "500", "--quiet"]) == 0
    info = json.loads((out / "truth" / "scene.json").read_text())
    assert info["texture"] == "polished" and info["detector"]["dose_e_per_px"] == 500.0
    assert read_image(out / "end_state" / "view_1.tif").bit_depth == 8
    assert main(["synth", str(tmp_path / "t"), "--dose", "500", "--quiet"]) == 2
    assert "--noise realistic" in capsys.readouterr().err
