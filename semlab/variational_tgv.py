"""A first+second-order (TGV-like) Huber prior for :mod:`semlab.variational`.

The first-difference prior of :func:`semlab.variational.refine_parallax` charges a slip-band
wall (a ramp of the parallax) the full rise at its top and bottom corners, so it pulls
narrow extrusions down and cuts the corners of the walls. Total generalised variation of
second order (Bredies, Kunisch & Pock 2010) measures the parallax against an auxiliary
slope field ``w = (wx, wy)``:

    R(d, w) = Σ ρ_H((∂x d − wx) / s) + ρ_H((∂y d − wy) / s) + Σ_{c ∈ x, y} ρ_H(∂c wx / s₂) + ρ_H(∂c wy / s₂)

so a piecewise-affine surface costs nothing inside its pieces (``w`` follows the slope),
a step still costs linearly (the first term, TV beyond ``s``) and a kink (the corner of a
wall) costs linearly in its change of slope (the second term). Here the gradient of ``w``
is the plain one of each component (not the symmetrised one of TGV proper: "TGV-like").
``s`` is the noise rule's scale of :mod:`semlab.variational`, ``s₂ = s / window`` (a
subset of ``window`` pixels resolves a slope change of about ``s / window``; the scale of
the second-order prior of ``prior_order=2``).

Each IRLS step solves the joint quadratic model in ``u = (d, wx, wy)`` exactly (sparse LU,
one factor per step; the same factor gives the posterior samples and the plug-in bias).

Conventions as :mod:`semlab.variational` (window arrays ``[row, col]``).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse

__all__ = ["tgv_operators", "initial_slopes", "tgv_step", "tgv_samples"]


def _d1(length):
    """Forward differences, ``(length − 1, length)``."""
    return sparse.diags([-np.ones(length - 1), np.ones(length - 1)], [0, 1],
                        shape=(length - 1, length))


def _avg(length):
    """Means of neighbour pairs, ``(length − 1, length)``."""
    return sparse.diags([np.full(length - 1, 0.5), np.full(length - 1, 0.5)], [0, 1],
                        shape=(length - 1, length))


def tgv_operators(shape):
    """Sparse operators of the prior on a C-ordered ``shape`` = (rows, cols) grid.

    Returns
    -------
    B1 : sparse matrix, ``(E, 3N)``
        First-order residuals ``(∂x d − P wx, ∂y d − P wy)`` on the horizontal then vertical
        neighbour pairs (``E`` of them; ``P`` the pair mean), for ``u = (d, wx, wy)``.
    B2 : sparse matrix, ``(2E, 3N)``
        Second-order residuals ``(∂x wx, ∂y wx, ∂x wy, ∂y wy)``.
    """
    n, m = shape
    In, Im = sparse.identity(n), sparse.identity(m)
    gx, gy = sparse.kron(In, _d1(m)), sparse.kron(_d1(n), Im)
    px, py = sparse.kron(In, _avg(m)), sparse.kron(_avg(n), Im)
    zx, zy = sparse.csr_matrix(gx.shape), sparse.csr_matrix(gy.shape)
    B1 = sparse.bmat([[gx, -px, zx], [gy, zy, -py]], format="csr")
    B2 = sparse.bmat([[zx, gx, zx], [zy, gy, zy], [zx, zx, gx], [zy, zy, gy]], format="csr")
    return B1, B2


def initial_slopes(d, sigma_px=2.0):
    """Slope field ``(wx, wy)`` of a parallax map: central differences of ``d`` smoothed
    by a Gaussian of ``sigma_px``; ``(2, rows, cols)``."""
    g = ndimage.gaussian_filter(np.asarray(d, float), sigma_px, mode="nearest")
    return np.stack([np.gradient(g, axis=1), np.gradient(g, axis=0)])


def _huber_w(t, c):
    a = np.abs(t)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


def _weights(u, ops, s, s2, c):
    B1, B2 = ops
    return (_huber_w((B1 @ u) / s, c) / s ** 2, _huber_w((B2 @ u) / s2, c) / s2 ** 2)


def _system(D, u, ops, s, s2, c):
    B1, B2 = ops
    w1, w2 = _weights(u, ops, s, s2, c)
    N = D.size
    dd = np.concatenate([D.ravel(), np.zeros(2 * N)]) + 1e-12
    P = B1.T @ sparse.diags(w1) @ B1 + B2.T @ sparse.diags(w2) @ B2
    A = (sparse.diags(dd) + P).tocsc()
    lu = sparse.linalg.splu(A, permc_spec="MMD_AT_PLUS_A", options=dict(SymmetricMode=True))
    return lu, P, (w1, w2)


def tgv_step(D, rhs, d, w, s, s2, c, ops=None):
    """One IRLS step of the data model ``Σ D (d − d_lin)²`` plus the prior.

    Parameters
    ----------
    D : (n, m) array
        Data precision per pixel (``w_data J²``).
    rhs : (n, m) array
        Data right-hand side (``D d_w − w_data J r₀``).
    d : (n, m) array
        Current parallax (for the Huber weights), pixels.
    w : (2, n, m) array
        Current slopes ``(wx, wy)``, pixels per pixel.
    s, s2 : float
        Prior scales of the first- and second-order residuals.
    c : float
        Huber threshold in scales.
    ops : tuple, optional
        ``tgv_operators(d.shape)`` (built when missing).

    Returns
    -------
    d, w : the minimiser of the reweighted quadratic model.
    """
    ops = ops or tgv_operators(d.shape)
    u = np.concatenate([np.ravel(d), np.ravel(w)])
    lu, _, _ = _system(D, u, ops, s, s2, c)
    N = D.size
    b = np.concatenate([np.ravel(rhs), np.zeros(2 * N)])
    x = lu.solve(b)
    return x[:N].reshape(D.shape), x[N:].reshape((2,) + D.shape)


def tgv_samples(D, d, w, s, s2, c, rng, n, prior=True, ops=None):
    """Perturbation samples of the parallax and its plug-in prior bias.

    ``x = A⁻¹ (D^½ n₁ + Bᵀ W^½ n₂)`` (``A`` the joint precision at ``(d, w)``) has the
    posterior covariance ``A⁻¹``; its ``d`` block is a sample of the parallax's posterior
    (the slopes marginalised). Without ``prior`` only the data noise (``A⁻¹ D A⁻¹``).

    Returns
    -------
    samples : list of ``n`` (rows, cols) arrays
    bias : (rows, cols) array
        ``A⁻¹ Bᵀ W B û`` on the ``d`` block: the prior's pull on the estimate.
    """
    ops = ops or tgv_operators(d.shape)
    B1, B2 = ops
    N = D.size
    u = np.concatenate([np.ravel(d), np.ravel(w)])
    lu, P, (w1, w2) = _system(D, u, ops, s, s2, c)
    out = []
    for _ in range(int(n)):
        b = np.concatenate([np.sqrt(D).ravel() * rng.standard_normal(N), np.zeros(2 * N)])
        if prior:
            b = b + B1.T @ (np.sqrt(w1) * rng.standard_normal(len(w1)))
            b = b + B2.T @ (np.sqrt(w2) * rng.standard_normal(len(w2)))
        out.append(lu.solve(b)[:N].reshape(D.shape))
    bias = lu.solve(P @ u)[:N].reshape(D.shape)
    return out, bias
