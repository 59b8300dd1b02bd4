"""Report figures of semlab.plots: units, legends, sizes and the trend sentence."""

import io

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from semlab import plots  # noqa: E402
from semlab.errors import SemlabError  # noqa: E402
from semlab.stats import linear_trend  # noqa: E402


@pytest.fixture(autouse=True)
def _close_figures():
    yield
    plt.close("all")


def _jpeg_bytes(fig, dpi=80):
    buf = io.BytesIO()
    fig.savefig(buf, format="jpeg", dpi=dpi, pil_kwargs={"quality": 80})
    return len(buf.getvalue())


def test_height_unit_switches_to_nm_below_one_micrometre():
    assert plots.height_unit([0.06, -0.02]) == ("nm", 1000.0)
    assert plots.height_unit([0.5, np.nan, -1.2]) == ("µm", 1.0)
    assert plots.height_unit([]) == ("nm", 1000.0)


def test_downsample_block_means():
    img = np.arange(7 * 10, dtype=float).reshape(7, 10)
    small, k = plots.downsample(img, 5)
    assert k == 2 and small.shape == (3, 5)
    assert small[1, 2] == pytest.approx(img[2:4, 4:6].mean())
    same, k = plots.downsample(img, 10)
    assert k == 1 and same.shape == img.shape


def test_downsample_averages_the_measured_pixels_of_each_block():
    z = np.arange(6 * 8, dtype=np.float32).reshape(6, 8)
    z[0, 0] = np.nan                       # a hole: its block is the mean of the other three
    z[2:4, 2:4] = np.nan                   # a block with nothing measured stays NaN
    small, k = plots.downsample(z, 4)
    assert k == 2 and small.shape == (3, 4) and small.dtype == np.float32
    assert small[0, 0] == pytest.approx(np.nanmean(z[:2, :2]))
    assert np.isnan(small[1, 1]) and np.isfinite(np.delete(small.ravel(), 5)).all()
    assert small[2, 3] == pytest.approx(z[4:6, 6:8].mean())
    same, k = plots.downsample(z, 8)
    assert k == 1 and np.array_equal(same, z, equal_nan=True)
    # a long strip keeps one block across instead of vanishing
    strip, k = plots.downsample(np.ones((3000, 10)), 100)
    assert k == 10 and strip.shape == (300, 1)
    assert plots.downsample(np.ones((10, 3000)), 100)[0].shape == (1, 300)


def test_large_maps_are_shown_from_block_means_on_the_full_maps_axes():
    """A 3000 px map is drawn from a copy of at most max_px a side (the notebook kernel does
    not hold 12 Mpx float64 copies), on axes that still span the whole map."""
    rng = np.random.default_rng(1)
    z = rng.normal(0, 0.05, (3000, 1200)).astype(np.float32)
    z[:40] = np.nan
    sg = np.full_like(z, 0.01)
    ax = plots.show_height_map(z, pixel_size_um=0.03, max_px=1000)
    im = ax.images[0]
    assert max(im.get_array().shape) <= 1000
    assert im.get_extent() == pytest.approx((-0.015, 1199.5 * 0.03, 2999.5 * 0.03, -0.015))
    fig = plots.show_heightmap_panels(z, sg, pixel_size_um=0.03, max_px=1000)
    for a in fig.axes[:3:2] + fig.axes[1:2]:
        if a.images:
            assert max(a.images[0].get_array().shape[:2]) <= 1000
            assert a.images[0].get_extent()[1] == pytest.approx(1199.5 * 0.03)
    assert fig.axes[2].get_title() == f"measured: {100 * np.isfinite(z).mean():.1f} %"
    ax = plots.show_hillshade(z, 0.03, max_px=1000)
    assert max(ax.images[0].get_array().shape[:2]) <= 1000
    assert ax.images[0].get_extent()[1] == pytest.approx(1199.5)
    img = rng.random((3000, 1200))
    ax = plots.show_height_points(img, [[10, 10]], [0.01], 0.03, max_px=1000)
    assert max(ax.images[0].get_array().shape) <= 1000
    for ax in (plots.show_image(img, max_px=1000),
               plots.show_reference_surface(img, [[10, 10], [900, 2500]], [0.0, 0.01],
                                            [True, True])):
        assert max(ax.images[0].get_array().shape) <= 1000
        assert ax.images[0].get_extent() == pytest.approx((-0.5, 1199.5, 2999.5, -0.5))
    small = plots.show_image(img[:100, :100])                 # small images as they are
    assert small.images[0].get_array().shape == (100, 100)


def test_show_height_points_um_axes_nm_colourbar_and_contrasting_edges():
    rng = np.random.default_rng(0)
    img = rng.random((60, 80))
    pts = rng.uniform(0, 79, (30, 2))
    z = rng.uniform(-0.06, 0.06, 30)
    ax = plots.show_height_points(img, pts, z, pixel_size_um=0.03)
    assert ax.get_xlabel() == "x (µm)" and ax.get_ylabel() == "y (µm)"
    left, right, bottom, top = ax.images[0].get_extent()
    assert right == pytest.approx(79.5 * 0.03) and bottom == pytest.approx(59.5 * 0.03)
    sc = ax.collections[0]
    np.testing.assert_allclose(sc.get_offsets(), pts * 0.03)
    np.testing.assert_allclose(sc.get_array(), z * 1000)          # nm
    assert np.allclose(sc.get_edgecolors()[:, :3], 0.0)           # black edges
    cbar_ax = ax.figure.axes[-1]
    assert cbar_ax.get_ylabel().startswith("z (nm)")


def test_show_height_map_in_um_and_nm():
    z = np.linspace(-0.05, 0.05, 20 * 30).reshape(20, 30)
    ax = plots.show_height_map(z, pixel_size_um=0.1)
    assert ax.get_xlabel() == "x (µm)"
    assert ax.images[0].get_extent()[1] == pytest.approx(2.95)
    assert ax.figure.axes[-1].get_ylabel().startswith("z (nm)")
    assert ax.images[0].get_array().max() == pytest.approx(50.0)


def test_projections_and_profile_in_nm_with_legends():
    rng = np.random.default_rng(1)
    xyz = np.column_stack([rng.uniform(0, 10, 40), rng.uniform(0, 8, 40), np.zeros(40)])
    z = rng.normal(0, 0.03, 40)
    fig = plots.plot_height_projections(xyz, z, np.full(40, 0.01))
    assert fig.axes[0].get_ylabel().startswith("z (nm)")
    assert fig.axes[0].get_legend() is not None
    ax = plots.plot_point_profile(np.arange(5.0), [0.2, 0.1, 0, -0.1, 1.5], np.full(5, 0.05))
    assert ax.get_ylabel() == "z (µm)"          # one value above 1 µm: µm


def test_linear_trend_ci_covers_the_true_slope():
    rng = np.random.default_rng(2)
    hits = 0
    for seed in range(200):
        r = np.random.default_rng(seed)
        x = r.uniform(0, 20, 50)
        y = 0.004 * x + r.normal(0, 0.02, 50)
        lo, hi = linear_trend(x, y)["slope_ci"]
        hits += lo <= 0.004 <= hi
    assert 0.90 <= hits / 200 <= 0.99             # a 95 % interval
    with pytest.raises(SemlabError, match="at least 3"):
        linear_trend([1, 2], [1, 2])
    with pytest.raises(SemlabError, match="constant"):
        linear_trend([1, 1, 1], [1, 2, 3])


def test_trend_sentence_reports_slope_ci_p_and_agrees_with_the_sign():
    rng = np.random.default_rng(3)
    y = rng.uniform(0, 20, 200)
    z = 0.002 * y + rng.normal(0, 0.005, 200)     # +20 nm per 10 µm
    s = plots.trend_sentence(y, z, axis="y")
    assert s.startswith("Along y, z rises by 20 nm per 10 µm (95 % CI ")
    assert "p < 0.0001" in s and "n = 200" in s and s.endswith("more extrusion at high y.")
    assert s.count(".") <= 3 and "\n" not in s     # one sentence
    s = plots.trend_sentence(y, -z, axis="y")
    assert "falls by" in s and s.endswith("more extrusion at low y.")
    noise = np.random.default_rng(30).normal(0, 0.005, 200)
    assert linear_trend(y, noise)["p"] > 0.05
    assert plots.trend_sentence(y, noise, axis="x").endswith("no significant trend with x.")


def test_tracks_overview_grid_cycles_legend_and_small_images():
    rng = np.random.default_rng(4)
    frames = [rng.random((384, 512)) for _ in range(8)]
    xy = np.tile(rng.uniform(20, 360, (1, 25, 2)), (8, 1, 1))
    valid = rng.random((8, 25)) > 0.2
    fig = plots.tracks_overview(frames, xy, valid, cycles=np.arange(8) * 1000.0)
    shown = [ax for ax in fig.axes if ax.images]
    assert len(shown) == 4
    titles = [ax.get_title() for ax in shown]
    assert titles[0] == "frame 7 · 7000 cycles" and titles[-1].startswith("frame 0")
    assert all(max(ax.images[0].get_array().shape) <= 300 for ax in shown)
    assert all(t.get_fontsize() >= plots.REPORT_FONTSIZE for ax in shown
               for t in ax.get_xticklabels())
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels == ["valid step", "flagged step", "trail to the last frame"]
    # small enough for a notebook as the report shows it (JPEG, 80 dpi), even of white noise
    assert _jpeg_bytes(fig) < 300_000
    assert len(plots.tracks_overview(frames[:2], xy[:2], valid[:2]).axes) == 2


def test_fb_errors_legend_names_every_colour():
    e = np.abs(np.random.default_rng(5).normal(0, 0.3, (5, 40))) + 1e-3
    v = e < 0.5
    ax = plots.plot_fb_errors(e, v, 0.5)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[0] == f"valid ({int(v.sum())})" and labels[1] == f"flagged ({int((~v).sum())})"
    assert labels[2] == "threshold 0.5 px"


def test_displacement_histograms_share_bins_and_overlap_as_outlines():
    rng = np.random.default_rng(6)
    seed = np.array(["corner"] * 60 + ["stereo"] * 20)
    d = np.r_[rng.normal(0.5, 0.1, 60), rng.normal(0.9, 0.05, 20)]
    fig = plots.displacement_histograms(d - 0.3, d * 0.1, np.abs(d), seed)
    for ax in fig.axes:
        patches = ax.patches
        assert len(patches) == 2
        edges = [p.get_path().vertices[:, 0] for p in patches]
        assert np.array_equal(np.unique(edges[0]), np.unique(edges[1]))   # same bins
        assert all(not p.get_fill() for p in patches)                     # outlines
        labels = [t.get_text() for t in ax.get_legend().get_texts()]
        assert labels == ["corner-seeded (60)", "stereo-seeded (20)"]
    np.testing.assert_allclose(plots.shared_bins([[0, 1], [3, np.nan]], 3), [0, 1, 2, 3])


def test_show_picked_points_one_panel_per_view():
    rng = np.random.default_rng(7)
    imgs = [rng.random((40, 50))] * 3
    pts = rng.uniform(0, 39, (4, 3, 2))
    fig = plots.show_picked_points(imgs, pts, np.arange(4), titles=["a", "b", "c"])
    assert [ax.get_title() for ax in fig.axes] == ["a", "b", "c"]
    assert len(fig.axes[1].texts) == 4


def test_show_static_jpeg_is_smaller_for_sem_images(monkeypatch):
    shown = []
    monkeypatch.setattr("IPython.display.display", lambda obj: shown.append(obj))
    from scipy import ndimage

    rng = np.random.default_rng(8)
    # SEM-like texture: smooth relief plus a little pixel noise (white noise alone is the
    # worst case for both formats)
    frames = [ndimage.gaussian_filter(rng.random((384, 512)), 2.0) + 0.01 * rng.random((384, 512))
              for _ in range(4)]
    xy = rng.uniform(20, 360, (4, 10, 2))
    valid = np.ones((4, 10), bool)
    plots.show_static(plots.tracks_overview(frames, xy, valid), dpi=100, fmt="png")
    plots.show_static(plots.tracks_overview(frames, xy, valid), dpi=100, fmt="jpeg")
    png, jpeg = shown
    assert png.format == "png" and jpeg.format == "jpeg"
    assert len(jpeg.data) < 0.6 * len(png.data)
    assert not plt.get_fignums()                  # closed after showing
    with pytest.raises(ValueError, match="fmt"):
        plots.show_static(plt.figure(), fmt="gif")


def test_line_families_views_one_panel_per_view_and_a_note_without_image():
    img = np.random.default_rng(9).random((50, 60))
    fams = {"x": [[5, 5, 40, 8], [5, 20, 40, 24]], "y": [[10, 5, 12, 45], [30, 5, 33, 45]]}
    fig = plots.show_line_families_views([img, None], [fams, fams])
    assert len(fig.axes) == 2
    assert [t.get_text() for t in fig.axes[0].get_legend().get_texts()] == ["family x",
                                                                           "family y"]
    assert "no image" in fig.axes[1].texts[0].get_text()


def test_stability_figure_has_a_series_per_model():
    st = {"sizes": np.array([8, 16, 32]), "f_angle_deg_median": np.array([3.0, 1.0, 0.3]),
          "f_angle_deg_iqr": np.array([1.0, 0.5, 0.1]),
          "epipole_angle_deg_median": np.array([2.0, 0.8, 0.2]),
          "epipole_angle_deg_iqr": np.array([1.0, 0.4, 0.1])}
    fig = plots.stability_figure({"affine": st, "8point": st})
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["F (affine)", "epipole / epipolar direction (affine)", "F (8point)",
                      "epipole / epipolar direction (8point)"]


def test_lateral_vs_depth_titles_carry_the_correlations_and_heights_in_nm():
    rng = np.random.default_rng(10)
    d = rng.uniform(0, 1, 40)
    z = 0.05 * d + rng.normal(0, 0.005, 40)
    fig = plots.lateral_vs_depth(d, z, d * 0.6, d * 0.8)
    assert fig.axes[0].get_ylabel() == "z (nm)"
    r = np.corrcoef(d, z)[0, 1]
    assert fig.axes[0].get_title().startswith(f"Pearson {r:+.2f} [")
    np.testing.assert_allclose(fig.axes[0].lines[0].get_ydata(), z * 1000)


def test_strain_maps_directions_and_history():
    gx, gy = np.arange(0, 100, 10.0), np.arange(0, 60, 10.0)
    e = np.full((6, 10), 0.01)
    fig = plots.strain_maps(gx, gy, {"E_xx": e, "E_yy": -e}, pixel_size_um=0.03)
    assert [ax.get_title() for ax in fig.axes[:2]] == ["E_xx", "E_yy"]
    assert fig.axes[0].get_xlabel() == "x (µm)"
    # the cells are centred on their grid points: edges half a spacing (5 px) beyond them
    assert fig.axes[0].images[0].get_extent() == pytest.approx(
        [-5 * 0.03, 95 * 0.03, 55 * 0.03, -5 * 0.03])
    holes = np.zeros((6, 10), bool)
    holes[2, 3] = holes[4, 7] = True
    fig = plots.strain_maps(gx, gy, {"E_xx": e, "E_yy": -e}, interpolated=holes)
    for ax in fig.axes[:2]:                    # each map marks the interpolated points
        (dots,) = ax.lines
        np.testing.assert_allclose(np.column_stack(dots.get_data()), [[30, 20], [70, 40]])
    (leg,) = fig.legends                       # named once, below the maps
    assert "interpolated" in leg.get_texts()[0].get_text()
    fig = plots.strain_maps(gx, gy, {"E_xx": np.full((6, 10), np.nan)})   # nothing measured
    assert fig.axes[0].images[0].get_clim() == pytest.approx((-1e-6, 1e-6))
    # error bars: a one-sided scale from 0, labelled as the 1σ
    sig = np.linspace(1e-4, 1e-3, 60).reshape(6, 10)
    fig = plots.strain_maps(gx, gy, {"1σ of E_xx": sig}, sigma=True)
    assert fig.axes[0].images[0].get_clim() == pytest.approx((0.0, np.percentile(sig, 98)))
    assert fig.axes[1].get_ylabel() == "1σ of the strain (–)"
    assert fig.axes[0].images[0].get_cmap().name == "viridis"
    fig = plots.strain_maps(gx, gy, {"E_xx": np.full((6, 10), np.nan)})
    assert fig.axes[0].images[0].get_clim() == pytest.approx((-1e-6, 1e-6))
    ax = plots.principal_directions(gx, gy, e, np.zeros_like(e))
    assert ax.get_legend() is not None and ax.yaxis_inverted()
    ax = plots.strain_history({"exx": [0.0, 0.001, 0.002], "eyy": [0, 0, 0.001]},
                              cycles=[0, 1000, 2000])
    assert ax.get_xlabel() == "cycles" and len(ax.lines) == 2
    assert not ax.containers and ax.get_title() == ""
    # with the history's 1σ: a ±1σ error bar at every point (none where σ is NaN)
    ax = plots.strain_history({"exx": [0.0, 0.001, 0.002], "exx_sigma": [0.0, 1e-4, np.nan],
                               "eyy": [0, 0, 0.001], "eyy_sigma": [np.nan] * 3},
                              cycles=[0, 1000, 2000])
    (bars,) = ax.containers
    seg = bars.lines[2][0].get_segments()
    assert np.allclose([s[1, 1] - s[0, 1] for s in seg], [0.0, 2e-4, 0.0])
    assert "1σ" in ax.get_title()


def test_error_histograms_share_bins_in_nm():
    rng = np.random.default_rng(11)
    ax = plots.error_histograms({"raw": rng.normal(0, 0.09, 100), "auto": rng.normal(0, 0.01, 300)})
    edges = [np.unique(p.get_path().vertices[:, 0]) for p in ax.patches]
    assert np.array_equal(edges[0], edges[1]) and edges[0].max() > 100      # nm
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["raw (100)", "auto (300)"]
