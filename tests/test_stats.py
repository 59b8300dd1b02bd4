"""Tests of semlab.stats on samples from known distributions."""

import numpy as np
import pytest

from semlab.errors import SemlabError
from semlab.stats import bimodality, compare_distributions, correlation


def test_bimodality_detects_two_modes_and_their_parameters():
    rng = np.random.default_rng(0)
    v = np.r_[rng.normal(-2.0, 0.5, 600), rng.normal(3.0, 0.8, 400), [np.nan, np.nan]]
    r = bimodality(v)
    assert r["prefers_two"] and r["delta_bic"] > 10 and r["n_dropped"] == 2
    assert np.allclose(r["means"], [-2.0, 3.0], atol=0.15)
    assert np.allclose(r["sigmas"], [0.5, 0.8], atol=0.1)
    assert np.allclose(r["weights"], [0.6, 0.4], atol=0.05)


def test_bimodality_rejects_single_gaussian():
    v = np.random.default_rng(1).normal(5.0, 2.0, 1000)
    r = bimodality(v)
    assert not r["prefers_two"] and r["delta_bic"] < 10
    assert abs(r["mean_1"] - 5.0) < 0.2 and abs(r["sigma_1"] - 2.0) < 0.15


def test_compare_distributions():
    rng = np.random.default_rng(2)
    a, b, c = rng.normal(0, 1, 500), rng.normal(0, 1, 500), rng.normal(0.5, 1, 500)
    same, diff = compare_distributions(a, b), compare_distributions(a, c)
    assert same["p_value"] > 0.01 and diff["p_value"] < 1e-6
    assert diff["ks_statistic"] > same["ks_statistic"]
    assert abs(diff["median_b"] - 0.5) < 0.15


def test_correlation_known_coefficient_and_ci_coverage():
    rng = np.random.default_rng(3)
    rho = 0.6
    z = rng.multivariate_normal([0, 0], [[1, rho], [rho, 1]], size=400)
    x, y = z[:, 0].copy(), z[:, 1].copy()
    x[:3] = np.nan
    r = correlation(x, y, n_boot=500)
    assert r["n"] == 397 and r["n_dropped"] == 3
    lo, hi = r["pearson_ci"]
    assert lo < rho < hi and hi - lo < 0.2
    assert abs(r["pearson_r"] - rho) < 0.08 and r["pearson_p"] < 1e-10
    assert r["spearman_ci"][0] < r["spearman_rho"] < r["spearman_ci"][1]
    # independent variables: p not small, CI covers 0
    r0 = correlation(rng.normal(size=300), rng.normal(size=300), n_boot=300)
    assert r0["pearson_ci"][0] < 0 < r0["pearson_ci"][1] and r0["pearson_p"] > 0.01


def test_spearman_is_one_for_monotone_nonlinear():
    x = np.linspace(0, 3, 50)
    r = correlation(x, np.exp(3 * x), n_boot=200)
    assert np.isclose(r["spearman_rho"], 1.0) and r["pearson_r"] < 0.95


def test_errors():
    with pytest.raises(SemlabError):
        correlation([1, 2, np.nan], [1, 2, 3])
    with pytest.raises(SemlabError):
        correlation([1, 2, 3], [1, 2])
    with pytest.raises(SemlabError):
        correlation([1, 2, 3, 4], [1, 1, 1, 1])
    with pytest.raises(SemlabError):
        correlation([1, 2, 3, 4], [1, 2, 3, 5], ci=1.5)
    with pytest.raises(SemlabError):
        bimodality([1.0, 2.0, np.nan])
    with pytest.raises(SemlabError):
        bimodality(np.ones(50))
    with pytest.raises(SemlabError):
        compare_distributions([1.0], [1.0, 2.0])


def test_robust_sd_is_the_normal_sd_despite_outliers():
    from semlab.stats import robust_sd

    x = np.random.default_rng(3).normal(5.0, 0.7, 20000)
    assert abs(robust_sd(x) - 0.7) < 0.02
    assert abs(robust_sd(np.r_[x, np.full(400, 1e9)]) - 0.7) < 0.03     # 2 % gross outliers
    assert robust_sd(x - 5.0, about=0.0) == pytest.approx(robust_sd(x), rel=0.02)
    assert robust_sd([1.0, 1.0, 1.0]) == 0.0
