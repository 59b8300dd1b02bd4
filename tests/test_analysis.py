"""semlab.analysis: each step once, cached by its inputs and settings, result files written
by the analysis itself (never half-written)."""

import json

import numpy as np
import pytest

import semlab
from semlab import analysis, pipeline, series
from semlab.variational import VariationalParams


@pytest.fixture(scope="module")
def computed(small_experiment_master, tmp_path_factory):
    """One analysis of the small experiment, run once for the tests of this module."""
    out = tmp_path_factory.mktemp("an") / "out"
    an = semlab.Analysis(small_experiment_master, out, n_boot=0, progress=False)
    status = an.run()
    return small_experiment_master, out, an, status


def test_run_computes_each_step_once_and_writes_its_files(computed):
    _, out, an, status = computed
    assert status["stereo"] == "ok" and status["tracking"] == "ok"
    assert an.computed.count("stereo") == 1 and an.computed.count("tracking") == 1
    files = {p.name for p in out.iterdir()}
    assert {"points3d.csv", "calibration.json", "tracks.csv", "displacements.csv"} <= files
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["analysis_config"]["n_boot"] == 0
    recorded = json.loads((out / ".semlab" / "status.json").read_text())
    assert recorded["status"] == status


def test_a_second_analysis_loads_everything_from_the_cache(computed):
    exp, out, an, status = computed
    again = semlab.Analysis(exp, out, n_boot=0, progress=False)
    assert again.run() == status
    assert again.computed == []
    np.testing.assert_array_equal(again.stereo().z_um, an.stereo().z_um)


def test_a_changed_setting_recomputes_only_the_steps_that_depend_on_it(computed):
    exp, out, an, _ = computed
    other = semlab.Analysis(exp, out, n_boot=0, track_target_sigma_px=None, progress=False)
    other.tracking()
    assert other.computed == ["tracking"]  # the stereo seeds came from the cache


def test_tracking_with_subsets_sized_by_information(computed):
    """The default tracking: subsets sized by their information ("auto": 0.02 px), LK on
    request (then no target)."""
    exp, out, an, _ = computed
    tr = an.tracking().tracks
    assert an.config.track_target == 0.02 and an.config.track_target_sigma_px == "auto"
    assert tr.params["target_sigma_px"] == 0.02 and tr.method == "subset"
    assert semlab.AnalysisConfig(track_method="lk").track_target is None
    assert semlab.AnalysisConfig(track_target_sigma_px="none").track_target is None
    with pytest.raises(semlab.SemlabError, match="track_target_sigma_px"):
        semlab.AnalysisConfig(track_target_sigma_px="small")
    other = semlab.Analysis(exp, out, n_boot=0, track_method="lk", progress=False)
    assert other.tracking().tracks.method == "lk" and other.computed == ["tracking"]
    with pytest.raises(semlab.SemlabError, match="track_target_sigma_px"):
        semlab.AnalysisConfig(track_method="lk", track_target_sigma_px=0.02)  # LK: no subsets
    with pytest.raises(semlab.SemlabError, match="track_target_sigma_px"):
        semlab.AnalysisConfig(track_method="subset", track_target_sigma_px=0)


def test_stereo_subsets_sized_by_information_and_fixed_on_request(computed, monkeypatch):
    """By default the refined clicks' subsets are sized to 0.05 px and the automatic grid's
    are fixed (stage 9 pools the information; recorded in calibration.json); each has its
    own setting, and a changed setting recomputes the heights."""
    exp, out, an, _ = computed
    assert an.config.stereo_target == 0.05 and an.config.stereo_grid_target is None
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["auto_match_params"]["target_sigma_px"] is None
    assert cal["analysis_config"]["stereo_target_sigma_px"] == 0.05
    assert cal["analysis_config"]["stereo_grid_target_sigma_px"] is None
    assert semlab.AnalysisConfig(stereo_target_sigma_px="none").stereo_target is None
    assert semlab.AnalysisConfig(stereo_grid_target_sigma_px="None").stereo_grid_target is None
    for key in ("stereo_target_sigma_px", "stereo_grid_target_sigma_px"):
        for bad in (0, -0.1, float("nan"), "small", True):
            with pytest.raises(semlab.SemlabError, match=key):
                semlab.AnalysisConfig(**{key: bad})
    seen = []
    real = pipeline.match_views

    def spy(*args, **kw):
        seen.append((kw["refine_kw"], kw["auto_kw"]))
        return real(*args, **kw)

    monkeypatch.setattr(pipeline, "match_views", spy)
    fixed = semlab.Analysis(exp, out.parent / "fixed", n_boot=0, stereo_target_sigma_px="none",
                            stereo_grid_target_sigma_px=0.05, map_prior="isotropic",
                            heightmap=False, progress=False)
    res = fixed.stereo()
    assert fixed.computed == ["stereo"]
    assert seen == [({"target_sigma_px": None},
                     {"target_sigma_px": 0.05,
                      "variational_params": fixed.config.variational_params()})]
    assert res.calibration["auto_match_params"]["target_sigma_px"] == 0.05
    # stage 9's maps with the configured prior, recorded
    assert res.calibration["auto_match_params"]["variational_params"]["band_along"] == 0
    assert (cal["auto_match_params"]["variational_params"]["band_along"]
            == VariationalParams().band_along == 30)


def test_a_failed_step_is_an_error_every_time_and_leaves_no_file(small_experiment, tmp_path,
                                                                 monkeypatch, capsys):
    calls = []

    def broken(*a, **k):
        calls.append(1)
        raise semlab.SemlabError("the tracks are all lost (a test)")

    monkeypatch.setattr(series, "run_tracking", broken)
    an = semlab.Analysis(small_experiment, tmp_path / "out", n_boot=0, progress=False)
    status = an.run(["tracking"])
    assert "the tracks are all lost" in status["tracking"]
    with pytest.raises(analysis.StepFailed, match="step 'tracking' failed"):
        an.tracking()
    fresh = semlab.Analysis(small_experiment, tmp_path / "out", n_boot=0, progress=False)
    with pytest.raises(analysis.StepFailed):
        fresh.tracking()
    assert len(calls) == 1  # cached failure: not recomputed by later callers
    assert not (tmp_path / "out" / "tracks.csv").exists()
    # for the notebooks: None and the error printed, once per call, not a traceback
    assert fresh.optional("tracking") is None
    assert "the tracks are all lost" in capsys.readouterr().out
    with pytest.raises(TypeError, match="tracking"):
        fresh.optional("trackin")


def test_a_writer_failing_half_way_leaves_no_result_file(small_experiment, tmp_path, monkeypatch):
    def half(result, folder):
        (folder / "points3d.csv").write_text("point_id,x_px\n0,")
        raise OSError("disk full (a test)")

    monkeypatch.setattr(pipeline, "write_stereo_results", half)
    an = semlab.Analysis(small_experiment, tmp_path / "out", n_boot=0, progress=False)
    with pytest.raises(OSError):
        an.stereo()
    assert not (tmp_path / "out" / "points3d.csv").exists()


def test_config_refuses_unknown_and_impossible_settings():
    with pytest.raises(TypeError, match="did you mean 'track_method'"):
        semlab.AnalysisConfig.from_dict({"trackmethod": "lk"})
    with pytest.raises(semlab.SemlabError, match="track_method"):
        semlab.AnalysisConfig(track_method="optical")
    with pytest.raises(semlab.SemlabError, match="n_boot"):
        semlab.AnalysisConfig(n_boot=-1)


def test_the_cache_key_follows_the_input_files(small_experiment, tmp_path):
    a = semlab.Analysis(small_experiment, tmp_path / "o1", progress=False)
    csv = small_experiment / "annotations" / "correspondences.csv"
    csv.write_text(csv.read_text())  # same bytes: same key
    b = semlab.Analysis(small_experiment, tmp_path / "o1", progress=False)
    assert a._key("stereo", {}) == b._key("stereo", {})
    lines = csv.read_text().splitlines()
    csv.write_text("\n".join(lines[:-1]) + "\n")  # one click fewer: another key
    c = semlab.Analysis(small_experiment, tmp_path / "o1", progress=False)
    assert c._key("stereo", {}) != a._key("stereo", {})


def test_tilt_matches_of_three_views_are_computed_once_for_every_method(tmp_path):
    from semlab.synth import make_experiment

    exp = make_experiment(tmp_path / "exp", seed=0, size=(128, 160), tilts_deg=(-5.0, 0.0, 5.0),
                          tilt_in_toml=False, tilt_in_metadata=False, write_block=False,
                          n_frames=0, n_clicks=12, progress=False)
    an = semlab.Analysis(exp, tmp_path / "out", n_boot=0, progress=False)
    merged, raw = an.stereo(), an.stereo(method="raw")
    assert merged.tilt_source == raw.tilt_source == "estimated"
    # the same tilt matches: the same tilt steps (the common offset levels each method's own
    # reference surface)
    np.testing.assert_allclose(np.diff(merged.tilt_deg), np.diff(raw.tilt_deg), atol=1e-9)
    assert an.computed.count("tilt_matches") == 1


def test_cli_settings_become_the_config():
    from semlab.cli import _settings

    cfg = _settings(["heightmap=false", "track_method=subset", "n_boot=5"])
    assert cfg == semlab.AnalysisConfig(heightmap=False, track_method="subset", n_boot=5)
    with pytest.raises(semlab.SemlabError, match="did you mean 'heightmap'"):
        _settings(["heigthmap=false"])
    with pytest.raises(semlab.SemlabError, match="KEY=VALUE"):
        _settings(["heightmap"])


def test_heightmap_switched_off_is_not_run(computed):
    exp, out, _, _ = computed
    an = semlab.Analysis(exp, out, n_boot=0, heightmap=False, progress=False)
    assert "heightmap" not in an.applicable_steps()
    with pytest.raises(analysis.StepFailed, match="switched off"):
        an.heightmap()


def test_a_scheduler_that_is_not_an_address_is_refused_at_once(small_experiment):
    with pytest.raises(semlab.SemlabError, match="tcp://HOST:PORT"):
        semlab.Analysis(small_experiment, scheduler="localhost", progress=False)


def test_the_file_hash_memo_forgets_gone_and_changed_files_and_keeps_the_newest(tmp_path):
    files = []
    for i in range(4):
        p = tmp_path / f"f{i}.bin"
        p.write_bytes(bytes([i]) * 10)
        files.append(p)
    memo = {}
    for p in files:
        analysis._file_sha256(p, memo)
    assert len(memo) == 4
    files[0].unlink()                       # gone
    files[1].write_bytes(b"longer content")  # changed size: its old entry is stale
    pruned = analysis.prune_hash_memo(memo)
    assert sorted(pruned) == sorted(t for t in memo if "f2.bin" in t or "f3.bin" in t)
    newest = analysis.prune_hash_memo(memo, max_entries=1)
    assert list(newest) == [next(t for t in memo if "f3.bin" in t)]


def test_heightmap_roi_maps_only_that_window(computed, tmp_path):
    import tifffile

    exp, out, an, _ = computed
    full = tifffile.imread(out / "heightmap.tif")
    roi = (16, 24, 80, 72)
    other = semlab.Analysis(exp, tmp_path / "roi", n_boot=0, heightmap_roi=list(roi),
                            progress=False)
    assert other.config.heightmap_roi == roi
    hm, _ = other.heightmap()
    assert hm.roi == roi and hm.z_um.shape == (48, 64)
    part = tifffile.imread(tmp_path / "roi" / "heightmap.tif")
    both = np.isfinite(part) & np.isfinite(full[24:72, 16:80])
    assert both.mean() > 0.5
    # the window's own initial guess and σ scale: the same heights within a few nm
    assert np.nanmedian(np.abs(part - full[24:72, 16:80])[both]) < 0.005
    for bad in ([0, 0, 10], [5, 5, 2, 9], [0, 0, 10.5, 8], "all"):
        with pytest.raises(semlab.SemlabError, match="heightmap_roi"):
            semlab.AnalysisConfig(heightmap_roi=bad)
    outside = semlab.Analysis(exp, tmp_path / "out2", n_boot=0, heightmap_roi=[0, 0, 4000, 90],
                              progress=False)
    with pytest.raises(analysis.StepFailed, match="outside the views"):
        outside.heightmap()


def test_named_metrology_regions_get_their_row(small_experiment, tmp_path, monkeypatch):
    import csv

    toml = small_experiment / "experiment.toml"
    toml.write_text(toml.read_text() + "\n[metrology]\nregions = { left = [0, 0, 63, 95], "
                    "corner = [[0, 0], [40, 0], [0, 40]] }\n")
    an = semlab.Analysis(small_experiment, tmp_path / "out", n_boot=0, progress=False)
    hm, _ = an.heightmap()
    with open(tmp_path / "out" / "surface_parameters.csv", newline="") as f:
        rows = {r["region"]: r for r in csv.DictReader(f)}
    assert list(rows) == ["map", "left", "corner"]
    left = np.isfinite(hm.z_um[:, :64])
    assert int(rows["left"]["n_pixels"]) == int(left.sum()) > 0
    z = hm.z_um[:, :64][left]
    assert abs(float(rows["left"]["Sa_um"]) - np.mean(np.abs(z - z.mean()))) < 0.3 * float(
        rows["left"]["Sa_um"]) + 1e-4
    # the notebooks show the numbers the step computed and wrote, not a second computation
    measured = an.map_metrology()
    assert [r["region"] for r in measured["surface_parameters"]] == list(rows)
    for r in measured["surface_parameters"]:
        assert float(rows[r["region"]]["n_pixels"]) == r["n_pixels"]
        assert float(rows[r["region"]]["Sa_um"]) == pytest.approx(r["Sa"], rel=1e-3)
    assert len(measured["band_profiles"]) == len(measured["bands"]) == len(an.heightmap()[1])
    with open(tmp_path / "out" / "bands.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == len(measured["band_profiles"])
    from semlab import metrology

    calls = []
    monkeypatch.setattr(metrology, "surface_parameters", lambda *a, **k: calls.append(1))
    again = semlab.Analysis(small_experiment, tmp_path / "out", n_boot=0, progress=False)
    assert again.map_metrology()["surface_parameters"] == measured["surface_parameters"]
    assert calls == []                 # loaded with the map from the step's cache
