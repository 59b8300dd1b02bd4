"""ISO 25178 parameters, band profiles and the two-point profile: known answers."""

import numpy as np
import pytest

from semlab import metrology as mt, plots
from semlab.errors import GeometryError, SemlabError

S = 0.03  # µm per pixel


def _sine(shape=(120, 160), amp=0.1, period_px=20.0):
    x = np.arange(shape[1])[None, :] * np.ones((shape[0], 1))
    return amp * np.sin(2 * np.pi * x / period_px)


def test_height_parameters_of_a_sine_with_and_without_holes():
    z = _sine(amp=0.1)
    row = mt.surface_parameters(z, S)[0]
    assert row["region"] == "map" and row["n_pixels"] == z.size
    # the sampled sine (20 samples per period): Sa = A cot(π/20) / 10, about 2A/π
    assert row["Sa"] == pytest.approx(0.1 / np.tan(np.pi / 20) / 10, rel=1e-9)
    assert row["Sa"] == pytest.approx(2 * 0.1 / np.pi, rel=0.01)
    assert row["Sq"] == pytest.approx(0.1 / np.sqrt(2), rel=2e-3)
    assert row["Ssk"] == pytest.approx(0.0, abs=1e-6)
    assert row["Sku"] == pytest.approx(1.5, rel=2e-3)
    assert row["Sz"] == pytest.approx(0.2, rel=1e-2)
    holes = z.copy()
    rng = np.random.default_rng(0)
    holes[rng.random(z.shape) < 0.1] = np.nan          # 10 % not measured, at random
    h = mt.surface_parameters(holes, S)[0]
    assert h["n_pixels"] == int(np.isfinite(holes).sum())
    assert h["measured_fraction"] == pytest.approx(0.9, abs=0.01)
    for k in ("Sa", "Sq", "Sku"):
        assert h[k] == pytest.approx(row[k], rel=0.02), k


def test_sdr_summed_over_strips_is_the_whole_maps_with_a_strips_memory():
    import tracemalloc

    from surfalize import Surface

    z = np.random.default_rng(0).normal(0, 0.05, (2048, 256))
    whole = Surface(z, S, S).Sdr()
    mt._sdr(z[:10], S)                                  # imports and caches out of the count
    tracemalloc.start()
    try:
        by_strips = mt._sdr(z, S, strip_rows=64)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert by_strips == pytest.approx(whole, rel=1e-12)
    assert mt._sdr(z[:66], S, strip_rows=64) == pytest.approx(Surface(z[:66], S, S).Sdr(),
                                                              rel=1e-12)   # a 2-row last strip
    assert peak < 0.5 * z.nbytes       # surfalize on the whole map: ~9 copies of it


def test_sdr_of_a_tilted_plane_and_regions():
    g = 0.2                                              # slope dz/dx
    x = np.arange(100)[None, :] * np.ones((80, 1)) * S
    z = g * x
    z[:, 50:] = 0.0                                      # right half flat
    rows = mt.surface_parameters(z, S, regions={"slope": (0, 0, 50, 80),
                                                "flat": (55, 0, 100, 80)})
    by = {r["region"]: r for r in rows}
    assert by["slope"]["Sdr"] == pytest.approx((np.sqrt(1 + g ** 2) - 1) * 100, rel=1e-3)
    assert by["flat"]["Sdr"] == pytest.approx(0.0, abs=1e-9)
    assert by["flat"]["Sq"] == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(by["flat"]["Ssk"])                  # undefined for a flat region
    assert by["slope"]["n_pixels"] == 50 * 80
    mask = np.zeros(z.shape, bool)
    mask[:10, :10] = True
    assert mt.surface_parameters(z, S, regions={"m": mask})[1]["n_pixels"] == 100
    with pytest.raises(SemlabError, match="region 'bad'"):
        mt.surface_parameters(z, S, regions={"bad": (0, 0, 500, 10)})
    with pytest.raises(SemlabError, match="reserved"):
        mt.surface_parameters(z, S, regions={"map": (0, 0, 5, 5)})


def test_surface_parameters_csv(tmp_path):
    rows = mt.surface_parameters(_sine(), S, regions={"a": (0, 0, 40, 40)})
    p = mt.write_surface_parameters_csv(tmp_path / "surface_parameters.csv", rows)
    lines = p.read_text().splitlines()
    assert lines[0] == ("region,n_pixels,measured_fraction,Sa_um,Sq_um,Sp_um,Sv_um,Sz_um,"
                        "Ssk,Sku,Sdr_percent")
    assert len(lines) == 3 and lines[2].startswith("a,1600,1,")


def _ribbon(shape=(150, 200), angle_deg=35.0, offset_px=0.0, width_px=12.0, amp=0.2,
            edge_px=1.0, groove=None):
    """A straight extrusion ribbon (and optionally a groove beside it) through the centre."""
    hgt, wid = shape
    yy, xx = np.mgrid[0:hgt, 0:wid].astype(float)
    a = np.deg2rad(angle_deg)
    n = -(xx - wid / 2) * np.sin(a) + (yy - hgt / 2) * np.cos(a) - offset_px
    z = amp * 0.5 * (np.tanh((n + width_px / 2) / edge_px) - np.tanh((n - width_px / 2) / edge_px))
    if groove is not None:
        depth, at_px, sig_px = groove
        z -= depth * np.exp(-0.5 * ((n - at_px) / sig_px) ** 2)
    return z


def test_band_profile_measures_a_known_ribbon():
    z = _ribbon(amp=0.2, width_px=12.0, groove=(0.08, 14.0, 2.0))
    rng = np.random.default_rng(1)
    noisy = z + rng.normal(0, 0.005, z.shape)
    sig = np.full(z.shape, 0.005)
    a = np.deg2rad(35.0)
    c = np.array([100.0, 75.0])
    d = np.array([np.cos(a), np.sin(a)])
    band = mt.Band(0, tuple(c - 60 * d), tuple(c + 60 * d), "crack_id", half_width_px=30)
    p = mt.band_profile(noisy, sig, S, band)
    assert p["extrusion_um"] == pytest.approx(0.2, abs=max(0.01, 3 * p["extrusion_err_um"]))
    assert p["intrusion_um"] == pytest.approx(0.08, abs=max(0.01, 3 * p["intrusion_err_um"]))
    assert p["width_um"] == pytest.approx(12.0 * S, abs=max(0.03, 3 * p["width_err_um"]))
    assert 0 < p["extrusion_err_um"] < 0.01 and 0 < p["width_err_um"] < 0.05
    assert p["length_um"] == pytest.approx(120 * S)
    loc = mt.band_profile(noisy + 0.03, sig, S, band, baseline="local")   # an offset surface
    assert loc["baseline_um"] == pytest.approx(0.03, abs=0.005)
    assert loc["extrusion_um"] == pytest.approx(p["extrusion_um"], abs=0.005)
    assert loc["extrusion_err_um"] > p["extrusion_err_um"]           # the baseline's σ adds
    with pytest.raises(SemlabError, match="baseline"):
        mt.band_profile(noisy, sig, S, band, baseline="median")
    # the groove lies on the positive side (n > 0 is to the right of p0 -> p1 with y down)
    assert p["distance_um"][np.nanargmin(p["z_um"])] > 0


def test_detect_bands_finds_the_ribbon_direction_and_position():
    z = _ribbon(angle_deg=35.0, offset_px=10.0, amp=0.15) + 0.001 * np.arange(200)[None, :] * 0
    bands = mt.detect_bands(z, S, min_prominence_um=0.05)
    assert len(bands) >= 1
    b = bands[0]
    assert b.source == "detected"
    assert abs(((b.angle_deg - 35.0) + 90) % 180 - 90) < 1.0
    # the trace passes through the ribbon centre: offset 10 px along the normal
    a = np.deg2rad(35.0)
    n = np.array([-np.sin(a), np.cos(a)])
    mid = (np.asarray(b.p0_px) + np.asarray(b.p1_px)) / 2 - np.array([100.0, 75.0])
    assert mid @ n == pytest.approx(10.0, abs=1.5)
    assert mt.detect_bands(np.full((20, 20), np.nan), S) == []


def test_bands_from_clicks():
    t = np.linspace(0, 50, 6)
    pts = np.column_stack([10 + t * 0.8, 20 + t * 0.6])
    pts = np.vstack([pts, [[5.0, 5.0], [100.0, 100.0]]])
    cid = np.array([3] * 6 + [-1, 7])                    # crack 7 has one point only
    bands = mt.bands_from_clicks(pts, cid)
    assert len(bands) == 1 and bands[0].band_id == 3 and bands[0].source == "crack_id"
    ends = sorted([bands[0].p0_px, bands[0].p1_px])
    np.testing.assert_allclose(ends, [[10, 20], [50, 50]], atol=1e-9)
    assert bands[0].angle_deg == pytest.approx(np.degrees(np.arctan2(0.6, 0.8)))
    with pytest.raises(GeometryError):
        mt.bands_from_clicks(pts, cid[:-1])


def test_map_bands_puts_clicked_cracks_first():
    z = _ribbon(angle_deg=35.0, amp=0.15)
    pts = np.array([[10.0, 10.0], [60.0, 40.0], [110.0, 70.0]])
    bands = mt.map_bands(z, S, pts_px=pts, crack_id=np.array([4, 4, 4]), min_prominence_um=0.05)
    assert bands[0].source == "crack_id" and bands[0].band_id == 4
    assert [b.band_id for b in bands[1:]] == list(range(5, 5 + len(bands) - 1))
    assert len(bands) >= 2 and all(b.source == "detected" for b in bands[1:])


def test_bands_csv(tmp_path):
    z = _ribbon()
    band = mt.detect_bands(z, S, min_prominence_um=0.05)[0]
    p = mt.write_bands_csv(tmp_path / "bands.csv", [mt.band_profile(z, None, S, band)])
    head, row = p.read_text().splitlines()[:2]
    assert head.split(",") == list(mt.BANDS_COLUMNS)
    assert row.split(",")[1] == "detected"


def test_profile_between_on_a_plane_and_near_holes():
    x = np.arange(60)[None, :] * np.ones((40, 1))
    z = 0.01 * x
    sig = np.full(z.shape, 0.002)
    pr = mt.profile_between(z, sig, (5, 10), (45, 10), S, width_px=3)
    np.testing.assert_allclose(pr["z_um"], 0.01 * pr["xy_px"][:, 0], atol=1e-12)
    np.testing.assert_allclose(pr["distance_um"][-1], 40 * S)
    np.testing.assert_allclose(pr["sigma_um"], 0.002)
    z[:, 30] = np.nan
    pr = mt.profile_between(z, sig, (5, 10), (45, 10), S)
    dist = np.abs(pr["xy_px"][:, 0] - 30)
    assert np.all(np.isnan(pr["z_um"][dist < 1])) and np.isfinite(pr["z_um"][dist > 1]).all()
    with pytest.raises(GeometryError, match="same point"):
        mt.profile_between(z, sig, (5, 5), (5, 5), S)


def test_band_plots():
    import matplotlib.pyplot as plt

    z = _ribbon(groove=(0.05, 14.0, 2.0))
    bands = mt.detect_bands(z, S, min_prominence_um=0.03)
    profs = [mt.band_profile(z, np.full(z.shape, 0.004), S, b) for b in bands]
    fig = plots.plot_band_profiles(profs)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible()]
    assert len(titles) == len(bands) and titles[0].startswith("band 0")
    # the lowest point signed: below the baseline "−45", above it "+45", never "−-45"
    odd = dict(profs[0], extrusion_um=0.236, intrusion_um=-0.045)
    title = plots.plot_band_profiles([odd]).axes[0].get_title()
    assert "+236±" in title and "/ +45±" in title and "−-" not in title
    deep = dict(profs[0], extrusion_um=0.236, intrusion_um=0.045)
    assert "/ −45±" in plots.plot_band_profiles([deep]).axes[0].get_title()
    plt.close("all")
    ax = plots.show_bands(z, bands)
    assert len(ax.lines) == len(bands)
    # in µm axes the traces are drawn in µm too, over the map, and the view is the map's
    ax = plots.show_bands(z, bands, pixel_size_um=S)
    (x0, y0), (x1, y1) = bands[0].p0_px, bands[0].p1_px
    np.testing.assert_allclose(ax.lines[0].get_xydata(), [[x0 * S, y0 * S], [x1 * S, y1 * S]])
    assert ax.get_xlim() == pytest.approx((-0.5 * S, 199.5 * S))
    assert ax.get_xlim() == pytest.approx(ax.images[0].get_extent()[:2])
    ax = plots.plot_profile(mt.profile_between(z, None, (0, 0), (199, 149), S))
    assert ax.get_ylabel() == "z (nm)" and len(ax.collections) == 1
    plt.close("all")


def test_profile_tool_clicks_and_set_points():
    import matplotlib.pyplot as plt
    from types import SimpleNamespace

    from semlab.profile_tool import ProfileTool

    z = _ribbon()
    tool = ProfileTool(z, np.full(z.shape, 0.004), S)
    # the map's axes are in µm, so are the clicks (event.xdata); the end points are pixels
    assert tool.ax_map.get_xlabel() == "x (µm)"
    click = lambda x, y, ax=tool.ax_map: SimpleNamespace(  # noqa: E731
        inaxes=ax, xdata=x * S, ydata=y * S, button=1)
    tool._on_click(click(20.0, 20.0))
    assert tool.profile is None and len(tool.points) == 1
    tool._on_click(click(5.0, 5.0, ax=tool.ax_profile))      # clicks beside the map are ignored
    assert len(tool.points) == 1
    tool._on_click(click(180.0, 130.0))
    assert tool.points == [pytest.approx((20.0, 20.0)), pytest.approx((180.0, 130.0))]
    ref = mt.profile_between(z, np.full(z.shape, 0.004), (20, 20), (180, 130), S)
    np.testing.assert_allclose(tool.profile["z_um"], ref["z_um"])
    np.testing.assert_allclose(tool._line.get_xydata(), [[20 * S, 20 * S], [180 * S, 130 * S]])
    assert len(tool.ax_profile.lines) >= 1 and tool.ax_profile.get_ylabel() == "z (nm)"
    tool._on_click(click(30.0, 30.0))                        # a third click starts again
    assert len(tool.points) == 1
    prof = tool.set_points((0, 75), (199, 75))
    assert prof["distance_um"][-1] == pytest.approx(199 * S)
    np.testing.assert_allclose(tool._line.get_xydata(), [[0, 75 * S], [199 * S, 75 * S]])
    assert tool.ax_map.get_xlim() == pytest.approx((-0.5 * S, 199.5 * S))
    plt.close("all")


def test_regions_on_map_follow_the_map_window(tmp_path):
    from semlab.io import write_tiff

    roi = (10, 20, 74, 68)                    # the map covers view-0 x 10..73, y 20..67
    mask = np.zeros((96, 128), np.uint8)
    mask[30:40, 50:60] = 1
    write_tiff(tmp_path / "m.tif", mask)
    regions = {"box": [12, 22, 21, 31], "tri": [[10, 20], [40, 20], [10, 50]],
               "pit": tmp_path / "m.tif", "away": [100, 80, 120, 90]}
    m = mt.regions_on_map(regions, roi)
    assert all(v.shape == (48, 64) and v.dtype == bool for v in m.values())
    # the rectangle is inclusive (as [stereo] reference_region): 10 × 10 view-0 pixels
    assert m["box"].sum() == 100 and m["box"][2:12, 2:12].all()
    assert m["pit"].sum() == 100 and m["pit"][10:20, 40:50].all()
    assert m["tri"][1, 1] and m["tri"][5, 5] and not m["tri"][29, 29]
    assert 400 < m["tri"].sum() < 500              # half of a 30 × 30 square
    assert not m["away"].any()
    z = np.where(np.arange(64)[None, :] < 32, 0.1, -0.1) * np.ones((48, 1))
    rows = mt.surface_parameters(z, 0.03, regions=m)
    by = {r["region"]: r for r in rows}
    assert by["box"]["n_pixels"] == 100 and by["box"]["Sa"] == 0.0
    assert np.isnan(by["away"]["Sa"]) and by["away"]["n_pixels"] == 0
