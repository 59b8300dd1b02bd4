"""Tests of semlab.strain on affine displacement fields with known strain."""

import numpy as np
import pytest

from semlab.errors import GeometryError, SemlabError
from semlab.strain import (gradient_from_field, gradient_from_triangles, gradient_local_lsq,
                           green_lagrange, max_shear, principal_strains, small_strain,
                           strain_history, surface_green_lagrange, triangle_areas)

G_TRUE = np.array([[0.012, -0.004], [0.007, -0.003]])


def _scatter(n=300, seed=0, size=100.0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, size, (n, 2))


def _affine_disp(X, G, t=(1.5, -2.0)):
    return X @ G.T + np.asarray(t)


def test_triangles_recover_uniform_gradient_exactly():
    X = _scatter()
    G, T = gradient_from_triangles(X, _affine_disp(X, G_TRUE))
    assert G.shape == (len(T), 2, 2) and T.shape[1] == 3
    assert np.abs(G - G_TRUE).max() < 1e-10


def test_lsq_recovers_uniform_gradient_exactly():
    X = _scatter()
    G = gradient_local_lsq(X, _affine_disp(X, G_TRUE), gauge_length=30.0)
    ok = np.isfinite(G).all(axis=(1, 2))
    assert ok.mean() > 0.9
    assert np.abs(G[ok] - G_TRUE).max() < 1e-10


def test_field_gradient_exact_for_affine_field():
    yy, xx = np.mgrid[0:40, 0:50] * 0.5                  # spacing 0.5 µm
    ux = G_TRUE[0, 0] * xx + G_TRUE[0, 1] * yy
    uy = G_TRUE[1, 0] * xx + G_TRUE[1, 1] * yy
    G = gradient_from_field(ux, uy, 0.5)
    assert G.shape == (40, 50, 2, 2)
    assert np.abs(G - G_TRUE).max() < 1e-10


def test_field_gradient_window_exact_with_holes_and_borders():
    """The strain-window plane fit is exact for a linear field, near the borders and around
    missing (NaN) points, with anisotropic spacing."""
    yy, xx = np.mgrid[0:30, 0:40].astype(float)
    ux = G_TRUE[0, 0] * xx * 0.5 + G_TRUE[0, 1] * yy * 0.25 + 3.0
    uy = G_TRUE[1, 0] * xx * 0.5 + G_TRUE[1, 1] * yy * 0.25 - 1.0
    holes = np.random.default_rng(3).random(ux.shape) < 0.2
    ux[holes] = np.nan
    uy[5, 7] = np.nan
    G = gradient_from_field(ux, uy, (0.5, 0.25), window=5)
    ok = np.isfinite(G).all(axis=(-2, -1))
    assert ok.mean() > 0.95 and ok[0, 0] and ok[-1, -1]
    assert np.abs(G[ok] - G_TRUE).max() < 1e-9
    # a lone finite point (too few neighbours) gives NaN, not a number
    lone = np.full((9, 9), np.nan)
    lone[4, 4] = 1.0
    assert np.isnan(gradient_from_field(lone, lone, 1.0, window=3)).all()


def test_field_gradient_window_averages_noise():
    """With noise, a 7x7 window has far less scatter than central differences."""
    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[0:80, 0:80].astype(float)
    ux = 0.01 * xx + rng.normal(0, 0.05, xx.shape)
    uy = -0.005 * yy + rng.normal(0, 0.05, xx.shape)
    Gc = gradient_from_field(ux, uy, 1.0)
    Gw = gradient_from_field(ux, uy, 1.0, window=7)
    assert np.nanstd(Gw[..., 0, 0]) < 0.25 * np.nanstd(Gc[..., 0, 0])
    assert abs(np.nanmedian(Gw[..., 0, 0]) - 0.01) < 1e-3
    assert abs(np.nanmedian(Gw[..., 1, 1]) + 0.005) < 1e-3
    for bad in (4, 1, 2.5):
        with pytest.raises(SemlabError, match="window"):
            gradient_from_field(ux, uy, 1.0, window=bad)


def test_methods_within_2_percent_with_noise():
    rng = np.random.default_rng(1)
    Gbig = np.array([[0.02, 0.005], [-0.004, 0.015]])
    X = _scatter(2000, seed=2, size=1000.0)
    u = _affine_disp(X, Gbig) + rng.normal(0, 0.01, X.shape)     # 0.01 px noise
    E_true = small_strain(Gbig)
    G, T = gradient_from_triangles(X, u)
    w = triangle_areas(X, T)
    Gm = (G * w[:, None, None]).sum(0) / w.sum()
    Gl = np.nanmean(gradient_local_lsq(X, u, gauge_length=200.0), axis=0)
    for Ge in (Gm, Gl):
        E = small_strain(Ge)
        assert np.abs(E - E_true).max() < 0.02 * np.abs(E_true).max()
    # dense field with noise
    yy, xx = np.mgrid[0:200, 0:200].astype(float)
    ux = Gbig[0, 0] * xx + Gbig[0, 1] * yy + rng.normal(0, 0.01, xx.shape)
    uy = Gbig[1, 0] * xx + Gbig[1, 1] * yy + rng.normal(0, 0.01, xx.shape)
    Gf = gradient_from_field(ux, uy, 1.0).reshape(-1, 2, 2).mean(0)
    assert np.abs(small_strain(Gf) - E_true).max() < 0.02 * np.abs(E_true).max()


def test_rotation_has_zero_green_lagrange_but_small_strain_does_not():
    th = np.deg2rad(30.0)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    G = R - np.eye(2)
    assert np.abs(green_lagrange(G)).max() < 1e-12
    eps = small_strain(G)
    assert np.abs(eps[0, 0] - (np.cos(th) - 1)) < 1e-12 and abs(eps[0, 0]) > 0.1
    # the same from points via triangles
    X = _scatter()
    Gt, _ = gradient_from_triangles(X, X @ R.T - X)
    assert np.abs(green_lagrange(Gt)).max() < 1e-10


def test_pure_shear_principal_directions_at_45_degrees():
    g = 0.01
    E = small_strain(np.array([[0.0, g], [g, 0.0]]))
    e1, e2, ang = principal_strains(E)
    assert np.isclose(e1, g) and np.isclose(e2, -g) and np.isclose(ang, 45.0)
    assert np.isclose(max_shear(E), g)
    e1, e2, ang = principal_strains(small_strain(np.array([[0.0, -g], [-g, 0.0]])))
    assert np.isclose(ang, -45.0)
    # uniaxial along y
    e1, e2, ang = principal_strains(np.diag([0.0, 0.02]))
    assert np.isclose(e1, 0.02) and np.isclose(abs(ang), 90.0)


def test_surface_green_lagrange_adds_out_of_plane_term():
    G = np.zeros((2, 2))
    gz = np.array([0.1, 0.0])                             # surface tilted about y
    E = surface_green_lagrange(G, gz)
    # a line along x of length 1 becomes sqrt(1 + 0.1²): E_xx = ½(λ² - 1) = 0.005
    assert np.isclose(E[0, 0], 0.005) and np.isclose(E[1, 1], 0.0) and np.isclose(E[0, 1], 0.0)
    with pytest.raises(SemlabError):
        surface_green_lagrange(G, np.zeros(3))


def test_strain_history_follows_growing_uniform_strain():
    X = _scatter(200, seed=3, size=200.0)
    cycles = np.array([0, 1000, 2000, 4000])
    xy = np.stack([X + _affine_disp(X, G_TRUE * k / 3, t=(0, 0)) for k in range(4)])
    valid = np.ones(xy.shape[:2], bool)
    valid[2, :5] = False
    for method in ("triangles", "lsq"):
        h = strain_history(xy, cycles, valid=valid, method=method, gauge_length=60.0)
        # the reference is frame 0: deformation from 0 to k is F_k F_0^-1 = I + G k/3
        expect = np.array([green_lagrange(G_TRUE * k / 3)[0, 0] for k in range(4)])
        assert np.allclose(h["exx"], expect, atol=1e-10)
        assert h["n_points"][2] == 195 and h["n_points"][0] == 200
        assert np.array_equal(h["cycles"], cycles)


def test_errors():
    with pytest.raises(GeometryError):
        gradient_from_triangles(np.zeros((2, 2)), np.zeros((2, 2)))
    with pytest.raises(GeometryError):
        gradient_from_triangles(np.c_[np.arange(5.0), np.arange(5.0)], np.zeros((5, 2)))
    with pytest.raises(GeometryError):
        gradient_from_triangles(np.zeros((4, 2)), np.zeros((3, 2)))
    with pytest.raises(GeometryError):
        gradient_local_lsq(_scatter(), np.zeros((300, 2)), gauge_length=-1)
    with pytest.raises(SemlabError):
        gradient_from_field(np.zeros((3, 3)), np.zeros((3, 4)), 1.0)
    with pytest.raises(SemlabError):
        small_strain(np.zeros((3, 3)))
    with pytest.raises(SemlabError):
        strain_history(np.zeros((3, 5, 2)), [0, 1], method="triangles")
    with pytest.raises(SemlabError):
        strain_history(np.zeros((3, 5, 2)), [0, 1, 2], method="lsq")


def test_lsq_too_few_neighbours_gives_nan():
    X = _scatter(50, size=1000.0)
    G = gradient_local_lsq(X, np.zeros_like(X), gauge_length=1.0)
    assert np.isnan(G).all()
