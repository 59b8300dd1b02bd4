"""semlab.series: the seeds of the series chain and its strain step's failure."""

import dataclasses

import numpy as np
import pytest

import semlab
from semlab import series
from semlab.errors import SemlabError
from semlab.tracking import grid_seeds, seed_sigma_px


def test_grid_seeds_cover_the_frame_evenly_and_avoid_existing_seeds():
    g = grid_seeds((96, 128), spacing_px=16)
    assert g.shape == (15, 2)                       # x 24, 40, .. 103; y 24, 40, 56, 72
    assert g[:, 0].min() == 24 and g[:, 0].max() <= 127 - 24 and g[:, 1].max() <= 95 - 24
    assert np.allclose(np.unique(np.diff(np.unique(g[:, 0]))), 16)
    near = grid_seeds((96, 128), spacing_px=16, avoid=np.array([[25.0, 23.0], [200.0, 0.0]]))
    assert len(near) == 14 and not np.any(np.all(near == [24.0, 24.0], axis=1))
    big = grid_seeds((1536, 2048), max_seeds=2000)  # spacing widened to fit max_seeds
    assert 1800 < len(big) <= 2000
    assert len(grid_seeds((40, 40))) == 0            # smaller than twice the border
    with pytest.raises(SemlabError, match="spacing_px"):
        grid_seeds((96, 128), spacing_px=0)


def test_seed_sigma_is_the_information_of_the_subset():
    """Textured half: small σ, falling with the subset size; flat half: no information."""
    rng = np.random.default_rng(3)
    from scipy import ndimage

    img = 100 + 20 * ndimage.gaussian_filter(rng.standard_normal((96, 160)), 1.5)
    img[:, 80:] = 100.0
    img = img + 0.5 * rng.standard_normal(img.shape)
    pts = np.array([[40.0, 48.0], [120.0, 48.0]])
    s10, s20 = seed_sigma_px(img, pts, half_window=10), seed_sigma_px(img, pts, half_window=20)
    assert s20[0] < s10[0] < 0.05
    assert s10[1] > 20 * s10[0]


@pytest.fixture(scope="module")
def small_series(tmp_path_factory):
    from semlab.experiment import load
    from semlab.synth import make_experiment

    root = tmp_path_factory.mktemp("series")
    toml = make_experiment(root / "exp", seed=1, size=(128, 160), tilts_deg=(), n_frames=3,
                           progress=False)
    return load(toml)


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_run_tracking_adds_grid_seeds(small_series):
    corners = series.run_tracking(small_series, progress=False)
    both = series.run_tracking(small_series, progress=False, grid_kw={"spacing_px": 16})
    n_c = (both.seed == "corner").sum()
    assert n_c == corners.tracks.n_tracks and (both.seed == "grid").sum() >= 5
    assert np.array_equal(both.tracks.xy[-1][:n_c], corners.tracks.xy[-1])
    g = both.tracks.xy[-1][both.seed == "grid"]
    full = grid_seeds((128, 160), spacing_px=16, avoid=corners.tracks.xy[-1])
    last = small_series.frames(progress=False)[-1]
    # without the points whose 21x21 subset cannot reach LK's max_sigma_px (0.05) at all
    assert np.allclose(g, full[seed_sigma_px(last, full, half_window=10, smooth_sigma_px=0)
                               <= 0.05])
    assert (corners.seed == "grid").sum() == 0           # LK: "auto" adds no grid
    # sized subsets: "auto" seeds the grid where the last frame's subsets can reach the
    # steps' max_sigma_px (here everywhere but where the texture is weakest)
    sized = series.run_tracking(small_series, method="subset", progress=False,
                                track_kw={"target_sigma_px": 0.02})
    g = sized.tracks.xy[-1][sized.seed == "grid"]
    full = grid_seeds((128, 160), avoid=corners.tracks.xy[-1])
    assert 0 < len(g) <= len(full)
    assert np.all(seed_sigma_px(last, g) <= 0.1)
    with pytest.raises(SemlabError, match="grid_kw"):
        series.run_tracking(small_series, progress=False, grid_kw="yes")


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_no_strain_is_an_error_of_the_strain_step(small_series, tmp_path, monkeypatch):
    """Too few valid tracks before the last frame and the dense strain from subsets (whose
    start is the tracks'): run_strain raises, and in an analysis the strain step fails with
    that message (its status, which `semlab run` turns into the error and exit status 2) and
    writes no strain.npz, never an empty one."""
    r = series.run_tracking(small_series, progress=False)
    tr = r.tracks
    lost = dataclasses.replace(r, tracks=dataclasses.replace(
        tr, valid=np.vstack([np.zeros_like(tr.valid[:-1]), tr.valid[-1:]])))
    with pytest.raises(SemlabError, match="no strain: no frame before the last has enough "
                                          "valid tracks.*does not need the tracks"):
        series.run_strain(small_series, lost, dense_method="subsets")
    monkeypatch.setattr(series, "run_tracking", lambda *a, **k: lost)
    an = semlab.Analysis(small_series, tmp_path / "out", progress=False,
                         dense_strain_method="subsets")
    status = an.run(["tracking", "strain"])
    assert status["tracking"] == "ok"
    assert "step 'strain' failed" in status["strain"] and "no strain" in status["strain"]
    assert not (tmp_path / "out" / "strain.npz").exists()
    assert (tmp_path / "out" / "tracks.csv").is_file()
    with pytest.raises(semlab.StepFailed, match="enough valid tracks"):
        an.strain()
    # LK tracks: the subsets are the advice; subsets whose σ exceeds the tracking's cap:
    # the frames' information is the limit, with the numbers
    with pytest.raises(SemlabError, match="try track_method='subset'"):
        series.run_strain(small_series, lost, dense_method="subsets")
    weak = dataclasses.replace(lost, tracks=dataclasses.replace(
        lost.tracks, method="subset", params={**tr.params, "max_sigma_px": 0.1},
        sigma_px=np.full(tr.sigma_px.shape, 0.3)))
    with pytest.raises(SemlabError, match=r"median predicted 1σ is 0\.30 px and 100 % of them "
                                          r"exceed the 0\.1 px.*less noise") as info:
        series.run_strain(small_series, weak, dense_method="subsets")
    assert "track_method='subset'" not in str(info.value)
    sharp = dataclasses.replace(weak, tracks=dataclasses.replace(
        weak.tracks, sigma_px=np.full(tr.sigma_px.shape, 0.01)))
    with pytest.raises(SemlabError, match="failed the tracking's other checks"):
        series.run_strain(small_series, sharp, dense_method="subsets")


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_run_strain_writes_the_sparse_strain_sigma_of_the_tracks(small_series, tmp_path):
    """strain.npz holds E_lsq_sigma (M, 3): the tracks' sigma_px in the reference frame
    propagated through the local least-squares strain; NaN for tracks made without direct
    correction (whose sigma_px is that of the last chained step only)."""
    from semlab import strain as st

    r = series.run_tracking(small_series, progress=False, grid_kw={"spacing_px": 16})
    tr = r.tracks
    # every estimated step counted valid: this tests the strain step, not the tracking
    allv = dataclasses.replace(r, tracks=dataclasses.replace(
        tr, valid=np.isfinite(tr.xy).all(axis=2) & np.isfinite(tr.sigma_px)))
    S = series.run_strain(small_series, allv)
    ref = S["ref_frame"]
    ok = allv.tracks.valid[ref] & allv.tracks.valid[-1]
    s = r.pixel_size_um
    G, C = st.gradient_local_lsq(tr.xy[ref][ok] * s, (tr.xy[-1][ok] - tr.xy[ref][ok]) * s,
                                 S["gauge_length_um"], disp_sigma=tr.sigma_px[ref][ok] * s)
    expect = st.strain_sigma(G, C)
    assert np.isfinite(expect).any()
    series.write_strain_results(S, tmp_path)
    with np.load(tmp_path / "strain.npz") as z:
        assert z["E_lsq_sigma"].shape == (int(ok.sum()), 3)
        assert np.allclose(z["E_lsq_sigma"], expect, equal_nan=True)
        # the history's 1σ of each frame's mean strain: 0 in the last frame (the reference)
        hs = z["history_exx_sigma"]
        assert hs.shape == (3,) and hs[-1] == 0 and np.isfinite(hs).all() and hs[0] > 0
    chained = dataclasses.replace(allv, tracks=dataclasses.replace(
        allv.tracks, params={**tr.params, "direct_correction": False}))
    S_chained = series.run_strain(small_series, chained)
    assert np.isnan(S_chained["E_lsq_sigma"]).all()
    assert np.isnan(S_chained["history"]["exx_sigma"]).all()


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_the_dense_strain_method_is_a_setting_of_the_analysis(small_series, tmp_path,
                                                              monkeypatch):
    """``AnalysisConfig.dense_strain_method`` picks the dense strain's displacement (the
    subsets: no E_sigma), keys the strain step's cache, and a wrong word is an error naming
    the setting."""
    r = series.run_tracking(small_series, progress=False, grid_kw={"spacing_px": 16})
    allv = dataclasses.replace(r, tracks=dataclasses.replace(   # the strain step's test
        r.tracks, valid=np.isfinite(r.tracks.xy).all(axis=2)))
    monkeypatch.setattr(series, "run_tracking", lambda *a, **k: allv)
    subs = semlab.Analysis(small_series, tmp_path / "subsets", progress=False,
                           dense_strain_method="subsets")
    S = subs.strain()
    assert str(S["dense_method"]) == "subsets" and "E_sigma" not in S
    var = semlab.Analysis(small_series, tmp_path / "map", progress=False)
    assert var.config.dense_strain_method == "variational"
    assert str(var.strain()["dense_method"]) == "variational"
    assert (subs.config.for_step("strain")["dense_strain_method"]
            != var.config.for_step("strain")["dense_strain_method"])
    with pytest.raises(SemlabError, match="dense_strain_method = 'dic'.*'subsets'"):
        semlab.AnalysisConfig(dense_strain_method="dic")


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_without_valid_tracks_the_dense_strain_comes_from_the_map_alone(small_series):
    """No frame before the last with enough valid tracks: the variational map still gives the
    dense strain, from frame 0 (found frame by frame back from the last), with its 1σ; no
    sparse strain, and a warning of the step says so. It agrees with the map started from
    every track as if valid (the same frames), within its 1σ."""
    r = series.run_tracking(small_series, progress=False, grid_kw={"spacing_px": 16})
    tr = r.tracks
    allv = dataclasses.replace(r, tracks=dataclasses.replace(
        tr, valid=np.isfinite(tr.xy).all(axis=2)))
    lost = dataclasses.replace(r, tracks=dataclasses.replace(
        tr, valid=np.vstack([np.zeros_like(tr.valid[:-1]), tr.valid[-1:]])))
    with pytest.warns(semlab.SemlabWarning, match="sparse strain: none.*dense strain is the "
                                                  "variational map's alone, from frame 0"):
        S = series.run_strain(small_series, lost)
    assert S["ref_frame"] == 0 and not S["sparse_strain"]
    assert S["pts_px"].shape == (0, 2) and np.isnan(S["gauge_length_um"])
    with_tracks = series.run_strain(small_series, allv)
    assert with_tracks["ref_frame"] == 0 and with_tracks["sparse_strain"]
    E3 = lambda d: np.stack([d["E"][..., 0, 0], d["E"][..., 1, 1], d["E"][..., 0, 1]], -1)  # noqa: E731
    diff = np.abs(E3(S) - E3(with_tracks))
    assert np.isfinite(diff).mean() > 0.9
    assert np.nanmedian(diff / S["E_sigma"]) < 0.25
