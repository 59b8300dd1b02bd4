"""Min-σ fusion of two dense height maps (semlab.fusion)."""

import numpy as np
import pytest

from semlab.errors import SemlabError
from semlab import fusion
from semlab.fusion import fuse_heightmaps, min_sigma_choice
from semlab.heightmap import HeightMap


def _two_maps(shape=(64, 96), seed=0):
    """Truth 0; map a is sharp on the left half, map b on the right, σ telling so."""
    rng = np.random.default_rng(seed)
    left = np.zeros(shape, bool)
    left[:, : shape[1] // 2] = True
    s_a = np.where(left, 0.01, 0.10)
    s_b = np.where(left, 0.10, 0.01)
    z_a = rng.normal(0, 1, shape) * s_a
    z_b = rng.normal(0, 1, shape) * s_b
    return z_a, s_a, z_b, s_b, left


def _rms(a):
    return float(np.sqrt(np.mean(a ** 2)))


def test_min_sigma_choice_takes_the_sharper_map_on_each_part():
    z_a, s_a, z_b, s_b, left = _two_maps()
    ok = np.ones(left.shape, bool)
    z, s, valid, pick_b = min_sigma_choice(z_a, s_a, ok, z_b, s_b, ok)
    assert valid.all()
    np.testing.assert_array_equal(pick_b, ~left)
    # either map alone is ~0.07 RMS (half its pixels at 0.1); the fusion is ~0.01
    assert _rms(z) < 0.015
    assert _rms(z_a) > 0.05 and _rms(z_b) > 0.05
    np.testing.assert_allclose(s, 0.01, rtol=1e-6)
    # the kept σ is honest: about 68 % of the errors within 1σ
    assert 0.6 < np.mean(np.abs(z) < s) < 0.76


def test_min_sigma_choice_fills_from_the_other_map_where_one_is_missing():
    z_a, s_a, z_b, s_b, left = _two_maps()
    v_a = np.ones(left.shape, bool)
    v_a[:, :8] = False                        # a not measured on its sharp strip
    z_a = np.where(v_a, z_a, np.nan)
    v_b = np.ones(left.shape, bool)
    v_b[:, -8:] = False                       # b not measured on its sharp strip
    v_b[:4, :8] = False                       # neither measured in one corner
    z, s, valid, pick_b = min_sigma_choice(z_a, s_a, v_a, z_b, s_b, v_b)
    assert not valid[:4, :8].any() and np.isnan(z[:4, :8]).all()
    assert pick_b[4:, :8].all()               # only b measured there
    assert not pick_b[:, -8:].any()           # only a measured there
    np.testing.assert_array_equal(z[4:, :8], z_b[4:, :8].astype(np.float32))
    assert valid.sum() == valid.size - 32


def test_min_sigma_choice_rejects_different_grids():
    z = np.zeros((8, 8))
    with pytest.raises(SemlabError, match="same pixel grid"):
        min_sigma_choice(z, z + 1, z == 0, z[:4], z[:4] + 1, z[:4] == 0)


def _hm(z, s, roi):
    return HeightMap(z_um=z.astype(np.float32), sigma_um=s.astype(np.float32),
                     valid=np.isfinite(z), pixel_size_um=0.1, roi=roi, parallax=None,
                     notes=["made in a test"])


def test_fuse_heightmaps_keeps_roi_and_notes_and_checks_roi():
    z_a, s_a, z_b, s_b, left = _two_maps()
    roi = (0, 0, left.shape[1], left.shape[0])
    hf = fuse_heightmaps(_hm(z_a, s_a, roi), _hm(z_b, s_b, roi))
    assert hf.roi == roi and hf.valid.all()
    assert _rms(hf.z_um) < 0.015
    assert "made in a test" in hf.notes[0] and "50.0 % of the measured pixels" in hf.notes[-1]
    with pytest.raises(SemlabError, match="same heightmap_roi"):
        fuse_heightmaps(_hm(z_a, s_a, roi), _hm(z_b, s_b, (1, 0) + roi[2:]))


def test_inverse_variance_known_answers_and_scatter():
    from semlab.fusion import inverse_variance

    a = np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 2.0], [np.nan, 0.0]])
    b = np.array([[1.0, 1.0], [2.0, 4.0], [np.nan, 0.0], [3.0, 3.0]])
    f, s, wb = inverse_variance(a, [1.0, 1.0, 1.0, 1.0], b, [1.0, np.sqrt(3.0), 1.0, 2.0])
    assert np.allclose(f[0], 0.5) and np.isclose(s[0], np.sqrt(0.5)) and wb[0] == 0.5
    assert np.allclose(f[1], [0.5, 1.0]) and np.isclose(wb[1], 0.25)   # σ_b² = 3 σ_a²
    assert np.isclose(s[1], np.sqrt(0.75))
    assert np.allclose(f[2], [1.0, 2.0]) and s[2] == 1.0 and wb[2] == 0   # no b: a
    assert np.allclose(f[3], [3.0, 3.0]) and s[3] == 2.0 and wb[3] == 1   # no a: b
    # uncorrelated estimates: the average's scatter is its σ
    rng = np.random.default_rng(0)
    sa, sb = rng.uniform(0.5, 2, 20000), rng.uniform(0.5, 2, 20000)
    f, s, _ = inverse_variance(rng.normal(0, sa), sa, rng.normal(0, sb), sb)
    assert abs(np.std(f / s) - 1) < 0.02
    # a σ that is huge, infinite or tiny (a point the map barely constrains, or a perfect one)
    # weighs nothing or everything, without an overflow (warnings are errors here; pollen_pot1
    # in CI once gave one)
    f, s, wb = inverse_variance(np.zeros(3), [1.0, 1e-200, 1e300], np.ones(3),
                                [1e300, 1.0, np.inf])
    assert np.allclose(f, [0.0, 0.0, 0.0]) and np.allclose(s, [1.0, 1e-200, 1e300])
    assert np.allclose(wb, 0.0)
    f, s, wb = inverse_variance(np.zeros(1), [1e300], np.ones(1), [1e-300])
    assert f[0] == 1.0 and s[0] == 1e-300 and wb[0] == 1.0
    with pytest.raises(SemlabError, match="one σ per row"):
        inverse_variance(a, [1.0], b, [1.0])
    # a weight σ apart from the bar's: w_b = σa² / (σa² + σb'²), σ = sqrt(w_a² σa² + w_b² σb²)
    f, s, wb = inverse_variance(a[:2], [1.0, 1.0], b[:2], [2.0, 2.0],
                                weight_sigma_b=[1.0, np.sqrt(3.0)])
    assert np.allclose(wb, [0.5, 0.25]) and np.allclose(f, [[0.5, 0.5], [0.5, 1.0]])
    assert np.allclose(s, [np.hypot(0.5, 1.0), np.hypot(0.75, 0.5)])
    f, s, wb = inverse_variance(a[:1], [1.0], b[:1], [2.0], weight_sigma_b=[np.nan])
    assert wb[0] == 0 and s[0] == 1.0 and np.allclose(f, 0.0)     # no weight σ: b unused
    with pytest.raises(SemlabError, match="one σ per row"):
        inverse_variance(a, np.ones(4), b, np.ones(4), weight_sigma_b=[1.0])


def test_inverse_variance_keeps_a_shared_error_in_full():
    """An error both estimates carry (a wall rounded by the subset and the map alike) is not
    averaged away: the average's 1σ keeps it in full, and then matches the scatter."""
    from semlab.fusion import inverse_variance

    f, s, wb = inverse_variance(np.zeros((1, 2)), [np.sqrt(2.0)], np.ones((1, 2)), [1.0],
                                shared_sigma=[1.0])
    # w_b = 2 / 3: sqrt((1/3)² (2 − 1) + (2/3)² 1 + 1)
    assert np.isclose(wb[0], 2 / 3) and np.isclose(s[0], np.sqrt(1 / 9 + 4 / 9 + 1))
    rng = np.random.default_rng(1)
    n = 20000
    ss, na, nb = rng.uniform(0.2, 1.5, n), rng.uniform(0.5, 2, n), rng.uniform(0.3, 1, n)
    shared = rng.normal(0, ss)
    a, b = shared + rng.normal(0, na), shared + rng.normal(0, nb)
    sa = np.hypot(ss, na)
    f, s, _ = inverse_variance(a, sa, b, nb, shared_sigma=ss)
    assert abs(np.std(f / s) - 1) < 0.02
    f0, s0, _ = inverse_variance(a, sa, b, nb)          # without: the bar is too small
    assert np.std(f0 / s0) > 1.2
    # a shared σ above σ_a is capped at σ_a; NaN means none; one per row
    _, s1, _ = inverse_variance(np.zeros(2), [1.0, 1.0], np.zeros(2), [1.0, 1.0],
                                shared_sigma=[5.0, np.nan])
    assert np.isclose(s1[0], np.sqrt(0.25 + 1.0)) and np.isclose(s1[1], np.sqrt(0.5))
    with pytest.raises(SemlabError, match="shared σ"):
        inverse_variance(np.zeros(2), [1.0, 1.0], np.zeros(2), [1.0, 1.0], shared_sigma=[1.0])


def test_sample_parallax_bilinear_and_holes():
    from semlab.fusion import sample_parallax
    from semlab.heightmap import DenseParallax

    yy, xx = np.mgrid[0:20, 0:30].astype(float)
    valid = np.ones((20, 30), bool)
    valid[10, 15] = False
    # roi starts at (5, 3): element [i, j] is the view-0 pixel (5 + j, 3 + i)
    dm = DenseParallax(x1_px=xx + 5 + 0.5 * (yy + 3), y1_px=yy + 3 + 0.1,
                       sigma_px=np.full((20, 30), 0.2), sigma_y_px=np.full((20, 30), 0.3), valid=valid, zncc=np.ones((20, 30)),
                       roi=(5, 3, 35, 23), sigma_scale=1.0, params=None)
    p = np.array([[7.25, 4.5], [20.0, 13.0], [2.0, 4.0], [12.5, 9.75]])
    xy1, s = sample_parallax(dm, p)
    assert np.allclose(xy1[0], [7.25 + 0.5 * 4.5, 4.6]) and np.isclose(s[0], 0.2)
    assert np.allclose(xy1[3], [12.5 + 0.5 * 9.75, 9.85])
    assert np.all(np.isnan(xy1[1])) and np.isnan(s[1])     # next to a hole
    assert np.all(np.isnan(xy1[2])) and np.isnan(s[2])     # outside the roi
    # the weight σ of a variational map, when it has one
    with pytest.raises(SemlabError, match="no 'weight_sigma_px'"):
        sample_parallax(dm, p, sigma="weight_sigma_px")
    from dataclasses import replace
    _, sw = sample_parallax(replace(dm, weight_sigma_px=np.full((20, 30), 0.1)), p,
                            sigma="weight_sigma_px")
    assert np.isclose(sw[0], 0.1) and np.isnan(sw[1])


def test_agreement_scale_is_the_missing_variance_of_the_second_estimate():
    rng = np.random.default_rng(3)
    n = 4000
    truth = rng.normal(0, 5, n)
    sa, sb = np.full(n, 0.1), rng.uniform(0.05, 0.2, n)
    a = truth + sa * rng.standard_normal(n)
    # b's errors as its σ say: 1 up to the median's sampling scatter; smaller than it says:
    # exactly 1 (never lowered)
    assert fusion.agreement_scale(a, sa, truth + sb * rng.standard_normal(n), sb) == \
        pytest.approx(1.0, abs=0.05)
    assert fusion.agreement_scale(a, sa, truth + 0.3 * sb * rng.standard_normal(n), sb) == 1.0
    # b's errors 3× its σ: k with σ_a² + k² σ_b² the variance of the difference, ≈ 3
    b = truth + 3 * sb * rng.standard_normal(n)
    assert fusion.agreement_scale(a, sa, b, sb) == pytest.approx(3.0, rel=0.08)
    # robust: 10 % wild rows barely move it; unusable rows are left out
    wild = b.copy()
    wild[: n // 10] += 50.0
    sb_bad = sb.copy()
    sb_bad[-5:] = np.nan
    assert fusion.agreement_scale(a, sa, wild, sb_bad) == pytest.approx(3.0, rel=0.25)
    assert fusion.agreement_scale(a[:5], sa[:5], b[:5], sb[:5]) == 1.0   # too few to tell


def test_local_agreement_scale_sees_an_estimate_wrong_on_part_of_the_view():
    """``b``'s errors 4× its σ on a fifth of the view (x < 24) and as its σ says elsewhere:
    the global scale spreads that over the whole view (k ≈ 1.5: too little there, too much
    elsewhere), the local one (``xy``) puts it where it is (≈ 4 there, ≈ 1 elsewhere), and
    its average is better in both parts; with as many neighbours as rows the local scale is
    the global one on every row."""
    rng = np.random.default_rng(5)
    xy = np.stack(np.meshgrid(np.arange(0, 120, 2.0), np.arange(0, 80, 2.0)), -1).reshape(-1, 2)
    n = len(xy)
    truth = rng.normal(0, 5, n)
    sa, sb = np.full(n, 0.1), np.full(n, 0.05)
    bad = xy[:, 0] < 24
    a = truth + sa * rng.standard_normal(n)
    b = truth + np.where(bad, 4.0, 1.0) * sb * rng.standard_normal(n)
    kg = fusion.agreement_scale(a, sa, b, sb)
    kl = fusion.agreement_scale(a, sa, b, sb, xy=xy)
    assert isinstance(kg, float) and 1.2 < kg < 2.0, kg
    assert kl.shape == (n,)
    inner = xy[:, 0] < 12                  # its 100 neighbours (~20 px wide) in the bad fifth
    far = xy[:, 0] > 50
    assert np.median(kl[inner]) > 3.0 and np.median(kl[far]) < 1.2, (
        np.median(kl[inner]), np.median(kl[far]))
    err = lambda k, m: np.sqrt(np.mean((fusion.inverse_variance(a, sa, b, k * sb)[0]  # noqa: E731
                                        - truth)[m] ** 2))
    assert err(kl, bad) < 0.8 * err(kg, bad), (err(kl, bad), err(kg, bad))
    assert err(kl, far) < 0.99 * err(kg, far), (err(kl, far), err(kg, far))
    assert np.allclose(fusion.agreement_scale(a, sa, b, sb, xy=xy, neighbours=n), kg,
                       rtol=1e-6)
    assert np.array_equal(fusion.agreement_scale(a[:5], sa[:5], b[:5], sb[:5], xy=xy[:5]),
                          np.ones(5))


def test_held_out_error_ranks_estimates_counting_the_noise_they_share_with_it():
    """A subset-like estimate ``a`` (reference noise plus its own), a better estimate ``b``
    (a fifth of the variance, sharing part of the reference noise) and their average, judged
    by a held-out estimate ``c = t + β (own − reference noise)``, which shares the reference
    noise with ``a``: without the covariance the comparison prefers ``a`` to the average
    (although the average's error is less than half of ``a``'s), with it the ranking is the
    true mean-square error's, up to one constant; a bad ``b`` still loses. Shape errors are
    refused, and too few usable rows give ``inf``."""
    rng = np.random.default_rng(4)
    n, beta = 20000, 2.0
    t = rng.normal(0, 5, n)
    ref, own, other = (0.1 * rng.standard_normal(n) for _ in range(3))
    a = t + own - ref                                 # σ_a² = 0.02, half of it reference
    b = t - 0.3 * ref + 0.01 * rng.standard_normal(n)  # σ_b² = 0.001, mostly reference
    avg = fusion.inverse_variance(a, np.full(n, 0.02 ** 0.5), b, np.full(n, 0.001 ** 0.5))[0]
    c = (t + beta * (other - ref) + 3.0)[:, None]     # an offset: compared after its median
    mse = [np.mean((x - t) ** 2) for x in (a, b, avg)]
    est = np.stack([a, b, avg])
    naive = fusion.held_out_error(est, c, np.zeros((3, n, 1)))
    assert naive[0] < naive[2], naive                 # the shared noise favours a
    wa = 0.001 / (0.02 + 0.001)                       # a's weight in the average
    cov_a, cov_b = beta * 0.01, beta * 0.3 * 0.01     # Cov(x − t, c − t) = β × its ref share
    shared = np.stack([np.full((n, 1), v) for v in (cov_a, cov_b, wa * cov_a + (1 - wa) * cov_b)])
    err = fusion.held_out_error(est, c, shared)
    assert np.argsort(err).tolist() == np.argsort(mse).tolist(), (err, mse)
    const = err - np.array(mse)                       # E(c − t)², the same for all three
    assert np.ptp(const) < 0.1 * np.mean(np.abs(const)), const
    bad = t + 0.3 * rng.standard_normal(n)            # worse than a, sharing nothing
    e2 = fusion.held_out_error(np.stack([a, bad]), c, shared[[0, 1]] * [[[1]], [[0]]])
    assert e2[0] < e2[1], e2
    with pytest.raises(SemlabError, match="shared of shape"):
        fusion.held_out_error(est, c, np.zeros((2, n, 1)))
    assert np.all(np.isinf(fusion.held_out_error(est[:, :5], c[:5], shared[:, :5])))