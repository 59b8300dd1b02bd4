"""Tests of semlab.strain on affine displacement fields with known strain."""

import numpy as np
import pytest

from semlab.errors import GeometryError, SemlabError
from semlab.strain import (dense_field_strain, fill_dense_holes, gradient_from_field, gradient_from_triangles, gradient_local_lsq,
                           green_lagrange, max_shear, mean_gradient_cov, principal_strains,
                           small_strain, strain_from_tracks, strain_history, strain_jacobian, strain_sigma,
                           surface_green_lagrange, triangle_areas, triangle_gradient_cov)

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


G_BIG = np.array([[0.05, -0.02], [0.03, -0.04]])   # large enough for the Green–Lagrange terms


def _components(E):
    return np.stack([E[..., 0, 0], E[..., 1, 1], E[..., 0, 1]], axis=-1)


def _monte_carlo(X, sigma, gauge, n_draws, weighted, seed=5):
    """Empirical std of (E_xx, E_yy, E_xy) over ``n_draws`` Gaussian displacement noise draws
    of the per-point (N, 2) ``sigma`` on the homogeneous field of ``G_BIG``."""
    rng = np.random.default_rng(seed)
    u0 = _affine_disp(X, G_BIG)
    E = []
    for _ in range(n_draws):
        u = u0 + rng.normal(size=X.shape) * sigma
        if weighted:
            G, _ = gradient_local_lsq(X, u, gauge, disp_sigma=sigma, weighted=True)
        else:
            G = gradient_local_lsq(X, u, gauge)
        E.append(_components(green_lagrange(G)))
    return np.std(E, axis=0)


@pytest.mark.parametrize("weighted", [False, True])
def test_lsq_strain_sigma_matches_monte_carlo(weighted):
    """Predicted 1σ of each strain component within 20 % of the std of 250 noise draws, with
    a different σ at every point and per component (heteroscedastic: a single mean σ would
    miss)."""
    X = _scatter(40, seed=6, size=60.0)
    rng = np.random.default_rng(7)
    sigma = rng.uniform(0.003, 0.03, X.shape)
    G0, C = gradient_local_lsq(X, _affine_disp(X, G_BIG), 30.0, disp_sigma=sigma,
                               weighted=weighted)
    assert C.shape == (40, 4, 4)
    pred = strain_sigma(G0, C)
    emp = _monte_carlo(X, sigma, 30.0, 250, weighted)
    ok = np.isfinite(pred).all(axis=1)
    assert ok.sum() >= 20 and np.array_equal(ok, np.isfinite(emp).all(axis=1))
    ratio = pred[ok] / emp[ok]
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    if weighted:  # the 1/σ² weights never do worse than the plain fit
        _, C_plain = gradient_local_lsq(X, _affine_disp(X, G_BIG), 30.0, disp_sigma=sigma)
        assert np.all(pred[ok] <= strain_sigma(G0, C_plain)[ok] * (1 + 1e-9))


def test_strain_jacobian_is_the_derivative_of_the_strain():
    """Analytic Jacobian = central finite differences, for both measures; the Green–Lagrange
    one is not the small-strain one at a 5 % gradient."""
    h = 1e-6
    for measure, fn in (("green_lagrange", green_lagrange), ("small", small_strain)):
        J = strain_jacobian(G_BIG, measure)
        num = np.zeros((3, 4))
        for k in range(4):
            d = np.zeros(4)
            d[k] = h
            num[:, k] = (_components(fn(G_BIG + d.reshape(2, 2)))
                         - _components(fn(G_BIG - d.reshape(2, 2)))) / (2 * h)
        assert np.abs(J - num).max() < 1e-8
    assert np.abs(strain_jacobian(G_BIG) - strain_jacobian(G_BIG, "small")).max() > 0.02
    with pytest.raises(SemlabError, match="measure"):
        strain_jacobian(G_BIG, "log")


def test_lsq_sigma_scales_linearly_and_keeps_the_gradient():
    X = _scatter(120, seed=8)
    u = _affine_disp(X, G_TRUE)
    sigma = np.random.default_rng(9).uniform(0.01, 0.05, len(X))
    G1, C1 = gradient_local_lsq(X, u, 30.0, disp_sigma=sigma)
    G3, C3 = gradient_local_lsq(X, u, 30.0, disp_sigma=3 * sigma)
    assert np.array_equal(G1, gradient_local_lsq(X, u, 30.0), equal_nan=True)
    assert np.array_equal(G1, G3, equal_nan=True)
    s1, s3 = strain_sigma(G1, C1), strain_sigma(G3, C3)
    ok = np.isfinite(s1)
    assert ok.any() and np.allclose(s3[ok], 3 * s1[ok], rtol=1e-12)
    # a scalar σ per point is the same σ on both components
    _, C2 = gradient_local_lsq(X, u, 30.0, disp_sigma=np.column_stack([sigma, sigma]))
    assert np.allclose(C1, C2, equal_nan=True)


def test_lsq_sigma_inf_points_are_left_out_and_nan_sigma_raises():
    X = _scatter(120, seed=8)
    u = _affine_disp(X, G_TRUE) + np.random.default_rng(10).normal(0, 0.01, X.shape)
    sigma = np.full(len(X), 0.01)
    bad = 17
    sigma[bad] = np.inf
    G, C = gradient_local_lsq(X, u, 30.0, disp_sigma=sigma)
    keep = np.arange(len(X)) != bad
    G_without, C_without = gradient_local_lsq(X[keep], u[keep], 30.0, disp_sigma=sigma[keep])
    assert np.isnan(G[bad]).all() and np.isnan(C[bad]).all()
    assert np.array_equal(G[keep], G_without, equal_nan=True)
    assert np.array_equal(C[keep], C_without, equal_nan=True)
    near = np.linalg.norm(X - X[bad], axis=1) < 15
    near[bad] = False
    fin = np.isfinite(G[near]).all(axis=(1, 2))      # the inf point is in their discs,
    assert fin.sum() >= 2                             # yet their σ stays finite
    assert np.isfinite(strain_sigma(G[near][fin], C[near][fin])).all()
    # a NaN displacement needs no σ; a NaN σ at a finite displacement is an error
    u_nan, s_nan = u.copy(), sigma.copy()
    u_nan[3], s_nan[3] = np.nan, np.nan
    G_nan, _ = gradient_local_lsq(X, u_nan, 30.0, disp_sigma=s_nan)
    assert np.isnan(G_nan[3]).all()
    s_nan[4] = np.nan
    with pytest.raises(GeometryError, match="NaN"):
        gradient_local_lsq(X, u_nan, 30.0, disp_sigma=s_nan)
    with pytest.raises(GeometryError, match=">= 0"):
        gradient_local_lsq(X, u, 30.0, disp_sigma=-sigma)
    with pytest.raises(GeometryError, match="shape"):
        gradient_local_lsq(X, u, 30.0, disp_sigma=sigma[:5])
    with pytest.raises(GeometryError, match="needs disp_sigma > 0"):
        gradient_local_lsq(X, u, 30.0, disp_sigma=np.zeros(len(X)), weighted=True)
    with pytest.raises(GeometryError, match="needs disp_sigma"):
        gradient_local_lsq(X, u, 30.0, weighted=True)


def test_strain_from_tracks_sigma_is_the_reference_frames_track_sigma():
    """E_lsq_sigma (M, 3) is the propagation of sigma_px[ref_frame] (µm), NaN without it;
    E_lsq does not change."""
    from scipy import ndimage

    rng = np.random.default_rng(1)
    f1 = ndimage.gaussian_filter(rng.normal(size=(96, 96)), 1.5)
    yy, xx = np.mgrid[0:96, 0:96].astype(float)
    f0 = ndimage.map_coordinates(f1, [yy, 48 + (xx - 48) * 1.01], order=3, mode="nearest")
    g = np.stack(np.meshgrid(np.arange(20.0, 80, 6), np.arange(20.0, 80, 6)), -1).reshape(-1, 2)
    xy = np.stack([np.column_stack([48 + (g[:, 0] - 48) / 1.01, g[:, 1]]), g])
    valid = np.ones(xy.shape[:2], bool)
    valid[0, 0] = False
    sig = np.stack([rng.uniform(0.01, 0.04, len(g)), np.zeros(len(g))])
    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=20.0)
    S = strain_from_tracks([f0, f1], xy, valid, sigma_px=sig, **kw)
    S0 = strain_from_tracks([f0, f1], xy, valid, **kw)
    assert S["E_lsq_sigma"].shape == (len(g) - 1, 3)
    assert np.isnan(S0["E_lsq_sigma"]).all()
    assert np.array_equal(S["E_lsq"], S0["E_lsq"], equal_nan=True)
    ok = valid[0]
    G, C = gradient_local_lsq(xy[0][ok] * 0.03, (xy[1][ok] - xy[0][ok]) * 0.03, 20.0 * 0.03,
                              disp_sigma=sig[0][ok] * 0.03)
    assert np.allclose(S["E_lsq_sigma"], strain_sigma(G, C), equal_nan=True)
    fin = np.isfinite(S["E_lsq_sigma"]).all(axis=1)
    assert fin.mean() > 0.8 and np.all(S["E_lsq_sigma"][fin] > 0)
    # the triangles' σ: the same propagation, per triangle
    assert S["E_tri_sigma"].shape == (len(S["tri"]), 3) and np.isnan(S0["E_tri_sigma"]).all()
    Ct = triangle_gradient_cov(xy[0][ok] * 0.03, S["tri"], sig[0][ok] * 0.03)
    Gt, _ = gradient_from_triangles(xy[0][ok] * 0.03, (xy[1][ok] - xy[0][ok]) * 0.03)
    assert np.allclose(S["E_tri_sigma"], strain_sigma(Gt, Ct))
    with pytest.raises(SemlabError, match="sigma_px"):
        strain_from_tracks([f0, f1], xy, valid, sigma_px=sig[:1], **kw)


def test_strain_history_sigma_matches_monte_carlo():
    """The 1σ of each frame's mean (triangles) strain within 20 % of the std of 300 noise
    draws; 0 in the reference frame; NaN for the lsq method and for a non-finite σ."""
    rng = np.random.default_rng(11)
    X = _scatter(60, seed=12)
    xy = np.stack([X + _affine_disp(X, G_BIG * k / 2, t=(0, 0)) for k in range(3)])
    sig = np.stack([rng.uniform(0.01, 0.05, 60), rng.uniform(0.005, 0.02, 60), np.zeros(60)])
    h0 = strain_history(xy, [0, 1, 2], ref_frame=2, sigma_px=sig)
    draws = []
    for _ in range(300):
        noisy = xy + rng.normal(size=xy.shape) * sig[:, :, None]
        h = strain_history(noisy, [0, 1, 2], ref_frame=2)
        draws.append([h["exx"], h["eyy"], h["exy"]])
    emp = np.std(draws, axis=0)                                   # (3 components, 3 frames)
    pred = np.array([h0["exx_sigma"], h0["eyy_sigma"], h0["exy_sigma"]])
    assert np.all(pred[:, 2] == 0)
    ratio = pred[:, :2] / emp[:, :2]
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    # the direct covariance of the mean gradient, as used there
    G, T = gradient_from_triangles(xy[2], xy[0] - xy[2])
    w = triangle_areas(xy[2], T)
    C = mean_gradient_cov(xy[2], T, w, sig[0])
    Gm = (G * w[:, None, None]).sum(axis=0) / w.sum()
    assert np.isclose(strain_sigma(Gm, C)[0], h0["exx_sigma"][0], rtol=1e-12)
    assert np.isnan(strain_history(xy, [0, 1, 2], ref_frame=2, method="lsq", gauge_length=40.0,
                                   sigma_px=sig)["exx_sigma"]).all()
    sig[0, 5] = np.inf
    h = strain_history(xy, [0, 1, 2], ref_frame=2, sigma_px=sig)
    assert np.isnan(h["exx_sigma"][0]) and np.isfinite(h["exx_sigma"][1])
    assert "exx_sigma" not in strain_history(xy, [0, 1, 2], ref_frame=2)
    with pytest.raises(SemlabError, match="sigma_px"):
        strain_history(xy, [0, 1, 2], sigma_px=sig[:2])


def test_triangle_gradient_sigma_matches_monte_carlo():
    """Each triangle's strain 1σ (exact gradient covariance from its three vertices, first
    order to Green–Lagrange) within 20 % of the std of 400 noise draws, with a different σ
    per point and component; a vertex with σ = inf makes its triangles' σ NaN."""
    X = _scatter(30, seed=8, size=60.0)
    rng = np.random.default_rng(9)
    sigma = rng.uniform(0.003, 0.03, X.shape)
    u0 = _affine_disp(X, G_BIG)
    G0, T = gradient_from_triangles(X, u0)
    C = triangle_gradient_cov(X, T, sigma)
    assert C.shape == (len(T), 4, 4)
    pred = strain_sigma(G0, C)
    E = []
    for _ in range(400):
        u = u0 + rng.normal(size=X.shape) * sigma
        G = np.stack([np.linalg.solve(np.stack([X[t[1]] - X[t[0]], X[t[2]] - X[t[0]]], 1).T,
                                      np.stack([u[t[1]] - u[t[0]], u[t[2]] - u[t[0]]])).T
                      for t in T])                                   # the same triangles
        E.append(_components(green_lagrange(G)))
    ratio = pred / np.std(E, axis=0)
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    sigma[T[0, 0]] = np.inf
    Cn = triangle_gradient_cov(X, T, sigma)
    bad = np.any(T == T[0, 0], axis=1)
    assert np.isnan(Cn[bad]).all() and np.isfinite(Cn[~bad]).all()


def _slip_step_series(amp_px, x0_px, width_px, n=160, seed=2):
    """Two frames of a 160 px texture, the last slipped along y by ``amp_px`` across a step
    at ``x0_px`` (a tanh of ``width_px``): ``(f0, f1, step, xx, xy, valid, rng)`` with
    ``step(x)`` the slip in px, ``xx`` the x pixel coordinates, tracks ``xy`` (2, N, 2) on a
    10 px grid with their true positions, all ``valid``, and the generator for more draws."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    f1 = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.5)
    yy, xx = np.mgrid[0:n, 0:n].astype(float)

    def step(x):
        return amp_px * 0.5 * (1 + np.tanh((x - x0_px) / width_px))

    f0 = ndimage.map_coordinates(f1, [yy + step(xx), xx], order=3, mode="nearest")
    g = np.stack(np.meshgrid(np.arange(16.0, n - 16, 10), np.arange(16.0, n - 16, 10)),
                 -1).reshape(-1, 2)
    xy = np.stack([np.column_stack([g[:, 0], g[:, 1] - step(g[:, 0])]), g])
    return f0, f1, step, xx, xy, np.ones(xy.shape[:2], bool), rng


def test_dense_strain_keeps_the_band_subsets():
    """A slip band whose new surface changes the last frame's look (ZNCC 0.4–0.95 there) but
    whose step the subsets still measure: the dense strain's mean is the one the same window
    gives from the true displacement; with the former ZNCC floor 0.95 the band's subsets are
    left out and a third of the band's shear is lost."""
    f0, f1, step, xx, xy, valid, _ = _slip_step_series(1.5, 80.0, 1.5)  # 1.5 px of slip
    band = np.exp(-((xx - 80) / 4.0) ** 2)
    f1 = f1 * (1 + 1.5 * band) + 0.3 * band      # the band brighter in the last frame only
    # without filling the holes (which would interpolate the floored subsets)
    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=30.0, dense_fill=False,
              dense_method="subsets")
    S = strain_from_tracks([f0, f1], xy, valid, **kw)
    S95 = strain_from_tracks([f0, f1], xy, valid, dense_min_zncc=0.95, **kw)
    GX, _ = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    ideal = gradient_from_field(np.zeros(GX.shape), step(GX) * 0.03, 16 * 0.03, window=7)
    want = np.nanmean(ideal[..., 1, 0])          # mean ∂u_y/∂x, 2 E_xy to first order
    assert (S["zncc"] < 0.95).sum() >= 9         # the band's column of subsets
    assert 2 * np.nanmean(S["E"][..., 0, 1]) == pytest.approx(want, rel=0.05)
    assert 2 * np.nanmean(S95["E"][..., 0, 1]) < 0.8 * want


def test_fill_dense_holes_keeps_a_steps_size():
    """A slip step across the grid at 35° with the grid points near it missing (subsets that
    did not converge there): the plane fits without them lose a third of the step's mean
    gradient; filled by interpolation they give the full grid's within 3 %. A point whose
    window holds too few measured points is not filled."""
    gx, gy = np.meshgrid(np.arange(30.0), np.arange(20.0))
    a = np.deg2rad(35.0)
    d = (gx - 15) * np.sin(a) - (gy - 10) * np.cos(a)    # signed distance to the step, points
    ux, uy = np.where(d > 0, 0.05, 0.0), np.where(d > 0, 0.1, 0.0)
    full = gradient_from_field(ux, uy, 1.0, window=7)
    at_step = np.abs(d) < 1.5
    holes = at_step | ((gx >= 26) & (gy <= 4) & (d > 3))  # and a corner with few neighbours
    ux_h, uy_h = np.where(holes, np.nan, ux), np.where(holes, np.nan, uy)
    fx, fy, filled = fill_dense_holes(ux_h, uy_h, window=7)
    inside = np.zeros(holes.shape, bool)
    inside[3:-3, 3:-3] = True                             # near the border: on the hull
    assert filled[at_step & inside].all() and not np.any(filled & ~holes)
    assert np.isnan(fy[0, 29]) and not filled[0, 29]      # its window: 6 − 1 measured points
    np.testing.assert_array_equal(fy[~holes], uy[~holes])
    inner = (slice(3, -3), slice(3, -3))
    want = full[inner].mean(axis=(0, 1))
    got = gradient_from_field(fx, fy, 1.0, window=7)[inner].mean(axis=(0, 1))
    np.testing.assert_allclose(got, want, rtol=0.03)
    left = np.nanmean(gradient_from_field(ux_h, uy_h, 1.0, window=7)[inner], axis=(0, 1))
    assert np.all(np.abs(left) < 0.8 * np.abs(want))
    F, E, fl = dense_field_strain(ux_h, uy_h, 1.0, window=7)
    assert np.array_equal(fl, filled) and np.isfinite(E[inner]).all()
    assert not dense_field_strain(ux_h, uy_h, 1.0, window=7, fill=False)[2].any()
    # measured points all on one row: nothing to interpolate between, nothing filled
    one = np.full(ux.shape, np.nan)
    one[10] = 0.0
    assert not fill_dense_holes(one, one, window=7)[2].any()


def test_dense_strain_matches_beside_a_band_with_smaller_subsets():
    """A slip step with a strip of new surface (an extrusion) in the last frame: the 21 px
    subsets that reach into the strip do not converge; the smaller ones beside it do, and
    with them the plane fits see the step (without filling the holes)."""
    from scipy import ndimage

    x0 = 83.0
    f0, f1, step, xx, xy, valid, rng = _slip_step_series(3.0, x0, 0.3)
    fresh = ndimage.gaussian_filter(rng.normal(size=f1.shape), 1.5)
    f1 = np.where(np.abs(xx - x0) <= 3, fresh, f1)
    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=30.0, dense_fill=False,
              dense_method="subsets")
    S = strain_from_tracks([f0, f1], xy, valid, **kw)
    S1 = strain_from_tracks([f0, f1], xy, valid, dense_half_windows=(10,), **kw)
    GX, _ = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    beside = np.abs(GX - x0) < 12                          # the two columns beside the step
    assert np.isfinite(S["uy_um"][beside]).sum() >= np.isfinite(S1["uy_um"][beside]).sum() + 4
    small = S["dense_half_px"] < 10
    assert small.any() and np.all(S["dense_half_px"][small & np.isfinite(S["uy_um"])] >= 5)
    err = np.abs(S["uy_um"] - step(GX) * 0.03)[small & np.isfinite(S["uy_um"])] / 0.03
    assert np.all(err < 1.2)                               # each on one side of the step
    ideal = gradient_from_field(np.zeros(GX.shape), step(GX) * 0.03, 16 * 0.03, window=7)
    want = np.nanmean(ideal[..., 1, 0])
    assert 2 * np.nanmean(S["E"][..., 0, 1]) == pytest.approx(want, rel=0.1)
    assert 2 * np.nanmean(S1["E"][..., 0, 1]) < 0.9 * want


def test_dense_strain_variational_map_beats_the_subsets_on_a_noisy_texture():
    """A slip step on a noisy texture (noise 30 % of the texture's contrast): the variational
    displacement map (the default) gives the shear of the step with less than half the RMS
    error of the grid of subsets at the same grid points and plane fits (each subset sees its
    own window only), and the same mean."""
    f0, f1, step, xx, xy, valid, rng = _slip_step_series(1.5, 80.0, 1.0)
    sd = f1.std()
    f0 = f0 + rng.normal(0, 0.3 * sd, f0.shape)
    f1 = f1 + rng.normal(0, 0.3 * sd, f1.shape)
    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=30.0)
    S = strain_from_tracks([f0, f1], xy, valid, **kw)
    Ss = strain_from_tracks([f0, f1], xy, valid, dense_method="subsets", **kw)
    assert S["dense_method"] == "variational" and Ss["dense_method"] == "subsets"
    GX, _ = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
    want = gradient_from_field(np.zeros(GX.shape), step(GX) * 0.03, 16 * 0.03, window=7)[..., 1, 0]
    rms = [np.sqrt(np.nanmean((2 * s["E"][..., 0, 1] - want) ** 2)) for s in (S, Ss)]
    assert rms[0] < 0.5 * rms[1], rms
    assert 2 * np.nanmean(S["E"][..., 0, 1]) == pytest.approx(np.nanmean(want), rel=0.05)
    assert not S["dense_filled"].any() and np.isfinite(S["uy_um"]).all()


def test_dense_strain_variational_map_keeps_band_steps():
    """The two band scenes of the subset tests (a band brighter in the last frame only; a
    3 px step with a strip of new surface): the map keeps each step's shear in the plane fits
    (within 2 %) and every grid point within 0.4 px of the true displacement."""
    from scipy import ndimage

    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=30.0)
    f0, f1, step, xx, xy, valid, _ = _slip_step_series(1.5, 80.0, 1.5)
    band = np.exp(-((xx - 80) / 4.0) ** 2)
    scenes = [(f0, f1 * (1 + 1.5 * band) + 0.3 * band, step, xy, valid)]
    f0, f1, step, xx, xy, valid, rng = _slip_step_series(3.0, 83.0, 0.3)
    fresh = ndimage.gaussian_filter(rng.normal(size=f1.shape), 1.5)
    scenes.append((f0, np.where(np.abs(xx - 83.0) <= 3, fresh, f1), step, xy, valid))
    for a, b, step, xy, valid in scenes:
        S = strain_from_tracks([a, b], xy, valid, **kw)
        GX, _ = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
        want = gradient_from_field(np.zeros(GX.shape), step(GX) * 0.03, 16 * 0.03, window=7)
        assert 2 * np.nanmean(S["E"][..., 0, 1]) == pytest.approx(np.nanmean(want[..., 1, 0]),
                                                                  rel=0.02)
        assert np.max(np.abs(S["uy_um"] / 0.03 - step(GX))) < 0.4


def test_dense_method_is_checked():
    f0, f1, _, _, xy, valid, _ = _slip_step_series(1.5, 80.0, 1.5)
    with pytest.raises(SemlabError, match="dense_method"):
        strain_from_tracks([f0, f1], xy, valid, pixel_size_um=0.03, ref_frame=0,
                           dense_method="dic")


def test_dense_strain_sigma_holds_at_a_noisy_step():
    """The variational map's dense strain 1σ (posterior draws plus the prior's pull, which
    rounds the step) against the same plane fits of the true displacement: at least 90 % of
    the grid points within 2σ on every component for two noise draws (without the pull term
    the step's shear E_xy is 86 % on the second)."""
    for seed in (2, 3):
        f0, f1, step, xx, xy, valid, rng = _slip_step_series(1.5, 80.0, 1.0, seed=seed)
        sd = f1.std()
        f0 = f0 + rng.normal(0, 0.3 * sd, f0.shape)
        f1 = f1 + rng.normal(0, 0.3 * sd, f1.shape)
        S = strain_from_tracks([f0, f1], xy, valid, pixel_size_um=0.03, ref_frame=0,
                               gauge_length_px=30.0)
        GX, _ = np.meshgrid(S["grid_x_px"], S["grid_y_px"])
        Et = dense_field_strain(np.zeros(GX.shape), step(GX) * 0.03, 16 * 0.03, fill=False)[1]
        for c, (i, j) in enumerate(((0, 0), (1, 1), (0, 1))):
            z = np.abs(S["E"][..., i, j] - Et[..., i, j]) / S["E_sigma"][..., c]
            assert np.isfinite(z).all() and (z < 2).mean() >= 0.9, (seed, c, (z < 2).mean())


def test_frames_larger_than_a_tile_get_the_tiled_map():
    """Frames larger than ``FlowParams.tile_px`` get the variational map solved in tiles (not
    the subset grid, as frames above 1.5 Mpx did before), the results say how many, and the
    dense strain is the untiled one within a tenth of its 1σ (the tiles' posterior draws:
    ``tests/test_flow.py``)."""
    from semlab.flow import FlowParams

    f0, f1, _, _, xy, valid, _ = _slip_step_series(1.5, 80.0, 1.5)
    kw = dict(pixel_size_um=0.03, ref_frame=0, gauge_length_px=30.0)
    S = strain_from_tracks([f0, f1], xy, valid, **kw)
    T = strain_from_tracks([f0, f1], xy, valid, dense_flow_params=FlowParams(tile_px=64), **kw)
    assert S["dense_flow_tiles"] == 1 and T["dense_flow_tiles"] == 9
    assert T["dense_method"] == "variational" and np.isfinite(T["E_sigma"]).all()
    for c, (i, j) in enumerate(((0, 0), (1, 1), (0, 1))):
        d = np.abs(T["E"][..., i, j] - S["E"][..., i, j]) / S["E_sigma"][..., c]
        assert d.max() < 0.1, (c, d.max())


def test_chained_flow_start_reaches_a_frame_beyond_one_maps_reach():
    """Frames moving 5 px a frame (and stretching 0.4 % a frame): the map from the last frame
    straight into frame 0 from a zero start is lost (15 px, beyond its pyramid's reach), the
    map started from the frame-by-frame chain finds the known displacement."""
    from scipy import ndimage

    from semlab.flow import variational_flow
    from semlab.strain import chained_flow_start

    rng = np.random.default_rng(4)
    h, w, n_frames = 80, 112, 4
    base = ndimage.gaussian_filter(rng.normal(size=(h + 80, w + 80)), 2.0)
    c = ((w - 1) / 2, (h - 1) / 2)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)

    def moved(k):  # displacement (x, y) of every last-frame pixel into frame k, and frame k
        n = n_frames - 1 - k
        t, e = (5.0 * n, -1.0 * n), 0.004 * n
        px, py = c[0] + (xx - c[0] - t[0]) / (1 + e), c[1] + (yy - c[1] - t[1]) / (1 + e)
        img = ndimage.map_coordinates(base, [py + 40, px + 40], order=3)
        return t[0] + e * (xx - c[0]), t[1] + e * (yy - c[1]), img + 0.01 * rng.normal(size=(h, w))

    frames = [moved(k)[2] for k in range(n_frames)]
    tu, tv, _ = moved(0)
    inner = (slice(20, -20), slice(30, -30))
    start = chained_flow_start(frames, 0)
    assert start.shape == (h, w, 2)
    u, v, _ = variational_flow(frames[-1], frames[0], start[..., 0], start[..., 1])
    assert np.abs(u - tu)[inner].max() < 0.15 and np.abs(v - tv)[inner].max() < 0.15
    u, v, _ = variational_flow(frames[-1], frames[0], np.zeros((h, w)), np.zeros((h, w)))
    assert np.abs(u - tu)[inner].max() > 2.0
    # the last frame's own start is none; a shape the map cannot take is refused
    assert np.array_equal(chained_flow_start(frames, n_frames - 1), np.zeros((h, w, 2)))
    xy = np.zeros((n_frames, 8, 2))
    with pytest.raises(SemlabError, match="dense_start_px must be a finite"):
        strain_from_tracks(frames, xy, np.zeros((n_frames, 8), bool), 0.03, 0,
                           dense_start_px=np.zeros((h, w)))
