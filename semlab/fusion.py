"""Per-pixel fusion of two dense height maps by their predicted 1σ.

The subset map (:func:`semlab.heightmap.dense_parallax`) and the variational map
(:func:`semlab.variational.variational_parallax`) are computed from the same two views, so
their errors are correlated and an inverse-variance average would understate the σ. The
fusion here is the *minimum-σ choice*: at each pixel keep the estimate with the smaller
predicted 1σ (a map's value where only it is measured), and keep that estimate's σ.

Measured on the 8 scenes of ``benchmarks/dense_map.py`` (README, "Min-σ fusion of the two
maps"), it does not beat the better of the two maps: the two σ do not rank their errors
(on speckle the variational σ is smaller on most pixels while its error is larger), so it is
not a run option.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .errors import SemlabError

__all__ = ["min_sigma_choice", "fuse_heightmaps"]


def min_sigma_choice(z_a, sigma_a, valid_a, z_b, sigma_b, valid_b):
    """Per-pixel choice of the estimate with the smaller predicted 1σ.

    Parameters
    ----------
    z_a, sigma_a : (h, w) arrays
        First map's heights and 1σ (any unit, the same for both maps).
    valid_a : (h, w) bool array
    z_b, sigma_b, valid_b : (h, w) arrays
        The second map, on the same pixel grid.

    Returns
    -------
    z, sigma : (h, w) float32 arrays
        The chosen heights and their 1σ, NaN where neither map is measured.
    valid : (h, w) bool array
        Measured by at least one map.
    pick_b : (h, w) bool array
        True where the second map was chosen.
    """
    arrs = [np.asarray(a) for a in (z_a, sigma_a, valid_a, z_b, sigma_b, valid_b)]
    if len({a.shape for a in arrs}) != 1:
        raise SemlabError("min_sigma_choice: the two maps must be on the same pixel grid "
                          f"(shapes {[a.shape for a in arrs]}); map them with the same roi")
    z_a, s_a, v_a, z_b, s_b, v_b = arrs
    v_a = v_a.astype(bool) & np.isfinite(z_a) & np.isfinite(s_a)
    v_b = v_b.astype(bool) & np.isfinite(z_b) & np.isfinite(s_b)
    with np.errstate(invalid="ignore"):
        pick_b = v_b & (~v_a | (s_b < s_a))
    valid = v_a | v_b
    z = np.where(pick_b, z_b, z_a)
    s = np.where(pick_b, s_b, s_a)
    z = np.where(valid, z, np.nan).astype(np.float32)
    s = np.where(valid, s, np.nan).astype(np.float32)
    return z, s, valid, pick_b


def fuse_heightmaps(subset, variational):
    """Min-σ fusion of a subset and a variational :class:`~semlab.heightmap.HeightMap`.

    Parameters
    ----------
    subset, variational : semlab.heightmap.HeightMap
        Maps of the same views over the same ``roi`` and height model (both from
        :func:`semlab.heightmap.heightmap_from_stereo` with the same stereo result).

    Returns
    -------
    HeightMap
        Heights and 1σ of the map with the smaller σ at each pixel; ``parallax`` is the
        subset map's, and a note gives the share of pixels taken from each map.
    """
    if tuple(subset.roi) != tuple(variational.roi):
        raise SemlabError(f"fuse_heightmaps: roi {subset.roi} != {variational.roi}; map both "
                          "with the same heightmap_roi")
    z, s, valid, pick_v = min_sigma_choice(subset.z_um, subset.sigma_um, subset.valid,
                                           variational.z_um, variational.sigma_um,
                                           variational.valid)
    n = max(int(valid.sum()), 1)
    note = (f"min-σ fusion (semlab.fusion): {100 * (valid & ~pick_v).sum() / n:.1f} % of the "
            f"measured pixels from the subset map, {100 * pick_v.sum() / n:.1f} % from the "
            "variational map")
    return replace(subset, z_um=z, sigma_um=s, valid=valid,
                   notes=list(subset.notes) + [note])
