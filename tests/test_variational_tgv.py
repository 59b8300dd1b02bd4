"""The first+second-order (TGV-like) prior of semlab.variational_tgv: a ramp costs nothing."""

import numpy as np
import pytest

from semlab import variational as va, variational_tgv as tg
from semlab.errors import SemlabError


def _ramp(shape=(24, 32), a=0.15, b=-0.05, c=0.3):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    return a * xx + b * yy + c, np.stack([np.full(shape, a), np.full(shape, b)])


def test_an_affine_parallax_with_its_slopes_has_no_prior_residual():
    d, w = _ramp()
    B1, B2 = tg.tgv_operators(d.shape)
    u = np.concatenate([d.ravel(), w.ravel()])
    assert np.abs(B1 @ u).max() < 1e-12 and np.abs(B2 @ u).max() < 1e-12
    # a first-difference prior charges the same ramp its slope on every edge
    assert np.allclose(np.diff(d, axis=1), 0.15)


def test_step_returns_the_ramp_and_its_slope_where_tv_pulls():
    d_true, w_true = _ramp()
    D = np.ones(d_true.shape)
    s, s2, c = 0.02, 0.005, 0.1
    d, w = tg.tgv_step(D, D * d_true, np.zeros_like(d_true), np.zeros_like(w_true), s, s2, c)
    # a second step reweights at the first step's estimate: the exact ramp is its fixed point
    d, w = tg.tgv_step(D, D * d_true, d, w, s, s2, c)
    assert np.abs(d - d_true).max() < 1e-6 and np.abs(w - w_true)[:, 2:-2, 2:-2].max() < 1e-6
    # the first-difference prior of the same scale pulls the ends of the ramp in
    wh, wv = va._edge_weights(d_true, s, c)
    d_tv = va._linear_solver(D, wh, wv, va.VariationalParams(solver="direct"))(D * d_true)
    assert np.abs(d_tv - d_true).max() > 0.05


def test_unknown_prior_is_refused():
    v = np.random.default_rng(0).normal(size=(16, 16))
    with pytest.raises(SemlabError, match="prior"):
        va.refine_parallax(v, v, np.zeros((16, 16)), params=va.VariationalParams(prior="tv3"))
