"""Real-texture truth: exact geometry, a measured rendering error, whole experiment folders."""

import json

import numpy as np
import pytest
from scipy import ndimage

from semlab import realtex, synth
from semlab.errors import SemlabError

from conftest import shared_path

SIZE = (96, 128)


def _pattern(shape, periods=(5.0, 7.3, 11.0, 23.0)):
    """A band-limited test image: sum of oblique cosines (periods in source px), mean 1."""
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    img = np.ones(shape)
    for k, p in enumerate(periods):
        ang = 0.7 + 1.1 * k
        img += 0.05 * np.cos(2 * np.pi * (cc * np.cos(ang) + rr * np.sin(ang)) / p + k)
    return img, periods


def _pattern_at(cols, rows, periods):
    out = np.ones(np.shape(cols))
    for k, p in enumerate(periods):
        ang = 0.7 + 1.1 * k
        out += 0.05 * np.cos(2 * np.pi * (cols * np.cos(ang) + rows * np.sin(ang)) / p + k)
    return out


def test_zero_height_gives_the_pure_x_scaling_of_the_source():
    src, _ = _pattern((300, 360))
    scene, size = realtex.make_real_scene(src, size=SIZE, flat=True, source_tilt_deg=-5.0,
                                          antialias_px=0, n_landmarks=0)
    img, x, y = synth.render(scene, size, 8.0, blur_px=0, noise=0, shading=False)
    # the view at +8° shows, at u, the source at cs + (u - cx) s cos(-5°) / (cos 8° step)
    h, w = size
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    k = scene.pixel_size_um / scene.source_step_um
    cs, rs = scene.source_center_px
    cols = cs + (uu - cx) * k * np.cos(np.deg2rad(-5.0)) / np.cos(np.deg2rad(8.0))
    rows = rs + (vv - cy) * k
    direct = ndimage.map_coordinates(scene.source_coeffs, [rows, cols], order=3, prefilter=False)
    np.testing.assert_allclose(img, 0.45 * direct, atol=1e-9)
    # and a wrong scaling (no tilt change) does not fit
    wrong = ndimage.map_coordinates(scene.source_coeffs, [rows, cs + (uu - cx) * k], order=3,
                                    prefilter=False)
    assert np.abs(img - 0.45 * wrong).max() > 1e-3


def test_view_at_the_source_tilt_is_the_source():
    src, _ = _pattern((301, 361))  # odd: the view's pixel centres fall on source pixels
    scene, size = realtex.make_real_scene(src, size=SIZE, source_tilt_deg=-5.0, antialias_px=0,
                                          n_landmarks=0)
    img, _, _ = synth.render(scene, size, -5.0, blur_px=0, noise=0, shading=False)
    h, w = size
    cs, rs = scene.source_center_px
    k = scene.pixel_size_um / scene.source_step_um  # 2 source px per view px
    c0, r0 = cs - (w - 1) / 2 * k, rs - (h - 1) / 2 * k
    assert c0 == int(c0) and r0 == int(r0)
    on_grid = src[int(r0):int(r0) + h * 2:2, int(c0):int(c0) + w * 2:2]
    # relief does not distort the source view (only the other tilts see the parallax)
    np.testing.assert_allclose(img / 0.45, on_grid / src.mean(), atol=1e-7)


def test_rendering_error_on_a_band_limited_texture_with_relief():
    src, periods = _pattern((300, 360))
    scene, size = realtex.make_real_scene(src, size=SIZE, source_tilt_deg=0.0, antialias_px=0,
                                          n_landmarks=0, seed=2)
    for tilt in (-5.0, 8.0):
        img, x, y = synth.render(scene, size, tilt, blur_px=0, noise=0, shading=False)
        cols, rows = realtex.source_position(scene, x, y)
        exact = _pattern_at(cols, rows, periods) / src.mean()
        err = np.abs(img / 0.45 - exact)
        # under 0.3 % of the pattern's amplitude (0.2): the cubic spline on the source grid
        assert err.max() < 0.003 * 0.2, err.max()
    # the relief is there: the same pixels show different source points at the two tilts
    _, xa, _ = synth.render(scene, size, -5.0, noise=0, shading=False)
    _, xb, _ = synth.render(scene, size, 8.0, noise=0, shading=False)
    assert np.abs(xa - xb).max() > 0.05


def _blob_source(shape, pts, sigma=2.5):
    rr, cc = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    img = np.full(shape, 0.3)
    for c, r in pts:
        img += np.exp(-0.5 * ((cc - c) ** 2 + (rr - r) ** 2) / sigma ** 2)
    return img


def _centroid_errors(img, proj, background):
    h, w = img.shape
    ok = (proj[:, 0] > 8) & (proj[:, 0] < w - 9) & (proj[:, 1] > 8) & (proj[:, 1] < h - 9)
    err = []
    for px, py in proj[ok]:
        c0, r0 = int(round(px)), int(round(py))
        win = np.clip(img[r0 - 6:r0 + 7, c0 - 6:c0 + 7] - background, 0, None)
        yy, xx = np.mgrid[r0 - 6:r0 + 7, c0 - 6:c0 + 7]
        err.append(np.hypot((win * xx).sum() / win.sum() - px, (win * yy).sum() / win.sum() - py))
    return np.array(err)


@pytest.mark.parametrize("flat", [True, False])
def test_truth_point_projects_onto_its_rendered_feature(flat):
    shape = (300, 360)
    g = np.stack(np.meshgrid(np.arange(60, 300, 32.0), np.arange(60, 240, 32.0)), -1).reshape(-1, 2)
    src = _blob_source(shape, g + 0.37)
    scene, size = realtex.make_real_scene(src, size=SIZE, source_tilt_deg=-5.0, antialias_px=1.0,
                                          n_landmarks=0, seed=4, flat=flat)
    xy = realtex.material_at_source(scene, g[:, 0] + 0.37, g[:, 1] + 0.37)
    tilt = 8.0
    img, _, _ = synth.render(scene, size, tilt, blur_px=0, noise=0, shading=False)
    proj = synth.project_points(scene, xy, tilt, size)
    background = 0.45 * 0.3 / src.mean()
    err = _centroid_errors(img, proj, background)
    assert len(err) >= 10
    if flat:
        # no relief: the rendering is exact (the x-scaling moves every blob to its projection)
        assert err.max() < 1e-4, err
    else:
        # relief: the parallax between the source view (-5°) and +8° reaches 2.6 px; a blob
        # lying across a curved band edge is not mapped affinely, so its centroid moves off
        # the projection of its centre by a few hundredths of a pixel (not a rendering error)
        assert np.median(err) < 0.06 and err.max() < 0.35, err
        # ignoring the relief puts the blobs well away
        wrong = synth.project_points(scene, xy, tilt, size, height_scale=0.0)
        bad = _centroid_errors(img, wrong, background)
        assert np.median(bad) > 5 * np.median(err)


def test_material_at_source_inverts_source_position():
    src, _ = _pattern((300, 360))
    scene, _ = realtex.make_real_scene(src, size=SIZE, source_tilt_deg=7.0, n_landmarks=0)
    cols = np.array([120.3, 180.0, 240.7])
    rows = np.array([100.1, 150.0, 200.9])
    xy = realtex.material_at_source(scene, cols, rows)
    c, r = realtex.source_position(scene, xy[:, 0], xy[:, 1])
    np.testing.assert_allclose(c, cols, atol=1e-9)
    np.testing.assert_allclose(r, rows, atol=1e-12)


def test_bad_inputs_are_refused(tmp_path):
    src, _ = _pattern((120, 140))
    with pytest.raises(SemlabError, match="does not fit"):
        realtex.make_real_scene(src, size=(96, 128))
    with pytest.raises(SemlabError, match="must be 2D"):
        realtex.make_real_scene(np.zeros((3, 4, 5)))
    with pytest.raises(SemlabError, match="not found"):
        realtex.load_source("fei", data_root=tmp_path)
    # a field of view that needs texture outside the source says so
    scene, size = realtex.make_real_scene(src, size=(20, 30), n_landmarks=0, margin_px=1,
                                          slip_um=0.0)
    with pytest.raises(SemlabError, match="outside"):
        synth.render(scene, (80, 80), 0.0, noise=0, shading=False)


def test_fei_texture_cubic_rendering_agrees_with_quintic():
    path = shared_path("real_sem", realtex.SOURCES["fei"])
    scene, size = realtex.make_real_scene(path, size=(128, 160), source_tilt_deg=-5.0, seed=1,
                                          n_landmarks=0)
    img, x, y = synth.render(scene, size, 5.0, blur_px=0, noise=0, shading=False)
    cols, rows = realtex.source_position(scene, x, y)
    raw = realtex.load_source(path)
    src = ndimage.gaussian_filter(raw, 1.0)
    quintic = ndimage.map_coordinates(src / src.mean(), [rows, cols], order=5)
    diff = img / 0.45 - quintic
    tex_sd = np.std(img / 0.45)
    assert tex_sd > 0.05  # a real texture, not a flat image
    assert np.sqrt(np.mean(diff ** 2)) < 0.002 * tex_sd


def test_make_experiment_on_the_fei_texture(tmp_path):
    shared_path("real_sem", realtex.SOURCES["fei"])
    from semlab.experiment import load
    from semlab.io import read_image

    out = tmp_path / "fei"
    realtex.make_experiment(out, "fei", seed=1, size=SIZE, tilts_deg=(0.0, 8.0), n_frames=2,
                            n_clicks=10, progress=False)
    exp = load(out)
    assert exp.stereo.tilt_deg == [0.0, 8.0] and exp.stereo.shape == SIZE
    info = json.loads((out / "truth" / "realtex.json").read_text())
    assert info["source"] == "fei" and info["source_tilt_deg"] == 0.0
    assert json.loads((out / "truth" / "scene.json").read_text())["texture"] == "real:fei"
    # view 0 is the (rescaled, anti-aliased) real image with new noise
    v0 = read_image(out / "end_state" / "view_0.tif")
    assert v0.bit_depth == 8
    scene, _ = realtex.make_real_scene("fei", seed=1, size=SIZE, source_tilt_deg=0.0,
                                       n_landmarks=0)
    clean, _, _ = synth.render(scene, SIZE, 0.0, blur_px=0, noise=0, shading=False)
    a = v0.data - v0.data.mean()
    b = clean - clean.mean()
    assert (a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()) > 0.9
    # truth: heights of the surface, projections by the affine camera, clicks near them
    t = synth.read_truth_points(out / "truth")
    np.testing.assert_allclose(scene.height(t["x_um"], t["y_um"]), t["z_um"], atol=1e-9)
    p = synth.project_points(scene, np.column_stack([t["x_um"], t["y_um"]]), 8.0, SIZE)
    np.testing.assert_allclose(p[:, 0], t["v1_x_px"], atol=1e-9)
    rows = np.genfromtxt(out / "annotations" / "correspondences.csv", delimiter=",", names=True)
    assert len(rows) == 10


def test_cli_synth_real_texture(tmp_path, capsys):
    shared_path("real_sem", realtex.SOURCES["pollen"])
    from semlab.cli import main
    from semlab.experiment import load

    out = tmp_path / "p"
    assert main(["synth", str(out), "--texture", "real:pollen", "--size", "64x96", "--frames",
                 "2", "--clicks", "5", "--noise", "low", "--quiet"]) == 0
    exp = load(out)
    assert exp.stereo.shape == (64, 96) and len(exp.series.frame_paths) == 2
    assert json.loads((out / "truth" / "realtex.json").read_text())["source"] == "pollen"
    with pytest.raises(SystemExit):
        main(["synth", str(tmp_path / "q"), "--texture", "glossy", "--quiet"])
    assert "expected speckle" in capsys.readouterr().err


def test_series_frame_shows_the_known_displacement():
    shape = (300, 360)
    g = np.stack(np.meshgrid(np.arange(60, 300, 32.0), np.arange(60, 240, 32.0)), -1).reshape(-1, 2)
    src = _blob_source(shape, g + 0.21)
    scene, size = realtex.make_real_scene(src, size=SIZE, source_tilt_deg=0.0, n_landmarks=0,
                                          seed=1, slip_um=0.05)
    xy = realtex.material_at_source(scene, g[:, 0] + 0.21, g[:, 1] + 0.21)
    img, _, _ = synth.render(scene, size, 0.0, disp_fraction_left=1.0, blur_px=0, noise=0,
                             shading=False)
    moved = synth.frame_positions(scene, xy, 1.0, size)
    still = synth.frame_positions(scene, xy, 0.0, size)
    background = 0.45 * 0.3 / src.mean()
    err = _centroid_errors(img, moved, background)
    assert len(err) >= 10
    inside = ((moved[:, 0] > 8) & (moved[:, 0] < size[1] - 9) & (moved[:, 1] > 8)
              & (moved[:, 1] < size[0] - 9))
    shift = np.hypot(*(moved - still)[inside].T)
    assert shift.max() > 0.5  # the frame is displaced...
    assert np.median(err) < 0.03 and np.median(err) < 0.1 * np.median(shift)  # ...by the truth
