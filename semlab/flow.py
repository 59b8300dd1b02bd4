"""Variational in-plane displacement map of one frame pair: the stereo map's model in 2-D.

The unknown is the displacement ``(u, v)(x, y)`` of every pixel of ``img0``: the material
point at ``(x, y)`` in ``img0`` is at ``(x + u, y + v)`` in ``img1``. It is the minimum of

    E(u, v) = Σ_p ρ_D(r_p(u, v) / (k σ_p)) + Σ_{p~q} [ρ_H((u_p − u_q) / s) + ρ_H((v_p − v_q) / s)]

with the terms of :mod:`semlab.variational` (the 1-D stereo parallax) carried over: ``r_p``
the difference of the locally normalised images (gain, offset and contrast changes between
the frames removed), ``σ_p`` its noise from the measured image noise, ``k`` rescaling it to
the residuals left, Huber functions ``ρ_D`` and ``ρ_H`` (an outlying residual, a slip band's
step of the displacement cost linearly: a step is not smoothed away), and the prior scale
``s`` **not a tuned constant**: the median data-only 1σ of a displacement component over a
``15 × 15`` window, ``1 / sqrt(Σ_window ½|∇I|² / σ²)``, from the measured noise.

Why a map and not a grid of subsets for the dense strain: a subset's displacement is
estimated from its own window only, and on the nearly featureless early frames of a fatigue
series a 21 px subset's error is 0.3 px RMS, which a strain window's plane fits turn into
~0.002–0.007 of strain; subsets across a slip band's step do not converge and leave holes.
The map pools each pixel's data with its neighbours' through the prior, as far as the
noise says it must (``benchmarks/dense_strain_bands.py``).

Minimisation: coarse to fine over ``levels`` halvings (a slip band's step of several pixels
that the initial guess from the tracks misses is beyond one linearisation at full
resolution; on the real FEI series the bottom band's 5 px step was missed without), at each
level several re-warps, the data term linearised about the current warp and both Huber
functions by iteratively reweighted least squares; each linear system (the 2 × 2 block data
precision plus a weighted Laplacian per component) solved by conjugate gradients
preconditioned by classical algebraic multigrid (``pyamg``).

Large frames: a solve holds ~1.7 kB per pixel at its peak, so levels larger than
``FlowParams.tile_px`` are solved in core tiles, one after another in this process. Only the
linear solves are tiled: the prior scale and, at each re-warp, the residuals' noise factor
are measured on the whole level, and each re-warp solves every tile's core and ``halo_px``
around it with the ring beyond held at the estimate the re-warp started from (the prior's
edges into it tie the tile to its neighbours), then pastes the cores. A tiled map is the
whole-frame map to a tenth of its 1σ (``tests/test_flow.py``); without the halo it is not.

Conventions: images ``[row, col]``, displacements in pixels, ``u`` along x (columns), ``v``
along y (rows).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from .errors import SemlabError
from .stats import robust_sd
from .variational import (VariationalParams, _check_image_pair, _diff, _diff_matrix, _diff_t,
                          _grad_x, _grad_y, _huber_w, normalise_local)

__all__ = ["FlowParams", "variational_flow"]


@dataclass(frozen=True)
class FlowParams:
    """Parameters of :func:`variational_flow` (recorded in the results).

    Attributes
    ----------
    levels : int
        Halvings of the coarse-to-fine pyramid (0: full resolution only).
    warps : int
        Re-warps (linearisations) per level.
    irls : int
        Reweightings (linear solves) per warp.
    norm_sigma_px : float
        Gaussian σ of the local mean / standard deviation normalisation (as
        :class:`semlab.variational.VariationalParams`).
    grad_sigma_px : float
        Gaussian σ of the smoothing of the images for their gradient.
    data_huber : float
        Residuals beyond this many noise σ have linear cost.
    smooth_huber : float
        Neighbour differences beyond this many prior scales have linear cost.
    prior_window_px : int
        The prior-scale rule's window (module docstring).
    cg_tol, cg_iter : float, int
        Relative residual and iteration cap of each linear solve.
    tile_px : int
        Levels larger than this along either side are solved in core tiles of this size
        (multiple of 16, >= 64): a solve holds ~1.7 kB per pixel at its peak (a 1024² frame
        peaked at 1.8 GB, 2026-12-07), so a 768² core with its halo ~1.4 GB.
    halo_px : int
        How far a tile's solve reaches beyond its core, pixels of the level: several of the
        prior's smoothing lengths (about ``prior_window_px``); the ring beyond it is held at
        the current estimate, and the re-warps pass the tiles' results to their neighbours.
    """

    # the model's terms as the stereo map's (semlab.variational), not set apart
    levels: int = 2
    warps: int = VariationalParams.warps
    irls: int = VariationalParams.irls
    norm_sigma_px: float = VariationalParams.norm_sigma_px
    grad_sigma_px: float = VariationalParams.grad_sigma_px
    data_huber: float = VariationalParams.data_huber
    smooth_huber: float = VariationalParams.smooth_huber
    prior_window_px: int = VariationalParams.prior_window_px
    cg_tol: float = 1e-4
    cg_iter: int = 400
    tile_px: int = 768
    halo_px: int = 64

    def as_dict(self):
        """The parameters as a plain dict (for the results' records)."""
        return asdict(self)


def _check(img0, img1, u0, v0, prm):
    a, b = _check_image_pair(img0, img1, ("img0", "img1"), 16, "the displacement map")
    u, v = np.asarray(u0, float), np.asarray(v0, float)
    if u.shape != a.shape or v.shape != a.shape:
        raise SemlabError(f"u0 and v0 must be (H, W) = {a.shape} initial displacements, got "
                          f"{u.shape} and {v.shape}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        raise SemlabError("u0 and v0 hold NaN/inf: give an initial displacement at every pixel "
                          "(e.g. interpolated from tracks, nearest value outside their hull)")
    if not (int(prm.levels) >= 0 and int(prm.warps) >= 1 and int(prm.irls) >= 1
            and prm.smooth_huber > 0 and prm.data_huber > 0 and int(prm.halo_px) >= 0):
        raise SemlabError(f"FlowParams: levels must be >= 0, warps and irls >= 1, the Huber "
                          f"thresholds > 0, halo_px >= 0, got {prm!r}")
    from .parallel import plan_tiles
    plan_tiles((1, 1), prm.tile_px)        # its own check: a multiple of 16, >= 64
    return a.astype(float), b.astype(float), u, v


def _solver(A, prm):
    """``b -> A⁻¹ b`` by conjugate gradients to ``prm.cg_tol``, preconditioned by one
    multigrid hierarchy of ``A`` (reused for every ``b``)."""
    import pyamg
    from pyamg.krylov import cg

    # classical (Ruge–Stüben) multigrid on the coupled system: the same answer as smoothed
    # aggregation to the tolerance, at a quarter of its time on a 192² pair (its set-up's
    # eigenvalue estimate and coarse solves dominated)
    M = pyamg.ruge_stuben_solver(A).aspreconditioner(cycle="V")

    def solve(b):
        x, _ = cg(A, b, tol=prm.cg_tol, maxiter=int(prm.cg_iter), M=M)
        return x
    return solve


def _noise_floor(img):
    """The smallest white-noise σ the data term takes for ``img``: the quantisation noise of
    integer grey levels (``1/√12`` of a level), or ``1e-3`` of its standard deviation for
    other values. A rendered frame can measure zero noise (the DIC Challenge rotation set:
    82 % black background), and a zero σ would give its pixels infinite weight."""
    a = np.asarray(img, float)
    if np.all(a == np.round(a)):
        return 1.0 / np.sqrt(12.0)
    return 1e-3 * float(np.std(a)) or 1e-12


def _level_noise(img, given, floor):
    """The noise σ of one pyramid level: ``given`` or measured, at least ``floor``."""
    from .noise import image_noise_sigma

    sigma = image_noise_sigma(img) if given is None else float(given)
    return max(float(sigma), floor)


class _Level:
    """One pyramid level: the normalised frames, their gradients and ``img1``'s splines,
    over the whole frame (a few arrays per pixel; the linear systems are built per box)."""

    def __init__(self, img0, img1, prm, noise):
        self.n0, self.s0 = normalise_local(img0, prm.norm_sigma_px, noise[0])
        n1, self.s1 = normalise_local(img1, prm.norm_sigma_px, noise[1])
        self.c1 = ndimage.spline_filter(n1, order=3, mode="mirror")
        g0 = ndimage.gaussian_filter(self.n0, prm.grad_sigma_px, mode="reflect")
        g1 = ndimage.gaussian_filter(n1, prm.grad_sigma_px, mode="reflect")
        self.gx0, self.gy0 = _grad_x(g0), _grad_y(g0)
        self.cgx1 = ndimage.spline_filter(_grad_x(g1), order=3, mode="mirror")
        self.cgy1 = ndimage.spline_filter(_grad_y(g1), order=3, mode="mirror")

    def view(self, box=None):
        """The level over ``box`` = (y0, y1, x0, x1) of ``img0``'s pixels (default all)."""
        return _View(self, box or (0, self.n0.shape[0], 0, self.n0.shape[1]))


class _View:
    """A box of a level: ``img0``'s arrays cut to it, ``img1`` read wherever the warp goes."""

    def __init__(self, lv, box):
        y0, y1, x0, x1 = box
        self.lv, self.box = lv, box
        self.n0 = lv.n0[y0:y1, x0:x1]
        self.s0 = lv.s0[y0:y1, x0:x1]
        self.gx0, self.gy0 = lv.gx0[y0:y1, x0:x1], lv.gy0[y0:y1, x0:x1]
        self.yy, self.xx = np.mgrid[y0:y1, x0:x1].astype(float)

    def warp(self, u, v):
        """Warped ``img1``, the Jacobians along x and y, the residual's noise σ, inside."""
        lv = self.lv
        h, w = lv.n0.shape
        c = [self.yy + v, self.xx + u]
        inside = (c[1] >= 0) & (c[1] <= w - 1) & (c[0] >= 0) & (c[0] <= h - 1)
        kw = dict(order=3, prefilter=False, mode="mirror")
        w1 = ndimage.map_coordinates(lv.c1, c, **kw)
        jx = 0.5 * (ndimage.map_coordinates(lv.cgx1, c, **kw) + self.gx0)
        jy = 0.5 * (ndimage.map_coordinates(lv.cgy1, c, **kw) + self.gy0)
        s1 = ndimage.map_coordinates(lv.s1, c, order=1, mode="nearest")
        return w1, jx, jy, np.sqrt(self.s0 ** 2 + s1 ** 2), inside


def _prior_scale(lv, u, v, window):
    """The prior scale rule: median data-only 1σ of a displacement component over a
    ``window²`` window (module docstring)."""
    _, jx, jy, sig, inside = lv.warp(u, v)
    info = ndimage.uniform_filter(np.where(inside, 0.5 * (jx ** 2 + jy ** 2) / sig ** 2, 0.0),
                                  window, mode="reflect") * window ** 2
    good = info[inside]
    return float(np.median(1.0 / np.sqrt(np.maximum(good, 1e-12)))) if good.size else 1.0


def _system(lv, u, v, u0, v0, s, k, prm):
    """The normal matrix at ``(u, v)`` with the data term linearised about the warp
    ``(u0, v0)``: ``(A, g, wd, jx, jy, prior, lap)`` with ``g`` the energy's gradient, ``wd``
    the data weights, ``prior`` the (x, y) difference weights of each component and ``lap``
    their weighted Laplacians."""
    from scipy import sparse

    w1, jx, jy, sig, inside = lv.warp(u0, v0)
    rl = w1 - lv.n0 + jx * (u - u0) + jy * (v - v0)    # residual linearised about the warp
    wd = np.where(inside, _huber_w(rl / (k * sig), prm.data_huber) / (k * sig) ** 2, 0.0)
    gh, gv = _diff_matrix(u.shape, 1), _diff_matrix(u.shape, 0)
    lap, prior = [], []
    for f in (u, v):
        wh = _huber_w(_diff(f, 1) / s, prm.smooth_huber) / s ** 2
        wv = _huber_w(_diff(f, 0) / s, prm.smooth_huber) / s ** 2
        prior.append((wh, wv))
        lap.append(gh.T @ sparse.diags(wh.ravel()) @ gh + gv.T @ sparse.diags(wv.ravel()) @ gv)
    dxy = sparse.diags((wd * jx * jy).ravel())
    A = sparse.bmat([[sparse.diags((wd * jx * jx).ravel()) + lap[0], dxy],
                     [dxy, sparse.diags((wd * jy * jy).ravel()) + lap[1]]]).tocsr()
    g = np.concatenate([(wd * jx * rl).ravel() + lap[0] @ u.ravel(),
                        (wd * jy * rl).ravel() + lap[1] @ v.ravel()])
    return A, g, wd, jx, jy, prior, lap


def _noise_factor(lv, u, v):
    """``k``: the robust SD of the normalised residuals left at the warp ``(u, v)``, at least
    0.25 (the data term's noise rescaled to them)."""
    w1, _, _, sig, inside = lv.warp(u, v)
    tin = ((w1 - lv.n0) / sig)[inside]
    return max(0.25, robust_sd(tin)) if tin.size else 1.0


def _boxes(shape, prm):
    """The level's solve boxes: ``(core, box, free)`` per core tile of ``prm.tile_px``
    (one box, the whole level, when it fits): ``box`` the core grown by ``prm.halo_px`` and
    one pinned ring, clipped to the frame, ``free`` its (h, w) mask of unknowns (the ring is
    held at the current estimate: the prior's edges into it tie the box to its
    surroundings)."""
    from .parallel import plan_tiles

    h, w = shape
    if max(h, w) <= int(prm.tile_px):
        return [((0, h, 0, w), (0, h, 0, w), None)]
    out = []
    r = int(prm.halo_px) + 1
    for t in plan_tiles(shape, int(prm.tile_px)):
        box = (max(0, t.y0 - r), min(h, t.y1 + r), max(0, t.x0 - r), min(w, t.x1 + r))
        free = np.ones((box[1] - box[0], box[3] - box[2]), bool)
        if box[0] > 0:
            free[0] = False
        if box[1] < h:
            free[-1] = False
        if box[2] > 0:
            free[:, 0] = False
        if box[3] < w:
            free[:, -1] = False
        out.append(((t.y0, t.y1, t.x0, t.x1), box, free))
    return out


def _box_solver(A, free, prm):
    """``rhs -> A⁻¹ rhs`` over a box's free unknowns (both components; ``free`` None: all),
    the held ring's entries 0: ``A`` restricted to them and solved by :func:`_solver`."""
    if free is None:
        return _solver(A, prm)
    idx = np.flatnonzero(np.concatenate([free.ravel(), free.ravel()]))
    solve = _solver(A[idx][:, idx], prm)

    def solve_free(rhs):
        x = np.zeros(A.shape[0])
        x[idx] = solve(rhs[idx])
        return x
    return solve_free


def _solve_box(view, u, v, free, s, k, prm):
    """IRLS of one box from ``(u, v)`` (the box's arrays), its ring held: ``(u, v)``."""
    n = u.size
    u0, v0 = u.copy(), v.copy()
    for _ in range(int(prm.irls)):
        A, g, *_ = _system(view, u, v, u0, v0, s, k, prm)
        step = _box_solver(A, free, prm)(-g)       # the normal equations for the step
        u = u + step[:n].reshape(u.shape)
        v = v + step[n:].reshape(u.shape)
    return u, v


def _cut(a, box):
    return a[box[0]:box[1], box[2]:box[3]]


def _refine(lv, u, v, prm, bar=None):
    """IRLS minimisation at one level from ``(u, v)``; returns them, ``s`` and ``k``.

    The prior scale and, at each re-warp, the noise factor are measured on the whole level;
    each re-warp's linear solves run box by box (:func:`_boxes`), every box started at and
    its ring held at the estimate the re-warp began with, and the boxes' cores pasted
    together: one box, the whole level, is the untiled minimisation."""
    whole = lv.view()
    s = _prior_scale(whole, u, v, int(prm.prior_window_px))
    k = 1.0
    boxes = _boxes(u.shape, prm)
    for _ in range(int(prm.warps)):
        k = _noise_factor(whole, u, v)
        nu, nv = u.copy(), v.copy()
        for core, box, free in boxes:
            bu, bv = _solve_box(lv.view(box), _cut(u, box).copy(), _cut(v, box).copy(), free,
                                s, k, prm)
            cy, cx = core[0] - box[0], core[2] - box[2]
            sl = (slice(cy, cy + core[1] - core[0]), slice(cx, cx + core[3] - core[2]))
            nu[core[0]:core[1], core[2]:core[3]] = bu[sl]
            nv[core[0]:core[1], core[2]:core[3]] = bv[sl]
            if bar is not None:
                bar.update()
        u, v = nu, nv
    return u, v, s, k


def _posterior_samples(lv, u, v, s, k, prm, n_samples, at, seed=0):
    """``n_samples`` draws ``x = A⁻¹ (Jᵀ wd^½ n₁ + Gᵀ W^½ n₂) ~ N(0, A⁻¹)`` of the
    displacement's posterior at the final linearisation, at the pixels ``at`` ((N, 2) integer
    (x, y)): an (n_samples, N, 2) array, pixels; and the prior's pull there, (N, 2).
    Posterior draws, not the noise part ``A⁻¹ D A⁻¹`` alone: with the pull, the noise part
    made the dense strain's 1σ short on a uniform strain (E_xy 54 % / 90 % within 1σ / 2σ,
    scratch 2026-12-07) and at bands; the posterior is conservative on the uniform strain
    (1.7–2.7× the scatter) and close at bands (:func:`semlab.strain.strain_from_tracks`)."""
    rng = np.random.default_rng(seed)
    out = np.empty((int(n_samples), len(at), 2))
    bias = np.empty((len(at), 2))
    for core, box, free in _boxes(u.shape, prm):
        mine = np.flatnonzero((at[:, 1] >= core[0]) & (at[:, 1] < core[1])
                              & (at[:, 0] >= core[2]) & (at[:, 0] < core[3]))
        if not len(mine):
            continue
        bu, bv = _cut(u, box), _cut(v, box)
        A, _, wd, jx, jy, prior, lap = _system(lv.view(box), bu, bv, bu, bv, s, k, prm)
        solve = _box_solver(A, free, prm)
        shape, n = bu.shape, bu.size
        ay, ax = at[mine, 1] - box[0], at[mine, 0] - box[2]

        def solved(rhs):
            # A⁻¹ rhs (the ring held) at the points
            x = solve(rhs)
            return np.stack([x[:n].reshape(shape)[ay, ax], x[n:].reshape(shape)[ay, ax]], -1)

        # the prior's pull on the estimate (its plug-in bias, −A⁻¹ L d̂): a step's rounding
        bias[mine] = -solved(np.concatenate([lap[0] @ bu.ravel(), lap[1] @ bv.ravel()]))
        for i in range(int(n_samples)):
            d = np.sqrt(wd) * rng.standard_normal(shape)
            b = [d * jx, d * jy]
            for c, (wh, wv) in enumerate(prior):
                b[c] = b[c] + _diff_t(np.sqrt(wh) * rng.standard_normal(wh.shape), 1, shape)
                b[c] = b[c] + _diff_t(np.sqrt(wv) * rng.standard_normal(wv.shape), 0, shape)
            out[i, mine] = solved(np.concatenate([b[0].ravel(), b[1].ravel()]))
    return out, bias


def variational_flow(img0, img1, u0, v0, params=None, noise_sigma=None, progress=False,
                     n_samples=0, sample_at=None):
    """Displacement of every pixel of ``img0`` into ``img1`` (module docstring).

    Parameters
    ----------
    img0, img1 : (H, W) arrays
        The two frames (grey values).
    u0, v0 : (H, W) arrays
        Initial displacement along x and y of every ``img0`` pixel, pixels, to about a
        pixel at the finest level's reach (``2**levels`` pixels with the pyramid), e.g.
        interpolated from tracks. Finite everywhere.
    params : FlowParams, optional
    noise_sigma : (2,) floats, optional
        White-noise σ of the two frames, grey units; default measured on each pyramid level
        (:func:`semlab.noise.image_noise_sigma`). Either way at least the quantisation noise
        of integer grey levels (:func:`_noise_floor`); the data term is rescaled to the
        residuals actually left in any case.
    progress : bool
        Show a progress bar over the levels.
    n_samples : int
        Draws of the displacement's posterior ``N(0, A⁻¹)`` at the last linearisation (``A``
        the normal matrix: data precision from the noise rescaled to the residuals, prior
        precision from the edge weights), for the error of what is computed from the map:
        ``info["samples_px"]``, (n_samples, N, 2) perturbations ``(δu, δv)`` at
        ``sample_at``. The prior's pull (its plug-in bias ``−A⁻¹ L (u, v)``, ``L`` the
        prior's weighted Laplacian: how the map rounds a slip band's step) is not in them:
        ``info["bias_px"]``, (N, 2), at the same pixels.
    sample_at : (N, 2) int array, optional
        Pixels ``(x, y)`` of ``img0`` where the draws are kept (needed with ``n_samples``).

    Returns
    -------
    u, v : (H, W) float arrays
        Displacement along x and y, pixels: ``img0[y, x]`` is at ``(x + u, y + v)`` in
        ``img1``.
    info : dict
        ``prior_scale_px`` and ``noise_factor`` of the finest level, ``levels`` (used),
        ``tiles`` (the finest level's solve tiles, 1: untiled; ``params.tile_px``),
        ``params``, and ``samples_px`` and ``bias_px`` with ``n_samples``.

    Raises
    ------
    ImageError
        Frames with NaN/inf pixels, of different shapes or too small.
    SemlabError
        Initial displacements of the wrong shape or not finite; impossible parameters.

    Examples
    --------
    A texture shifted by (0.4, -0.3) px, started from zero:

    >>> import numpy as np
    >>> from scipy import ndimage
    >>> rng = np.random.default_rng(0)
    >>> f0 = ndimage.gaussian_filter(rng.normal(size=(96, 96)), 1.5)
    >>> f1 = ndimage.shift(f0, (-0.3, 0.4), order=3, mode="nearest")
    >>> u, v, _ = variational_flow(f1, f0, np.zeros((96, 96)), np.zeros((96, 96)))
    >>> round(float(np.median(u[20:-20, 20:-20])), 2), round(float(np.median(v[20:-20, 20:-20])), 2)
    (-0.4, 0.3)
    """
    from skimage.transform import pyramid_reduce, resize
    from tqdm.auto import tqdm

    prm = params or FlowParams()
    a, b, u, v = _check(img0, img1, u0, v0, prm)
    if n_samples:
        at = np.asarray(sample_at if sample_at is not None else np.zeros((0, 2)), int)
        if sample_at is None or at.ndim != 2 or at.shape[1] != 2 or np.any(at < 0) or np.any(
                at[:, 0] >= a.shape[1]) or np.any(at[:, 1] >= a.shape[0]):
            raise SemlabError("n_samples needs sample_at, an (N, 2) array of integer (x, y) "
                              f"pixels inside the {a.shape[1]}×{a.shape[0]} frame")
    noise = (None, None) if noise_sigma is None else tuple(float(x) for x in noise_sigma)
    levels = int(prm.levels)
    while levels > 0 and min(a.shape) / 2 ** levels < 16:   # a level needs some pixels
        levels -= 1
    p0, p1 = [a], [b]
    for _ in range(levels):
        p0.append(pyramid_reduce(p0[-1], 2, preserve_range=True))
        p1.append(pyramid_reduce(p1[-1], 2, preserve_range=True))
    f = 2.0 ** levels
    u = resize(u, p0[-1].shape, order=1, anti_aliasing=levels > 0) / f
    v = resize(v, p0[-1].shape, order=1, anti_aliasing=levels > 0) / f
    s = k = np.nan
    floor = (_noise_floor(a), _noise_floor(b))
    bar = tqdm(total=sum(len(_boxes(p.shape, prm)) for p in p0) * int(prm.warps),
               desc="displacement map", unit="solve", disable=not progress)
    for lvl in range(levels, -1, -1):
        if lvl < levels:
            u = resize(u, p0[lvl].shape, order=1) * 2.0
            v = resize(v, p0[lvl].shape, order=1) * 2.0
        # each level's own noise (the reduction averages it down), floored: the floor of the
        # full frame scaled as the reduction scales white noise (about 2× per halving)
        lv = _Level(p0[lvl], p1[lvl], prm,
                    [_level_noise(im[lvl], noise[i], floor[i] / 2 ** lvl)
                     for i, im in enumerate((p0, p1))])
        u, v, s, k = _refine(lv, u, v, prm, bar)
    bar.close()
    info = {"prior_scale_px": float(s), "noise_factor": float(k), "levels": levels,
            "tiles": len(_boxes(a.shape, prm)), "params": prm.as_dict()}
    if n_samples:
        info["samples_px"], info["bias_px"] = _posterior_samples(lv, u, v, s, k, prm,
                                                                 n_samples, at)
    return u, v, info
