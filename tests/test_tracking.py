"""Tests of semlab.tracking on synthetic series made here (known displacement field)."""

import csv
import warnings

import cv2
import numpy as np
import pytest
from scipy import ndimage

from semlab.errors import GeometryError, SemlabError, TrackingError
from semlab.registration import Transform2D
from semlab.tracking import (TRACKS_CSV_COLUMNS, Tracks, TrackingWarning, displacement_history,
                             displacements, median_outliers, normalize_frame,
                             shi_tomasi_seeds, track_reverse, tracks_to_records,
                             write_tracks_csv)

N_FRAMES = 6


def _texture(rng, shape, pad=20, sigma=2.0):
    t = ndimage.gaussian_filter(rng.standard_normal((shape[0] + 2 * pad, shape[1] + 2 * pad)), sigma)
    return t / t.std(), pad


def make_series(seed=0, shape=(150, 180), amp_px=2.0,
                contrast=(0.15, 0.3, 0.5, 0.7, 0.85, 1.0),
                noise=(0.08, 0.05, 0.03, 0.02, 0.01, 0.005)):
    """Band-limited texture displaced by a smooth field growing linearly over the frames.

    Frame f shows ``I_f(x) = a_f T(x - u_f(x)) + b_f + noise`` with early frames low in
    contrast and noisy and the brightness rising with f. Returns the frames (chronological)
    and ``truth(pts_last) -> (F, N, 2)`` true positions of the material points seen at
    ``pts_last`` in the last frame.
    """
    rng = np.random.default_rng(seed)
    H, W = shape
    tex, pad = _texture(rng, shape)
    yy, xx = np.mgrid[0:H, 0:W].astype(float)

    def u(f, x, y):
        t = f / (N_FRAMES - 1)
        return (amp_px * t * (0.6 * np.sin(2 * np.pi * x / W) + 0.4 * y / H),
                amp_px * t * (0.5 * np.cos(2 * np.pi * y / H) - 0.3 * x / W))

    frames = []
    for f in range(N_FRAMES):
        ux, uy = u(f, xx, yy)
        img = ndimage.map_coordinates(tex, [yy - uy + pad, xx - ux + pad], order=3, mode="reflect")
        frames.append(100 + 30 * f + 40 * contrast[f] * img + 40 * noise[f] * rng.standard_normal(shape))

    def truth(pts_last):
        ux, uy = u(N_FRAMES - 1, pts_last[:, 0], pts_last[:, 1])
        X = pts_last - np.c_[ux, uy]
        out = np.empty((N_FRAMES,) + pts_last.shape)
        for f in range(N_FRAMES):
            x = X.copy()
            for _ in range(60):                     # x = X + u_f(x), a contraction here
                ux, uy = u(f, x[:, 0], x[:, 1])
                x = X + np.c_[ux, uy]
            out[f] = x
        return out

    return frames, truth


@pytest.fixture(scope="module")
def series():
    frames, truth = make_series()
    seeds = shi_tomasi_seeds(frames[-1], quality=0.05, border_px=12)
    return frames, seeds, truth(seeds)


def _errors(tr, true_xy):
    return np.linalg.norm(tr.xy - true_xy, axis=2)


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
@pytest.mark.parametrize("method", ["lk", "subset"])
def test_reverse_tracking_flags_every_bad_step(series, method):
    if method == "subset":
        pytest.importorskip("semlab.subset")
    frames, seeds, true_xy = series
    tr = track_reverse(frames, seeds, method=method, progress=False, seed_kind="shi_tomasi")
    F, N = N_FRAMES, len(seeds)
    assert tr.xy.shape == (F, N, 2) and tr.valid.shape == (F, N) and tr.fb_error_px.shape == (F, N)
    # chronological storage: the reference (last) frame holds the seeds
    assert np.array_equal(tr.xy[-1], seeds) and tr.valid[-1].all() and (tr.fb_error_px[-1] == 0).all()
    err = _errors(tr, true_xy)
    # no step flagged valid with an error above 0.5 px
    assert not np.any(tr.valid & ~(err < 0.5)), np.nanmax(np.where(tr.valid, err, np.nan))
    # the clear frames are tracked (the check above is not vacuous) and accurately
    assert tr.valid[1:].mean() > 0.9
    assert np.sqrt(np.mean(err[1][tr.valid[1]] ** 2)) < 0.15
    # the noisy, low-contrast frame 0 has invalid steps, and they are the worse ones
    inv = ~tr.valid[0]
    assert inv.sum() > 0
    if tr.valid[0].any():
        assert np.nanmedian(err[0][inv]) > np.median(err[0][tr.valid[0]])
    # every invalid step carries a failing reason: fb, zncc or sigma, or no position
    assert np.all(tr.sigma_px[-1] == 0) and np.isfinite(tr.zncc[tr.valid]).all()
    assert (tr.seed_kind == "shi_tomasi").all()


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_pure_noise_frame_makes_steps_invalid_and_tracks_recover(series):
    frames, seeds, true_xy = series
    frames = list(frames)
    frames[2] = 130 + 20 * np.random.default_rng(5).standard_normal(frames[2].shape)
    tr = track_reverse(frames, seeds, progress=False)
    err = _errors(tr, true_xy)
    assert tr.valid[2].mean() < 0.05
    assert not np.any(tr.valid & ~(err < 0.5))
    # policy: suspended tracks resume from their last valid frame (3) in frame 1
    assert tr.valid[1].mean() > 0.8
    assert np.all(tr.gap_frames[1][tr.valid[1] & ~tr.valid[2]] == 1)
    assert np.all(tr.gap_frames[3] == 0)


def test_blank_frame_makes_steps_invalid(series):
    frames, seeds, true_xy = series
    frames = list(frames)
    frames[3] = np.full_like(frames[3], 77.0)
    with pytest.warns(TrackingWarning, match=r"\[3\]"):
        tr = track_reverse(frames, seeds, progress=False)
    assert not tr.valid[3].any() and np.isnan(tr.xy[3]).all()
    err = _errors(tr, true_xy)
    assert tr.valid[2].mean() > 0.8 and not np.any(tr.valid & ~(err < 0.5))


def test_records_csv_and_displacements(series, tmp_path):
    frames, seeds, true_xy = series
    tr = track_reverse(frames, seeds[:20], progress=False, seed_kind="stereo")
    rows = tracks_to_records(tr)
    assert len(rows) == 20 * N_FRAMES and tuple(rows[0])[:7] == TRACKS_CSV_COLUMNS
    assert tuple(rows[0])[7:] == ("zncc", "sigma_px", "gap_frames")
    assert [r["frame"] for r in rows[:N_FRAMES]] == list(range(N_FRAMES))
    p = write_tracks_csv(tmp_path / "tracks.csv", tr)
    with open(p) as fh:
        back = list(csv.DictReader(fh))
    assert len(back) == len(rows) and back[0]["seed"] == "stereo"
    assert list(back[0])[:7] == list(TRACKS_CSV_COLUMNS)
    last = back[N_FRAMES - 1]          # the reference (last) frame of track 0
    assert float(last["zncc"]) == pytest.approx(1.0) and int(last["gap_frames"]) == 0
    assert float(back[N_FRAMES - 1]["x_px"]) == pytest.approx(seeds[0, 0], abs=1e-6)
    with pytest.raises(SemlabError, match="overwrite"):
        write_tracks_csv(p, tr)
    write_tracks_csv(p, tr, overwrite=True)

    d = displacements(tr, pixel_size_um=0.03)
    ok = d["valid"]
    true_d = (true_xy[-1, :20] - true_xy[0, :20]) * 0.03
    assert np.all(np.isnan(d["dx_um"][~ok]))
    assert np.allclose(d["dx_um"][ok], true_d[ok, 0], atol=0.5 * 0.03)
    h = displacement_history(tr, 0.03)
    assert h["dx_um"].shape == (N_FRAMES, 20)
    assert np.allclose(h["dx_um"][-1][ok], d["dx_um"][ok])


def test_displacements_exact_on_constructed_tracks():
    xy = np.zeros((3, 2, 2))
    xy[1] = [[1, 0], [0, 0]]
    xy[2] = [[3, 4], [1, 1]]
    valid = np.ones((3, 2), bool)
    valid[0, 1] = False
    tr = Tracks(xy=xy, fb_error_px=np.zeros((3, 2)), valid=valid, zncc=np.ones((3, 2)),
                sigma_px=np.zeros((3, 2)), gap_frames=np.zeros((3, 2), int), seed_kind=np.array(["a", "b"], object),
                reference_frame=2)
    d = displacements(tr, pixel_size_um=0.5)
    assert d["d_um"][0] == pytest.approx(2.5) and np.isnan(d["d_um"][1])
    d = displacements(tr, 0.5, frame_from=1, frame_to=2)
    assert np.allclose(d["dx_um"], [1.0, 0.5])
    with pytest.raises(SemlabError):
        displacements(tr, pixel_size_um=None)
    with pytest.raises(TrackingError):
        displacements(tr, 0.5, frame_from=7)


def test_median_outliers_finds_a_jump():
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 100, (200, 2))
    u = np.c_[0.01 * X[:, 0], -0.02 * X[:, 1]] + rng.normal(0, 0.02, X.shape)
    u[17] += [1.0, 0.0]
    bad = median_outliers(X, u, np.ones(200, bool))
    assert bad[17] and bad.sum() <= 3


def test_normalize_frame_invariant_to_gain_and_offset():
    img = np.random.default_rng(0).normal(size=(32, 32))
    a, _ = normalize_frame(img)
    b, _ = normalize_frame(3.0 * img + 1000)
    assert np.allclose(a, b, atol=1e-5)
    assert normalize_frame(np.ones((9, 9)))[1]


def test_error_paths(series):
    frames, seeds, _ = series
    with pytest.raises(TrackingError, match="at least 2 frames"):
        track_reverse(frames[:1], seeds, progress=False)
    bad = list(frames)
    bad[2] = bad[2][:-1]
    with pytest.raises(TrackingError, match="frame 2"):
        track_reverse(bad, seeds, progress=False)
    with pytest.raises(TrackingError, match="no seeds"):
        track_reverse(frames, np.zeros((0, 2)), progress=False)
    with pytest.raises(TrackingError, match="outside"):
        track_reverse(frames, [[1000.0, 5.0]], progress=False)
    with pytest.raises(TrackingError, match="method"):
        track_reverse(frames, seeds, method="magic", progress=False)
    blank_last = list(frames)
    blank_last[-1] = np.zeros_like(frames[-1])
    with pytest.raises(TrackingError, match="reference"):
        track_reverse(blank_last, seeds, progress=False)
    with pytest.raises(TrackingError, match="blank"):
        shi_tomasi_seeds(np.full((64, 64), 5.0))
    # two unrelated images: every track is lost
    other = 100 + 40 * _texture(np.random.default_rng(99), frames[0].shape)[0][20:-20, 20:-20]
    with pytest.raises(TrackingError, match="lost"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TrackingWarning)
            track_reverse([other, frames[-1]], seeds, progress=False)


@pytest.mark.slow
def test_lk_steps_are_checked_against_a_subset_match(tmp_path):
    """On a synthetic series whose early frames have low contrast, plain LK (the reference
    paper's) marks steps valid that are more than 0.5 px off; with the IC-GN agreement
    check (default lk_check_px) no valid step is."""
    import csv as _csv

    from semlab.experiment import load
    from semlab.synth import make_experiment

    exp = load(make_experiment(tmp_path / "e", seed=1, tilts_deg=(), n_frames=6,
                               progress=False))
    frames = exp.frames()
    with open(tmp_path / "e" / "truth" / "points.csv") as fh:
        pts = list(_csv.DictReader(fh))
    F = len(frames)
    true = np.array([[[float(p[f"f{k}_x_px"]), float(p[f"f{k}_y_px"])] for p in pts]
                     for k in range(F)])
    h, w = frames[0].shape
    inside = np.all((true[..., 0] > 15) & (true[..., 0] < w - 16) & (true[..., 1] > 15)
                    & (true[..., 1] < h - 16), axis=0)
    true = true[:, inside]
    bad = {}
    for check in (None, 0.2):
        tr = track_reverse(frames, true[-1], method="lk", progress=False, lk_check_px=check)
        err = np.linalg.norm(tr.xy - true, axis=2)
        bad[check] = int((tr.valid & (err > 0.5)).sum())
        if check is not None:
            assert tr.valid[:-1].any()
    assert bad[None] > 0 and bad[0.2] == 0


def _drift(k, F):
    """Stage drift of frame k: a similarity about the centre of the 180x150 frames, the
    last frame being the reference (identity)."""
    if k == F - 1:
        return np.eye(3)
    rng = np.random.default_rng(40 + k)
    a = rng.uniform(0, 2 * np.pi)
    t = np.deg2rad(rng.uniform(-1.2, 1.2))
    s = 1 + rng.uniform(-0.003, 0.003)
    c = np.array([89.5, 74.5])
    A = s * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    m = np.eye(3)
    m[:2, :2] = A
    m[:2, 2] = c + rng.uniform(20, 25) * np.array([np.cos(a), np.sin(a)]) - A @ c
    return m


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_register_tracks_through_stage_drift(series):
    """Frames shifted by 20-25 px, rotated by up to 1.2° and re-magnified by up to 0.3 %:
    raw tracking loses the tracks, tracking in the registered geometry keeps about as many
    as without drift, positions in each frame's own pixels, no valid step 0.5 px off."""
    frames, seeds, true_xy = series
    F = len(frames)
    drifted, true_d = [], np.empty_like(true_xy)
    for k in range(F):
        m = _drift(k, F)
        drifted.append(cv2.warpAffine(frames[k].astype(np.float32), m[:2], (180, 150),
                                      flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT))
        true_d[k] = true_xy[k] @ m[:2, :2].T + m[:2, 2]
    h, w = frames[0].shape
    keep = np.all((true_d[..., 0] > 12) & (true_d[..., 0] < w - 13) & (true_d[..., 1] > 12)
                  & (true_d[..., 1] < h - 13), axis=0)
    seeds, true_xy, true_d = seeds[keep], true_xy[:, keep], true_d[:, keep]
    base = track_reverse(frames, seeds, progress=False)
    tr = track_reverse(drifted, seeds, progress=False, register="similarity")
    assert tr.registration is not None and tr.registration.model == "similarity"
    for k in range(F - 1):
        # the registration holds the drift and the motion of the largest rigidly moving
        # part of the material (slip bands move the rest by up to 2 px): it maps a good
        # share of the points onto their true positions (accuracy: test_registration*.py)
        e = np.linalg.norm(tr.registration.transforms[k](true_xy[-1]) - true_d[k], axis=1)
        assert np.mean(e < 0.3) > 0.2, (k, np.mean(e < 0.3))
        assert Transform2D(_drift(k, F)).distance(Transform2D.identity(), (h, w)) > 15
    err = np.linalg.norm(tr.xy - true_d, axis=2)
    assert np.array_equal(tr.xy[-1], seeds)
    assert not np.any(tr.valid & ~(err < 0.5))
    assert tr.valid[1:-1].mean() >= 0.8 * base.valid[1:-1].mean() > 0.5
    e0 = np.linalg.norm(base.xy - true_xy, axis=2)
    both = tr.valid[1] & base.valid[1]
    assert abs(np.sqrt(np.mean(err[1][both] ** 2)) - np.sqrt(np.mean(e0[1][both] ** 2))) < 0.03
    with pytest.raises(TrackingError):      # the raw frames cannot be tracked (motion > window)
        track_reverse(drifted, seeds, progress=False)


def test_register_rejects_unknown_model(series):
    frames, seeds, _ = series
    with pytest.raises(GeometryError, match="model"):
        track_reverse(frames, seeds, progress=False, register="projective")


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
@pytest.mark.filterwarnings("ignore:no frame before the last:UserWarning")
def test_run_tracking_writes_drift_and_removes_the_rigid_motion(tmp_path):
    """A series drifted by up to 25 px and 1° against the same series undrifted (same scene,
    same noise, same last frame): tracks.csv stays in each frame's own pixels, drift.csv
    holds the recovered drift, and displacements.csv with the rigid motion removed agrees
    with the undrifted run while its raw columns carry the drift."""
    from semlab.displacement import DISPLACEMENTS_CSV_COLUMNS
    from semlab.experiment import load
    from semlab.series import run_tracking, write_tracking_results
    from semlab.registration import read_drift_csv
    from semlab.synth import _stage_matrix, make_experiment

    kw = dict(seed=2, size=(192, 256), tilts_deg=(), n_frames=3, progress=False)
    runs = {}
    for name, dkw in (("still", {}), ("drift", dict(drift_shift_px=25, drift_rotation_deg=1.0))):
        exp = load(make_experiment(tmp_path / name, **kw, **dkw))
        res = run_tracking(exp, progress=False, corner_kw=dict(quality=0.05))
        runs[name] = (res, write_tracking_results(res, tmp_path / f"out_{name}"))
    (still, _), (drift, paths) = runs["still"], runs["drift"]
    assert np.array_equal(still.tracks.xy[-1], drift.tracks.xy[-1])        # same seeds
    names = [p.name for p in paths]
    assert "drift.csv" in names
    truth = read_drift_csv(tmp_path / "drift" / "truth" / "drift.csv")
    table = read_drift_csv(tmp_path / "out_drift" / "drift.csv")
    assert np.abs(truth["dx_px"][:-1]).max() > 5 and np.allclose(table["dx_px"], [
        r["dx_px"] for r in drift.tracks.registration.table()])
    # the registration holds the drift D and the material's own mean motion M (up to 12 px
    # here, non-uniform: slip bands), which the undrifted run measures alone: drifted = D @ M
    # up to how the features sample M
    for k in range(2):
        D = Transform2D(_stage_matrix({c: truth[c][k] for c in truth if c != "frame"}, (192, 256)))
        M = still.tracks.registration.transforms[k]
        g = np.stack(np.meshgrid(np.linspace(30, 225, 5), np.linspace(30, 161, 5)), -1).reshape(-1, 2)
        err = np.linalg.norm(drift.tracks.registration.transforms[k](g) - (D @ M)(g), axis=1)
        assert err.max() < 0.5, (k, err.max())
    with open(tmp_path / "out_drift" / "displacements.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == DISPLACEMENTS_CSV_COLUMNS
    both = np.isfinite(still.dx_um) & np.isfinite(drift.dx_um) & (still.frame_from == drift.frame_from)
    assert both.sum() >= 20
    s = 0.03
    # within the registrations' disagreement (< 0.5 px above), against > 3 px raw
    assert np.median(np.abs(drift.dx_um[both] - still.dx_um[both])) / s < 0.25
    assert np.median(np.abs(drift.dy_um[both] - still.dy_um[both])) / s < 0.25
    assert np.median(np.abs(drift.dx_raw_um[both] - still.dx_raw_um[both])) / s > 3   # the drift
    # tracks.csv: the drifted run's positions are in the drifted frames' own pixels
    f = int(np.min(drift.frame_from[both]))
    T = Transform2D(_stage_matrix({c: truth[c][f] for c in truth if c != "frame"}, (192, 256)))
    sel = both & drift.tracks.valid[f]
    assert np.median(np.linalg.norm(drift.tracks.xy[f, sel] - T(still.tracks.xy[f, sel]), axis=1)) < 0.1


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_subset_tracking_sizes_subsets_by_information(series):
    """target_sigma_px: each step's subset grows until its predicted total error (noise
    and curvature bias) reaches the target, so the noisy low-contrast frame 0 gets larger
    subsets than the clear frames and more valid steps than the fixed 21×21 subset, with
    no valid step 0.5 px off. The series' displacement is curved (2 px sinusoids over the
    frame): sizing by the noise alone grows more subsets to 41 px and is less accurate."""
    frames, seeds, true_xy = series
    fixed = track_reverse(frames, seeds, method="subset", progress=False)
    tr = track_reverse(frames, seeds, method="subset", progress=False, target_sigma_px=0.02,
                       max_half_window=20)
    err = _errors(tr, true_xy)
    assert not np.any(tr.valid & ~(err < 0.5))
    assert tr.subset_px.shape == tr.valid.shape and np.all(fixed.subset_px[1][fixed.valid[1]] == 21)
    s = tr.subset_px
    assert np.all((s[:-1][tr.valid[:-1]] >= 21) & (s[:-1][tr.valid[:-1]] <= 41))
    assert np.median(s[0][tr.valid[0]]) > np.median(s[-2][tr.valid[-2]])
    assert tr.valid[0].sum() > fixed.valid[0].sum() + 20
    assert tr.params["target_sigma_px"] == 0.02 and tr.params["curvature_neighbours"] == 9
    # every converged step of frames 0-1 (validity thresholds off): the curvature-aware
    # choice is more accurate than the noise-only one, which picks larger subsets
    kw = dict(method="subset", progress=False, target_sigma_px=0.02, max_half_window=20,
              max_sigma_px=None)
    rms, big = {}, {}
    for k_nb in (9, None):
        t = track_reverse(frames, seeds, curvature_neighbours=k_nb, **kw)
        conv = t.subset_px[:2] > 0
        rms[k_nb] = np.sqrt(np.mean(_errors(t, true_xy)[:2][conv] ** 2))
        big[k_nb] = (t.subset_px[:2] == 41).sum()
    assert rms[9] < 0.9 * rms[None] and big[9] < big[None], (rms, big)
    with pytest.raises(TrackingError, match="method='subset'"):
        track_reverse(frames, seeds, method="lk", target_sigma_px=0.02, progress=False)


def test_residual_check_flags_subsets_over_a_slip_step():
    """Frame 0 slipped by 1.2 px in x below y = 70 (a slip step): the subsets over the step
    fit no affine map and match a blend (0.3–0.8 px off) with a small σ and a fine
    forward–backward error; the residual check (default max_residual_ratio=2) marks them
    invalid and keeps the seeds whose subsets stay off the step."""
    rng = np.random.default_rng(0)
    tex, pad = _texture(rng, (140, 200))
    yy, xx = np.mgrid[0:140, 0:200].astype(float)

    def frame(step_px, seed):
        ux = np.where(yy >= 70, step_px, 0.0)
        img = ndimage.map_coordinates(tex, [yy + pad, xx - ux + pad], order=3)
        return 100 + 40 * img + 0.4 * np.random.default_rng(seed).standard_normal(img.shape)

    frames = [frame(1.2, 1), frame(0.0, 2)]
    gx, gy = np.meshgrid(np.arange(30, 171, 10.0), np.arange(25, 116, 5.0))
    seeds = np.column_stack([gx.ravel(), gy.ravel()])
    true0 = seeds + np.where(seeds[:, 1] >= 70, 1.2, 0.0)[:, None] * [1, 0]
    off_step = np.abs(seeds[:, 1] - 69.5) > 11        # subset rows all on one side
    for kw in ({}, {"target_sigma_px": 0.02}):
        n_bad = {}
        for rr in (None, 2.0):
            tr = track_reverse(frames, seeds, method="subset", progress=False,
                               outlier_threshold=None, max_residual_ratio=rr,
                               model_neighbours=None, **kw)
            e = np.linalg.norm(tr.xy[0] - true0, axis=1)
            n_bad[rr] = int((tr.valid[0] & (e > 0.3)).sum())
            if rr:
                assert tr.valid[0][off_step].all()
        assert n_bad[None] >= 20 and n_bad[2.0] == 0, n_bad


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_sized_steps_count_the_model_error_of_their_neighbourhood():
    """A 1.2 px slip step under noise 4x weaker than the texture: sized subsets over the
    step match a blend whose residual the noise hides (the residual check keeps ~30 steps
    0.3-0.7 px off). Counting the model error of the neighbours' displacement field in each
    step's σ (``model_neighbours``, default 12) makes most of them invalid; ``"auto"``
    max_sigma_px is 0.1 px with sized subsets, 0.05 px otherwise."""
    rng = np.random.default_rng(0)
    tex, pad = _texture(rng, (140, 200))
    yy, xx = np.mgrid[0:140, 0:200].astype(float)

    def frame(step_px, seed, noise=10.0):
        ux = np.where(yy >= 70, step_px, 0.0)
        img = ndimage.map_coordinates(tex, [yy + pad, xx - ux + pad], order=3)
        return 100 + 40 * img + noise * np.random.default_rng(seed).standard_normal(img.shape)

    frames = [frame(1.2, 1), frame(0.0, 2)]
    gx, gy = np.meshgrid(np.arange(30, 171, 10.0), np.arange(25, 116, 5.0))
    seeds = np.column_stack([gx.ravel(), gy.ravel()])
    true0 = seeds + np.where(seeds[:, 1] >= 70, 1.2, 0.0)[:, None] * [1, 0]
    n_bad, n_valid = {}, {}
    for mn in (None, 12):
        tr = track_reverse(frames, seeds, method="subset", progress=False, target_sigma_px=0.02,
                           model_neighbours=mn)
        e = np.linalg.norm(tr.xy[0] - true0, axis=1)
        n_bad[mn], n_valid[mn] = int((tr.valid[0] & (e > 0.3)).sum()), int(tr.valid[0].sum())
        assert tr.params["max_sigma_px"] == 0.1
    assert n_bad[None] >= 20 and n_bad[12] <= 0.3 * n_bad[None], n_bad
    assert n_valid[12] >= 100, n_valid                     # the clean rows stay valid
    clean = [frame(0.0, 3, noise=0.4), frame(0.0, 4, noise=0.4)]
    assert track_reverse(clean, seeds[:20], method="subset",
                         progress=False).params["max_sigma_px"] == 0.05
    with pytest.raises(TrackingError, match="max_sigma_px"):
        track_reverse(frames, seeds, max_sigma_px="big", progress=False)


@pytest.mark.filterwarnings("ignore::semlab.tracking.TrackingWarning")
def test_presmoothing_lets_subsets_converge_on_noisy_frames():
    """Frames 0-1 with 10x the noise: unsmoothed IC-GN converges on half the subsets of
    frame 0 and gives no finite σ in frame 1 (so no step there can be validated); with
    0.8 px pre-smoothing nearly all converge and the σ of frame 1 is finite and near the
    actual error."""
    frames, truth = make_series(noise=(0.3, 0.3, 0.03, 0.02, 0.01, 0.005))
    seeds = shi_tomasi_seeds(frames[-1], quality=0.05, border_px=12)
    true_xy = truth(seeds)
    kw = dict(method="subset", progress=False, max_sigma_px=None, min_zncc=None)
    raw = track_reverse(frames, seeds, **kw)
    sm = track_reverse(frames, seeds, smooth_sigma_px=0.8, **kw)
    assert (sm.subset_px[0] > 0).mean() > 0.85 > 0.6 > (raw.subset_px[0] > 0).mean()
    fin = np.isfinite(sm.sigma_px[1])
    assert np.isfinite(raw.sigma_px[1]).mean() < 0.1 and fin.mean() > 0.9
    err1 = _errors(sm, true_xy)[1][fin]
    assert np.sqrt(np.mean(err1 ** 2)) < 1.6 * np.median(sm.sigma_px[1][fin])
    assert sm.params["smooth_sigma_px"] == 0.8
