"""semlab.flow: the variational displacement map."""

import numpy as np
import pytest
from scipy import ndimage

from semlab.errors import ImageError, SemlabError
from semlab.flow import FlowParams, variational_flow

INNER = (slice(24, -24), slice(24, -24))


def _texture(n=128, seed=0):
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5), rng


def test_a_large_shift_needs_the_pyramid():
    """A 5 px shift started from zero: beyond one linearisation at full resolution (the map
    lands elsewhere), found to 0.01 px with the coarse-to-fine levels."""
    f0, _ = _texture()
    f1 = ndimage.shift(f0, (0, -5.0), order=3, mode="nearest")   # f1(x) = f0(x + 5)
    zero = np.zeros(f0.shape)
    u, v, info = variational_flow(f1, f0, zero, zero)
    assert info["levels"] == 2
    np.testing.assert_allclose(u[INNER], 5.0, atol=0.01)
    np.testing.assert_allclose(v[INNER], 0.0, atol=0.01)
    u0, _, _ = variational_flow(f1, f0, zero, zero, params=FlowParams(levels=0))
    assert abs(np.median(u0[INNER]) - 5.0) > 1.0


def test_the_prior_scale_follows_the_noise():
    """The smoothing is not a constant: with 5× the image noise the prior scale (what
    neighbours may differ by) grows about 5×, and the map of a sub-pixel shift stays unbiased."""
    f0, rng = _texture()
    out = []
    for noise in (0.01, 0.05):
        a = f0 + rng.normal(0, noise, f0.shape)
        b = ndimage.shift(f0, (0.3, 0.2), order=3, mode="nearest") + rng.normal(0, noise, f0.shape)
        u, v, info = variational_flow(b, a, np.zeros(f0.shape), np.zeros(f0.shape))
        assert np.median(u[INNER]) == pytest.approx(-0.2, abs=0.01)
        assert np.median(v[INNER]) == pytest.approx(-0.3, abs=0.01)
        out.append(info["prior_scale_px"])
    assert 3.5 < out[1] / out[0] < 6.5


def test_errors():
    f0, _ = _texture(32)
    z = np.zeros(f0.shape)
    bad = f0.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ImageError, match="NaN"):
        variational_flow(bad, f0, z, z)
    with pytest.raises(ImageError, match="one shape"):
        variational_flow(f0, f0[:-1], z, z)
    with pytest.raises(ImageError, match="at least 16"):
        variational_flow(f0[:8], f0[:8], z[:8], z[:8])
    with pytest.raises(SemlabError, match="u0 and v0 must be"):
        variational_flow(f0, f0, z[:-1], z)
    zn = z.copy()
    zn[0, 0] = np.nan
    with pytest.raises(SemlabError, match="NaN"):
        variational_flow(f0, f0, zn, z)
    with pytest.raises(SemlabError, match="warps and irls"):
        variational_flow(f0, f0, z, z, params=FlowParams(warps=0))
    with pytest.raises(SemlabError, match="tile_px must be"):
        variational_flow(f0, f0, z, z, params=FlowParams(tile_px=50))
    with pytest.raises(SemlabError, match="halo_px >= 0"):
        variational_flow(f0, f0, z, z, params=FlowParams(halo_px=-1))
    with pytest.raises(SemlabError, match="sample_at"):
        variational_flow(f0, f0, z, z, n_samples=4)
    with pytest.raises(SemlabError, match="sample_at"):
        variational_flow(f0, f0, z, z, n_samples=4, sample_at=[[40, 3]])


def test_a_noise_free_rendered_pair_with_a_black_background():
    """Integer frames that measure zero noise, a textured patch on a black background (as
    the DIC Challenge rotation set, 82 % black): the data term's σ is floored at the grey
    levels' quantisation noise instead of giving the pixels infinite weight (the solve broke
    down with NaN before), and the patch's 2 px shift is found."""
    from semlab.flow import _noise_floor
    from semlab.noise import image_noise_sigma

    f0, _ = _texture(160, seed=3)
    a = np.zeros((160, 160))
    a[40:120, 40:120] = np.round(100 + 400 * f0[40:120, 40:120])
    b = np.roll(a, 2, axis=1)                 # b(x) = a(x − 2): a's pixel x is at x + 2
    assert image_noise_sigma(a) == 0.0
    assert _noise_floor(a) == pytest.approx(1 / np.sqrt(12)) and _noise_floor(a + 0.5) < 0.1
    u, v, _ = variational_flow(a, b, np.zeros(a.shape), np.zeros(a.shape))
    assert np.isfinite(u).all() and np.isfinite(v).all()
    patch = (slice(50, 110), slice(50, 108))
    assert np.median(np.abs(u[patch] - 2.0)) < 0.01 and np.median(np.abs(v[patch])) < 0.01


def test_tiles_give_the_whole_frame_solve():
    """Frames larger than ``tile_px`` are solved in core tiles with a halo (the memory of one
    solve grows with its pixels): the map of a noisy texture with a slip band's 1.5 px step
    equals the whole-frame solve to a tenth of its posterior 1σ everywhere, the seams
    included (0.002 against 0.027 px), and so do the posterior's draws and the prior's pull.
    Without the halo (the ring held at the core's edge) the tiles are 0.27 px off."""
    f0, rng = _texture(176, seed=4)
    f0 = f0[:, :160]
    yy, xx = np.mgrid[0:176, 0:160].astype(float)
    step = 1.5 * 0.5 * (1 + np.tanh((xx - 70.0) / 1.5))
    f1 = ndimage.map_coordinates(f0, [yy - step, xx - 0.3], order=3, mode="nearest")
    noise = 0.1 * f0.std()
    a, b = f0 + rng.normal(0, noise, f0.shape), f1 + rng.normal(0, noise, f0.shape)
    zero = np.zeros(a.shape)
    at = np.column_stack([xx[8::16, 8::16].ravel(), yy[8::16, 8::16].ravel()]).astype(int)
    u, v, info = variational_flow(a, b, zero, zero, n_samples=24, sample_at=at)
    assert info["tiles"] == 1
    assert np.median(np.abs(v[:, 90:] - 1.5)) < 0.05      # the step is found
    sd = info["samples_px"].std(0)
    ut, vt, it = variational_flow(a, b, zero, zero, params=FlowParams(tile_px=64, halo_px=32),
                                  n_samples=24, sample_at=at)
    assert it["tiles"] == 9
    d = np.hypot(ut - u, vt - v)
    assert d.max() < 0.1 * np.median(sd)
    np.testing.assert_allclose(it["bias_px"], info["bias_px"], atol=0.01)
    np.testing.assert_allclose(np.median(it["samples_px"].std(0), 0), np.median(sd, 0), rtol=0.2)
    u0, v0, _ = variational_flow(a, b, zero, zero, params=FlowParams(tile_px=64, halo_px=0))
    assert np.hypot(u0 - u, v0 - v).max() > 0.05
