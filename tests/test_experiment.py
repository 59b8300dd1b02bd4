"""experiment.load: a valid folder loads; every kind of bad input names the file and the fix."""

import shutil
import warnings

import numpy as np
import pytest

from semlab.errors import ExperimentError, SemlabError
from semlab.experiment import load
from semlab.io import write_tiff


def _edit(root, old, new):
    p = root / "experiment.toml"
    text = p.read_text()
    assert old in text, f"{old!r} not in the TOML"
    p.write_text(text.replace(old, new))


def test_loads_synthetic_experiment(small_experiment_master):
    exp = load(small_experiment_master)
    assert exp.pixel_size_um == pytest.approx(0.03)
    assert exp.pixel_size_source.startswith("metadata:")
    assert exp.stereo.tilt_deg == [-5.0, 5.0] and exp.stereo.tilt_source == "experiment"
    assert exp.stereo.shape == (96, 128) and exp.stereo.camera == "affine"
    assert len(exp.series.frame_paths) == 4
    assert [p.name for p in exp.series.frame_paths] == sorted(p.name for p in exp.series.frame_paths)
    assert np.all(np.diff(exp.series.cycles) > 0)
    views = exp.views()
    assert len(views) == 2 and views[0].shape == (96, 128)
    c = exp.correspondences()
    assert c.pts.shape[1:] == (2, 2) and len(c.point_id) == c.pts.shape[0]
    assert exp.truth_dir is not None
    text = exp.summary()
    assert "0.03 µm/px" in text and "tilt -5.000°" in text


def test_load_accepts_toml_path(small_experiment_master):
    assert load(small_experiment_master / "experiment.toml").name.startswith("synthetic")


def test_tilts_from_metadata_when_toml_has_none(small_experiment):
    _edit(small_experiment, "tilt_deg = [-5.0, 5.0]\n", "")
    exp = load(small_experiment)
    assert exp.stereo.tilt_source == "metadata" and exp.stereo.tilt_deg == [-5.0, 5.0]


def test_toml_overrides_metadata_and_reports_it(small_experiment):
    _edit(small_experiment, "# pixel_size_um", "pixel_size_um = 0.05\n#")
    _edit(small_experiment, "tilt_deg = [-5.0, 5.0]", "tilt_deg = [-6.0, 5.0]")
    with pytest.warns(UserWarning, match="overrides"):
        exp = load(small_experiment)
    assert exp.pixel_size_um == 0.05 and exp.pixel_size_source == "experiment"
    assert exp.stereo.tilt_deg[0] == -6.0
    assert any("pixel_size_um" in n for n in exp.notes) and any("tilt" in n for n in exp.notes)


def test_missing_toml(tmp_path):
    with pytest.raises(ExperimentError, match="experiment file not found"):
        load(tmp_path)


def test_toml_syntax_error(small_experiment):
    (small_experiment / "experiment.toml").write_text("name = 'x\n[stereo]\n")
    with pytest.raises(ExperimentError, match="not valid TOML"):
        load(small_experiment)


def test_unknown_key_suggests_nearest(small_experiment):
    _edit(small_experiment, "tilt_deg =", "tilt_degs =")
    with pytest.raises(ExperimentError, match=r"unknown key 'tilt_degs' in \[stereo\]; did you mean 'tilt_deg'"):
        load(small_experiment)
    p = small_experiment / "experiment.toml"
    p.write_text("pixel_sise_um = 0.03\n" + p.read_text().replace("tilt_degs", "tilt_deg"))
    with pytest.raises(ExperimentError, match="did you mean 'pixel_size_um'"):
        load(small_experiment)


def test_neither_stereo_nor_series(tmp_path):
    (tmp_path / "experiment.toml").write_text('name = "x"\npixel_size_um = 0.03\n')
    with pytest.raises(ExperimentError, match="neither"):
        load(tmp_path)


def test_fewer_than_two_views(small_experiment):
    _edit(small_experiment, 'views = ["end_state/view_0.tif", "end_state/view_1.tif"]',
          'views = ["end_state/view_0.tif"]')
    with pytest.raises(ExperimentError, match="2 or more"):
        load(small_experiment)


def test_missing_view_file(small_experiment):
    (small_experiment / "end_state" / "view_1.tif").unlink()
    with pytest.raises(ExperimentError, match=r"views\[1\].*file not found"):
        load(small_experiment)


def test_views_of_different_sizes(small_experiment):
    f = small_experiment / "end_state" / "view_1.tif"
    f.unlink()
    write_tiff(f, np.zeros((50, 60), np.uint16), pixel_size_um=0.03, tilt_deg=5.0)
    with pytest.raises(ExperimentError, match="same size.*view_1.tif is 60×50"):
        load(small_experiment)


def test_frames_of_different_sizes(small_experiment):
    f = small_experiment / "series" / "frame_002.tif"
    f.unlink()
    write_tiff(f, np.zeros((50, 60), np.uint16), pixel_size_um=0.03)
    with pytest.raises(ExperimentError, match="frame_002.tif"):
        load(small_experiment)


def test_glob_matching_nothing(small_experiment):
    _edit(small_experiment, 'frames = "series/frame_*.tif"', 'frames = "series/img_*.tif"')
    with pytest.raises(ExperimentError, match="matches no image"):
        load(small_experiment)


def test_glob_frames_in_natural_order(small_experiment):
    # a microscope's numbering without leading zeros: frame_2 is before frame_10, as meant
    series = small_experiment / "series"
    for old, new in zip(sorted(series.glob("frame_*.tif")), ("f1", "f2", "f10", "f11")):
        old.rename(series / f"{new}.tif")
    _edit(small_experiment, 'frames = "series/frame_*.tif"', 'frames = "series/f*.tif"')
    names = [p.name for p in load(small_experiment).series.frame_paths]
    assert names == ["f1.tif", "f2.tif", "f10.tif", "f11.tif"]


def test_frames_as_list(small_experiment):
    _edit(small_experiment, 'frames = "series/frame_*.tif"',
          'frames = ["series/frame_000.tif", "series/frame_001.tif", "series/frame_002.tif", '
          '"series/frame_003.tif"]')
    assert len(load(small_experiment).series.frame_paths) == 4


def test_cycles_not_increasing(small_experiment):
    text = (small_experiment / "experiment.toml").read_text()
    import re

    text = re.sub(r"cycles = \[.*\]", "cycles = [0, 10, 5, 20]", text)
    (small_experiment / "experiment.toml").write_text(text)
    with pytest.raises(ExperimentError, match="increase strictly"):
        load(small_experiment)


def test_cycles_wrong_length(small_experiment):
    import re

    p = small_experiment / "experiment.toml"
    p.write_text(re.sub(r"cycles = \[.*\]", "cycles = [0, 10, 20]", p.read_text()))
    with pytest.raises(ExperimentError, match="3 values but there are 4"):
        load(small_experiment)


def test_no_pixel_size_anywhere(tmp_path):
    import cv2

    for i in range(2):
        cv2.imwrite(str(tmp_path / f"v{i}.png"), np.full((64, 72), 10 * i, np.uint8))
    (tmp_path / "experiment.toml").write_text('[stereo]\nviews = ["v0.png", "v1.png"]\n')
    with pytest.raises(ExperimentError, match="no pixel size anywhere.*add pixel_size_um"):
        load(tmp_path)
    (tmp_path / "experiment.toml").write_text('pixel_size_um = 0.1\n[stereo]\nviews = ["v0.png", "v1.png"]\n')
    exp = load(tmp_path)
    assert exp.stereo.tilt_source == "unknown" and exp.stereo.tilt_deg is None


def test_bad_camera_and_bad_pixel_size(small_experiment):
    _edit(small_experiment, 'camera = "affine"', 'camera = "afine"')
    with pytest.raises(ExperimentError, match="did you mean 'affine'"):
        load(small_experiment)
    _edit(small_experiment, 'camera = "afine"', 'camera = "affine"')
    _edit(small_experiment, "# pixel_size_um", "pixel_size_um = -1\n#")
    with pytest.raises(ExperimentError, match="positive"):
        load(small_experiment)


def test_tilt_list_wrong_length(small_experiment):
    _edit(small_experiment, "tilt_deg = [-5.0, 5.0]", "tilt_deg = [-5.0, 0.0, 5.0]")
    with pytest.raises(ExperimentError, match="tilt_deg has 3 values but there are 2 views"):
        load(small_experiment)


def _corr(root):
    return root / "annotations" / "correspondences.csv"


def test_correspondences_missing_columns(small_experiment):
    lines = _corr(small_experiment).read_text().splitlines()
    header = lines[0].replace("y1_px", "yy_px")
    _corr(small_experiment).write_text("\n".join([header] + lines[1:]) + "\n")
    with pytest.raises(SemlabError, match="correspondences.csv"):
        load(small_experiment)


def test_correspondences_nan(small_experiment):
    lines = _corr(small_experiment).read_text().splitlines()
    parts = lines[1].split(",")
    parts[1] = "nan"
    lines[1] = ",".join(parts)
    _corr(small_experiment).write_text("\n".join(lines) + "\n")
    with pytest.raises(SemlabError, match="correspondences.csv"):
        load(small_experiment)


def test_correspondences_outside_image(small_experiment):
    lines = _corr(small_experiment).read_text().splitlines()
    parts = lines[2].split(",")
    parts[3] = "5000.0"
    lines[2] = ",".join(parts)
    _corr(small_experiment).write_text("\n".join(lines) + "\n")
    with pytest.raises(SemlabError, match="correspondences.csv"):
        load(small_experiment)


def test_missing_correspondences_file(small_experiment):
    _corr(small_experiment).unlink()
    with pytest.raises(ExperimentError, match=r"\[stereo\] correspondences.*file not found"):
        load(small_experiment)


def test_series_only_and_stereo_only(small_experiment, tmp_path):
    only_series = tmp_path / "series_only"
    shutil.copytree(small_experiment, only_series)
    text = (only_series / "experiment.toml").read_text()
    head, rest = text.split("[stereo]")
    series = rest[rest.index("[series]"):]
    (only_series / "experiment.toml").write_text(head + series)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        exp = load(only_series)
    assert exp.stereo is None and len(exp.frames()) == 4
    with pytest.raises(ExperimentError, match="no \\[stereo\\]"):
        exp.views()
    assert exp.correspondences() is None


def test_reference_region_and_points_keys(small_experiment):
    import re


    toml = small_experiment / "experiment.toml"
    base = toml.read_text()

    def load_with(line):
        toml.write_text(re.sub(r"\[stereo\]\n", f"[stereo]\n{line}\n", base, count=1))
        return load(toml)

    assert load(toml).stereo.reference_region is None
    assert load_with("reference_region = [1, 2, 30, 40]").stereo.reference_region == [1, 2, 30, 40]
    poly = load_with("reference_region = [[0, 0], [50, 0], [0, 40]]").stereo.reference_region
    assert poly == [[0, 0], [50, 0], [0, 40]]
    pts = load_with("reference_points = [[1, 1], [90, 5], [10, 80]]").stereo.reference_points
    assert pts == [[1, 1], [90, 5], [10, 80]]
    with pytest.raises(ExperimentError, match="reference_region.*rectangle"):
        load_with("reference_region = [30, 2, 1, 40]")
    with pytest.raises(ExperimentError, match="reference_region.*not found"):
        load_with('reference_region = "nomask.png"')
    with pytest.raises(ExperimentError, match="reference_points.*outside"):
        load_with("reference_points = [[1, 1], [900, 5], [10, 80]]")
    with pytest.raises(ExperimentError, match="not both"):
        load_with("reference_points = [[1, 1], [90, 5], [10, 80]]\nreference_region = [1, 2, 3, 4]")


def test_metrology_regions_key(small_experiment):
    from pathlib import Path

    toml = small_experiment / "experiment.toml"
    base = toml.read_text()

    def load_with(text):
        toml.write_text(base + "\n[metrology]\n" + text + "\n")
        return load(toml)

    assert load(toml).metrology_regions == {}
    mask = np.zeros((96, 128), np.uint8)
    mask[10:30, 40:90] = 255
    write_tiff(small_experiment / "pit.tif", mask)
    exp = load_with('regions = { band = [1, 2, 30, 40], tri = [[0, 0], [50, 0], [0, 40]], '
                    'pit = "pit.tif" }')
    r = exp.metrology_regions
    assert r["band"] == [1, 2, 30, 40] and r["tri"] == [[0, 0], [50, 0], [0, 40]]
    assert isinstance(r["pit"], Path) and r["pit"].name == "pit.tif"
    assert list(r) == ["band", "tri", "pit"]
    # the same table written as [metrology.regions]
    toml.write_text(base + "\n[metrology.regions]\nband = [1, 2, 30, 40]\n")
    assert load(toml).metrology_regions == {"band": [1, 2, 30, 40]}
    with pytest.raises(ExperimentError, match=r"regions\.band.*rectangle"):
        load_with("regions = { band = [30, 2, 1, 40] }")
    with pytest.raises(ExperimentError, match=r"regions\.band.*outside the 128×96"):
        load_with("regions = { band = [1, 2, 300, 40] }")
    with pytest.raises(ExperimentError, match="'map' is reserved"):
        load_with("regions = { map = [1, 2, 30, 40] }")
    with pytest.raises(ExperimentError, match="must be a table of named regions"):
        load_with("regions = [1, 2, 30, 40]")
    with pytest.raises(ExperimentError, match="did you mean 'regions'"):
        load_with("region = { a = [1, 2, 30, 40] }")
    with pytest.raises(ExperimentError, match=r"regions\.pit.*not found"):
        load_with('regions = { pit = "nomask.png" }')
    write_tiff(small_experiment / "small.tif", mask[:50])
    with pytest.raises(ExperimentError, match="draw the mask on view 0 at its size"):
        load_with('regions = { pit = "small.tif" }')
    write_tiff(small_experiment / "empty.tif", 0 * mask)
    with pytest.raises(ExperimentError, match="is empty"):
        load_with('regions = { pit = "empty.tif" }')


def test_tilt_order_is_checked(small_experiment):
    """``[stereo] tilt_order`` (the sign convention of estimated tilts): a misspelt value is
    refused with a suggestion; one that contradicts the given tilts is refused naming both."""
    _edit(small_experiment, 'camera = "affine"', 'camera = "affine"\ntilt_order = "decreasng"')
    with pytest.raises(ExperimentError, match="tilt_order = 'decreasng'.*did you mean 'decreasing'"):
        load(small_experiment)
    _edit(small_experiment, 'tilt_order = "decreasng"', 'tilt_order = "decreasing"')
    with pytest.raises(ExperimentError, match="tilt_order = 'decreasing' but the tilts.*run the "
                       "other way"):
        load(small_experiment)
    _edit(small_experiment, 'tilt_order = "decreasing"', 'tilt_order = "increasing"')
    assert load(small_experiment).stereo.tilt_order == "increasing"
