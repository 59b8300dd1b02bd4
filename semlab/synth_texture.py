"""Texture regimes and the detector model of the synthetic SEM images (:mod:`semlab.synth`).

- :data:`TEXTURES` and their parameters: the material-attached contrast ``T(x, y)`` of
  :func:`semlab.synth.make_scene` (``"speckle"``, ``"polished"``, ``"featureless"``, described
  in :mod:`semlab.synth`);
- :class:`Detector`, :data:`NOISE_LEVELS`, :func:`detect`: Poisson shot noise for a dose,
  per-image gain/offset, scan-line jitter, quantisation with saturation; :func:`to_uint16` for
  the default 16-bit image with additive noise.

All names are re-exported by :mod:`semlab.synth`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .errors import SemlabError

__all__ = ["TEXTURES", "Detector", "NOISE_LEVELS", "as_detector", "detect", "to_uint16"]

# ---------------------------------------------------------------------------------------------
# Texture regimes

#: Texture regimes of :func:`make_scene` (see the module docstring).
TEXTURES = ("speckle", "polished", "featureless")

#: Per-regime texture parameters: particle density (image px² per particle; None: no particles),
#: particle amplitude range, fine-texture amplitude and correlation length (image px), grain
#: contrast (±), mean grain area (µm²), slip-line contrast (0: none).
_TEXTURE_PARAMS = {
    "speckle": dict(px_per_particle=500, particle_amp=(0.5, 1.0), fine_amp=0.10, fine_corr_px=1.3,
                    grain_contrast=0.08, grain_area_um2=16.0, slip_line_amp=0.0),
    "particles": dict(px_per_particle=1500, particle_amp=(0.5, 1.0), fine_amp=0.0, fine_corr_px=1.3,
                      grain_contrast=0.0, grain_area_um2=16.0, slip_line_amp=0.0),
    "polished": dict(px_per_particle=6000, particle_amp=(0.3, 0.8), fine_amp=0.06,
                     fine_corr_px=1.5, grain_contrast=0.03, grain_area_um2=40.0,
                     slip_line_amp=0.08),
    "featureless": dict(px_per_particle=None, particle_amp=(0.0, 0.0), fine_amp=0.0,
                        fine_corr_px=1.3, grain_contrast=0.0, grain_area_um2=16.0,
                        slip_line_amp=0.0),
}


def _make_texture(rng, extent, step, s, kind, bands):
    """Spline coefficients of (fine texture + particles + slip lines, grain contrast) on a raster.

    ``bands`` = (angle_deg, offsets_um, widths_um) places the slip lines of ``"polished"``.
    The random draws of ``"speckle"`` are in the order of the original generator, so a seed
    gives the same images as before the regimes existed.
    """
    par = _TEXTURE_PARAMS[kind]
    xmin, xmax, ymin, ymax = extent
    nx = int(np.ceil((xmax - xmin) / step)) + 1
    ny = int(np.ceil((ymax - ymin) / step)) + 1
    area_px = (xmax - xmin) * (ymax - ymin) / s ** 2
    n_part = int(area_px / par["px_per_particle"]) if par["px_per_particle"] else 0
    particles = np.column_stack([rng.uniform(xmin + 1, xmax - 1, n_part),
                                 rng.uniform(ymin + 1, ymax - 1, n_part)])
    sig = rng.uniform(1.0, 1.8, n_part) * s / step  # raster px
    amp = rng.uniform(*par["particle_amp"], n_part)
    fine = np.zeros((ny, nx))
    if par["fine_amp"]:
        # band-limited surface texture: white noise smoothed to the correlation length
        fine = ndimage.gaussian_filter(rng.standard_normal((ny, nx)), par["fine_corr_px"] * s / step)
        fine *= par["fine_amp"] / fine.std()
    # particles, drawn analytically
    rr = np.arange(ny)
    cc = np.arange(nx)
    for (px, py), sg, a in zip(particles, sig, amp):
        c0, r0 = (px - xmin) / step, (py - ymin) / step
        r_lo, r_hi = int(max(r0 - 5 * sg, 0)), int(min(r0 + 5 * sg + 1, ny))
        c_lo, c_hi = int(max(c0 - 5 * sg, 0)), int(min(c0 + 5 * sg + 1, nx))
        gr = np.exp(-0.5 * ((rr[r_lo:r_hi] - r0) / sg) ** 2)
        gc = np.exp(-0.5 * ((cc[c_lo:c_hi] - c0) / sg) ** 2)
        fine[r_lo:r_hi, c_lo:c_hi] += a * np.outer(gr, gc)
    if par["grain_contrast"]:
        # Voronoi grains with soft boundaries
        from scipy.spatial import cKDTree

        n_grains = max(4, int((xmax - xmin) * (ymax - ymin) / par["grain_area_um2"]))
        seeds = np.column_stack([rng.uniform(xmin, xmax, n_grains), rng.uniform(ymin, ymax, n_grains)])
        level = rng.uniform(-par["grain_contrast"], par["grain_contrast"], n_grains)
        yy, xx = np.mgrid[0:ny, 0:nx]
        _, lab = cKDTree(seeds).query(np.column_stack([xmin + xx.ravel() * step,
                                                       ymin + yy.ravel() * step]))
        grain = ndimage.gaussian_filter(level[lab].reshape(ny, nx), 1.5)
    else:
        grain = np.zeros((ny, nx))
    if par["slip_line_amp"]:
        fine += _slip_lines(rng, extent, step, s, bands, par["slip_line_amp"], (ny, nx))
    coeffs = np.stack([ndimage.spline_filter(fine, order=3), ndimage.spline_filter(grain, order=3)])
    return coeffs, particles


def _slip_lines(rng, extent, step, s, bands, amp, shape):
    """Fine slip lines inside each band ribbon (raster of the texture).

    Lines run along the band direction, 3–8 px apart, about 1 px wide (Gaussian profile), each
    with a random signed contrast of up to ``amp`` and broken along its length (a smooth random
    envelope), so that they carry information along the band as well as across it.
    """
    angle_deg, offsets, widths = bands
    ny, nx = shape
    xmin, _, ymin, _ = extent
    a = np.deg2rad(angle_deg)
    yy, xx = np.mgrid[0:ny, 0:nx]
    x = xmin + xx * step
    y = ymin + yy * step
    along = x * np.cos(a) + y * np.sin(a)
    normal = -x * np.sin(a) + y * np.cos(a)
    out = np.zeros(shape)
    # smooth random envelope along the lines (correlation ~10 px), thresholded into segments
    env_noise = ndimage.gaussian_filter(rng.standard_normal(shape), 10 * s / step)
    env_noise /= env_noise.std() + 1e-12
    for c, w in zip(offsets, widths):
        n_lines = max(2, int(w / (5.5 * s)))
        pos = c + np.sort(rng.uniform(-w / 2, w / 2, n_lines))
        for p in pos:
            sign_amp = amp * rng.uniform(0.4, 1.0) * rng.choice([-1.0, 1.0])
            phase = rng.uniform(0, 2 * np.pi)
            env = 0.5 * (1 + np.tanh(2.0 * (env_noise + np.sin(along / (6 * s) + phase) * 0.3)))
            out += sign_amp * env * np.exp(-0.5 * ((normal - p) / (0.5 * s)) ** 2)
    return out


# ---------------------------------------------------------------------------------------------
# Detection and digitisation


@dataclass(frozen=True)
class Detector:
    """Secondary-electron detection and digitisation of a rendered image (:func:`detect`).

    Attributes
    ----------
    dose_e_per_px : float
        Mean number of detected electrons per pixel for a relative signal of 1 (a flat
        surface renders at about 0.45). The shot noise is Poisson: a pixel of relative signal
        ``I`` has a relative standard deviation ``1/sqrt(dose · I)``.
    bits : int
        Digitiser depth (8: 0..255 counts); the image is written as uint8 (bits ≤ 8) or uint16.
    full_scale : float
        Relative signal at the top count; brighter pixels saturate there, negative ones at 0.
    gain_sd, offset_sd : float
        Per-image contrast/brightness setting: gain ``1 + N(0, gain_sd)`` and offset
        ``N(0, offset_sd)`` (relative signal), drawn for every image.
    jitter_px : float
        Scan-line jitter: every image row is shifted along x by ``N(0, jitter_px)`` pixels
        (before the noise). It moves features away from their truth positions: an error
        source, off by default.
    """

    dose_e_per_px: float = 1000.0
    bits: int = 8
    full_scale: float = 1.0
    gain_sd: float = 0.05
    offset_sd: float = 0.02
    jitter_px: float = 0.0

    def __post_init__(self):
        if not self.dose_e_per_px > 0:
            raise SemlabError(f"Detector dose_e_per_px must be > 0, got {self.dose_e_per_px!r}")
        if not 1 <= int(self.bits) <= 16:
            raise SemlabError(f"Detector bits must be 1..16, got {self.bits!r}")
        if not self.full_scale > 0:
            raise SemlabError(f"Detector full_scale must be > 0, got {self.full_scale!r}")
        if min(self.gain_sd, self.offset_sd, self.jitter_px) < 0:
            raise SemlabError("Detector gain_sd, offset_sd and jitter_px must be >= 0")


#: Noise presets: ``"low"`` (a slow, high-dose scan: shot noise 0.5 % of a flat surface's
#: signal) and ``"realistic"`` (a typical photo-quality scan: 2.1 %, signal-to-noise ~21).
NOISE_LEVELS = {
    "low": Detector(dose_e_per_px=20000.0),
    "realistic": Detector(dose_e_per_px=1000.0),
}


def as_detector(detector):
    """A :class:`Detector` from a Detector, a :data:`NOISE_LEVELS` name, or None (None)."""
    if detector is None or isinstance(detector, Detector):
        return detector
    if isinstance(detector, str) and detector in NOISE_LEVELS:
        return NOISE_LEVELS[detector]
    raise SemlabError(f"detector must be a synth.Detector, one of {tuple(NOISE_LEVELS)} or None, "
                      f"got {detector!r}")


def detect(img, detector, rng=None, gain=None, offset=None):
    """Detect and digitise a noise-free relative image: jitter, shot noise, gain, 8-bit counts.

    Parameters
    ----------
    img : (H, W) float array
        Relative signal (about 0..1), e.g. from :func:`render` with ``noise=0``.
    detector : Detector or str
        The model, or a :data:`NOISE_LEVELS` name.
    rng : numpy Generator, optional
    gain, offset : float, optional
        This image's contrast and brightness; default drawn from the detector's spreads.

    Returns
    -------
    (H, W) uint8 array (``bits`` ≤ 8) or uint16 array of counts, saturated at 0 and
    ``2**bits − 1``.
    """
    det = as_detector(detector)
    rng = np.random.default_rng() if rng is None else rng
    img = np.asarray(img, float)
    if det.jitter_px:
        h, w = img.shape
        shift = rng.normal(0, det.jitter_px, h)
        vv, uu = np.mgrid[0:h, 0:w].astype(float)
        img = ndimage.map_coordinates(img, [vv, uu - shift[:, None]], order=3, mode="nearest")
    gain = 1.0 + rng.normal(0, det.gain_sd) if gain is None else gain
    offset = rng.normal(0, det.offset_sd) if offset is None else offset
    electrons = rng.poisson(det.dose_e_per_px * np.clip(img, 0, None))
    signal = gain * electrons / det.dose_e_per_px + offset
    top = 2 ** int(det.bits) - 1
    counts = np.clip(np.round(signal / det.full_scale * top), 0, top)
    return counts.astype(np.uint8 if det.bits <= 8 else np.uint16)


def to_uint16(img, lo=0.0, hi=1.2):
    """Quantise a relative image (about 0..1) to 16-bit counts."""
    return np.clip((img - lo) / (hi - lo) * 65535.0, 0, 65535).round().astype(np.uint16)
