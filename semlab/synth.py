"""Synthetic SEM experiments with ground truth.

A physically motivated generator that is exact under semlab's affine camera model
(:mod:`semlab.camera`). Everything is keyed by the *end-state* material coordinates
``(x, y)`` in µm, origin on the tilt axis at the image centre:

- **heights** ``z(x, y)`` (µm): slip-band extrusion/intrusion ribbons along a band direction
  (default 35° from the image x axis), amplitudes 0.05–0.3 µm growing toward high y (the
  reference paper's trend), crack-like grooves along some bands, a gentle plane trend;
- **texture** ``T(x, y)``: material-attached contrast, so features move with the material, in
  one of three regimes (:data:`TEXTURES`, ``make_scene(texture=...)``):

  - ``"speckle"``: Voronoi grains (±8 %), a fine band-limited texture (10 %, ~1.3 px
    correlation) and dense bright particles (one per 500 px²): nearly a DIC speckle pattern;
  - ``"polished"``: what a polished, fatigued nickel or steel surface looks like: weak grain
    contrast (±3 %), a faint polishing texture (6 %, ~1.5 px correlation), sparse particles
    (one per 6000 px²) and fine slip lines along the bands (8 % contrast, broken along their
    length). With the ``"realistic"`` detector at ±5° and 0.03 µm/px, the Cramér–Rao bound of
    a 21×21 translation subset on its flat parts is about 25 nm of height (11 nm on
    ``"speckle"``);
  - ``"featureless"``: no material texture at all; the slip bands' topographic contrast is the
    only signal;
- **displacement** ``U(x, y)`` (µm) from the earliest frame to the end state: slip mostly along
  y with steps across the bands, a small x component, plus an optional uniform strain. At frame
  ``n`` the material point ``x`` sits at ``x − (1 − f_n) U(x)`` and its height is ``g_n z(x)``
  with ``f_n`` and ``g_n`` growing from 0 to 1 with the cycles;
- **image formation** (secondary electrons): yield rising with the local incidence angle
  (secant law), edge brightening on convex edges, Gaussian beam blur, a per-frame
  brightness/contrast drift; early frames have weak contrast (nearly featureless). Noise is
  either additive Gaussian on a 16-bit image (the default, ``detector=None``) or the
  :class:`Detector` model: Poisson shot noise for a given dose (detected electrons per pixel),
  per-image gain/offset, optional scan-line jitter, 8-bit quantisation with saturation
  (:func:`detect`; presets :data:`NOISE_LEVELS` ``"low"`` and ``"realistic"``);
- **views**: end-state view at stage tilt θ samples, for each pixel ``(u, v)``, the material
  point solving ``u = cx + (x cosθ + z(x, y) sinθ)/s``, ``v = cy + y/s`` (fixed-point
  iteration; slopes ≪ cot θ so there is no occlusion);
- **calibration block**: a box seen by a perspective camera of known K and R (one image per
  stereo tilt), with a ``lines.json`` of its visible edges plus click noise.

:func:`make_experiment` writes a whole experiment folder and ``truth/``.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from .camera import image_center, project_perspective, rotation_about_axis
from .errors import SemlabError

# ---------------------------------------------------------------------------------------------
# The scene


@dataclass(frozen=True)
class Scene:
    """Random parameters of a synthetic surface (the state of one synthetic sample).

    All lengths in µm; coordinates are end-state material coordinates (x right, y down,
    origin at the image centre of view 0's tilt axis).
    """

    band_angle_deg: float
    band_offsets_um: np.ndarray      # (B,) signed distance of each band centre from the origin
    band_widths_um: np.ndarray       # (B,)
    band_amplitudes_um: np.ndarray   # (B,) signed: > 0 extrusion, < 0 intrusion
    band_slip_um: np.ndarray         # (B,) displacement step across each band (along y mostly)
    edge_um: float                   # softness of ribbon edges
    crack_offsets_um: np.ndarray     # (C,) grooves, distance from origin along the band normal
    crack_depth_um: np.ndarray       # (C,) > 0
    crack_width_um: float
    crack_extent_um: np.ndarray      # (C, 2) start/end along the band direction
    trend_um_per_um: tuple           # (a, b): plane z = a x + b y
    y_gain_per_um: float             # amplitude growth toward high y
    uniform_strain: tuple            # (exx, eyy, exy) small uniform strain (of U)
    slip_x_fraction: float
    extent_um: tuple                 # (xmin, xmax, ymin, ymax) of the texture raster
    texture_step_um: float
    texture: np.ndarray = field(repr=False)        # spline coefficients of T on the raster
    particles_um: np.ndarray = field(repr=False)   # (P, 2) particle centres
    pixel_size_um: float = 0.03
    texture_kind: str = "speckle"    # one of TEXTURES (or "particles")

    # -- geometry helpers ---------------------------------------------------------------------
    def _band_coords(self, x, y):
        a = np.deg2rad(self.band_angle_deg)
        along = x * np.cos(a) + y * np.sin(a)
        normal = -x * np.sin(a) + y * np.cos(a)
        return along, normal

    def height(self, x, y):
        """End-state height z (µm) at material points (x, y) (µm), arrays of any shape."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        along, n = self._band_coords(x, y)
        z = self.trend_um_per_um[0] * x + self.trend_um_per_um[1] * y
        gain = 1.0 + self.y_gain_per_um * y
        e = self.edge_um
        for c, w, amp in zip(self.band_offsets_um, self.band_widths_um, self.band_amplitudes_um):
            rib = 0.5 * (np.tanh((n - c + w / 2) / e) - np.tanh((n - c - w / 2) / e))
            z = z + amp * gain * rib
        for c, d, (a0, a1) in zip(self.crack_offsets_um, self.crack_depth_um, self.crack_extent_um):
            env = 0.5 * (np.tanh((along - a0) / 0.3) - np.tanh((along - a1) / 0.3))
            z = z - d * env * np.exp(-0.5 * ((n - c) / self.crack_width_um) ** 2)
        return z

    def displacement(self, x, y):
        """Total displacement (ux, uy) in µm from the earliest frame to the end state,
        as a function of end-state material coordinates (x, y) in µm."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        _, n = self._band_coords(x, y)
        exx, eyy, exy = self.uniform_strain
        ux = exx * x + exy * y
        uy = exy * x + eyy * y
        for c, b in zip(self.band_offsets_um, self.band_slip_um):
            step = 0.5 * (1 + np.tanh((n - c) / (2.5 * self.edge_um)))
            uy = uy + b * step
            ux = ux + self.slip_x_fraction * b * step
        return ux, uy

    def texture_at(self, x, y, contrast=1.0):
        """Material texture (relative SE yield factor, about 1) at (x, y) in µm.

        ``contrast`` scales the fine texture and particles (grain contrast stays), which is
        how the early, nearly featureless frames are made.
        """
        xmin, _, ymin, _ = self.extent_um
        cols = (np.asarray(x, float) - xmin) / self.texture_step_um
        rows = (np.asarray(y, float) - ymin) / self.texture_step_um
        coords = np.stack([rows.ravel(), cols.ravel()])
        fine = ndimage.map_coordinates(self.texture[0], coords, order=3, prefilter=False,
                                       mode="nearest").reshape(np.shape(x))
        grain = ndimage.map_coordinates(self.texture[1], coords, order=3, prefilter=False,
                                        mode="nearest").reshape(np.shape(x))
        return 1.0 + grain + contrast * fine


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


def make_scene(seed=0, size=(384, 512), pixel_size_um=0.03, band_angle_deg=35.0, n_bands=6,
               amplitude_um=(0.05, 0.3), n_cracks=1, slip_um=0.15, uniform_strain=(0.0, 0.0, 0.0),
               flat=False, texture="speckle"):
    """Draw the random parameters of a synthetic sample.

    Parameters
    ----------
    seed : int
    size : (H, W)
        Image size in pixels the scene is meant for (sets the field of view).
    pixel_size_um : float
    band_angle_deg : float
        Slip-band direction, degrees from the image x axis.
    n_bands : int
    amplitude_um : (min, max)
        Range of ribbon height magnitudes (µm).
    n_cracks : int
        Crack-like grooves along bands.
    slip_um : float
        Typical displacement step across a band from the earliest frame to the end (µm);
        0 for no slip.
    uniform_strain : (exx, eyy, exy)
        Uniform small strain of the displacement field (dimensionless).
    flat : bool
        No heights at all (z ≡ 0), for tests of the projection model.
    texture : {"speckle", "polished", "featureless", "particles"}
        Texture regime (:data:`TEXTURES`, described in the module docstring); ``"sem"`` is the
        old name of ``"speckle"``. ``"particles"`` gives isolated Gaussian particles on a
        uniform background (for centroid tests of the projection). The heights and the
        displacement field do not depend on it: one seed gives the same surface in every regime.
    """
    kind = "speckle" if texture == "sem" else texture
    if kind not in _TEXTURE_PARAMS:
        raise SemlabError(f"texture must be one of {TEXTURES} (or 'particles'), got {texture!r}")
    rng = np.random.default_rng(seed)
    h, w = size
    s = float(pixel_size_um)
    half_w, half_h = (w - 1) / 2 * s, (h - 1) / 2 * s
    diag = np.hypot(half_w, half_h)
    if flat:
        n_bands, n_cracks = 0, 0
    offsets = np.sort(rng.uniform(-0.8 * diag, 0.8 * diag, n_bands))
    widths = rng.uniform(0.25, 0.7, n_bands)
    signs = np.where(np.arange(n_bands) % 2 == 0, 1.0, -1.0)
    rng.shuffle(signs)
    amps = signs * rng.uniform(amplitude_um[0], amplitude_um[1], n_bands)
    slip = rng.uniform(0.3, 1.0, n_bands) * slip_um * rng.choice([-1.0, 1.0], n_bands)
    if n_cracks:
        pick = rng.choice(n_bands, size=min(n_cracks, n_bands), replace=False)
        crack_off = offsets[pick] + widths[pick] / 2
        crack_depth = rng.uniform(0.1, 0.2, len(pick))
        a0 = rng.uniform(-0.8 * diag, -0.2 * diag, len(pick))
        crack_ext = np.stack([a0, a0 + rng.uniform(0.6, 1.2, len(pick)) * diag], axis=1)
    else:
        crack_off = crack_depth = np.zeros(0)
        crack_ext = np.zeros((0, 2))
    margin = 1.5 + 4 * slip_um + 0.02 * diag
    extent = (-half_w - margin, half_w + margin, -half_h - margin, half_h + margin)
    step = s / 2.0
    bands = (float(band_angle_deg), offsets, widths)
    tex, particles = _make_texture(rng, extent, step, s, kind, bands)
    return Scene(
        band_angle_deg=float(band_angle_deg), band_offsets_um=offsets, band_widths_um=widths,
        band_amplitudes_um=amps, band_slip_um=slip, edge_um=0.1,
        crack_offsets_um=crack_off, crack_depth_um=crack_depth, crack_width_um=0.08,
        crack_extent_um=crack_ext,
        trend_um_per_um=(0.0 if flat else 0.004, 0.0 if flat else -0.003),
        y_gain_per_um=0.0 if flat else 0.6 / (2 * half_h),
        uniform_strain=tuple(float(v) for v in uniform_strain), slip_x_fraction=0.15,
        extent_um=extent, texture_step_um=step, texture=tex, particles_um=particles,
        pixel_size_um=s, texture_kind=kind)


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
# Image formation


def _solve_view(scene, shape, tilt_deg, pixel_size_um, center_px, height_scale=1.0,
                disp_fraction_left=0.0, n_iter=30, pixel_xy=None):
    """Material end-state coordinates (x, y) seen at every pixel of a view.

    Solves ``s (u − cx) = X cosθ + g z(x) sinθ``, ``s (v − cy) = Y`` where ``(X, Y) =
    (x, y) − r U(x, y)`` is the position at the frame (``r`` = ``disp_fraction_left``), by
    fixed-point iteration (a contraction while |∇z| tanθ ≪ 1 and |∇U| ≪ 1).
    """
    h, w = shape
    cx, cy = center_px
    t = np.deg2rad(tilt_deg)
    s = pixel_size_um
    vv, uu = np.mgrid[0:h, 0:w].astype(float) if pixel_xy is None else (pixel_xy[1], pixel_xy[0])
    a = s * (uu - cx)
    b = s * (vv - cy)
    x = a / np.cos(t)
    y = b.copy()
    for _ in range(n_iter):
        ux, uy = scene.displacement(x, y) if disp_fraction_left else (0.0, 0.0)
        z = height_scale * scene.height(x, y) if height_scale else 0.0
        x_new = (a - z * np.sin(t)) / np.cos(t) + disp_fraction_left * ux
        y_new = b + disp_fraction_left * uy
        delta = max(np.max(np.abs(x_new - x)), np.max(np.abs(y_new - y)))
        x, y = x_new, y_new
        if delta < 1e-10:
            break
    return x, y


def _se_yield(scene, x, y, tilt_deg, height_scale, h_um=1e-3):
    """Secondary-electron yield factor from the local incidence angle, plus edge brightening."""
    if not height_scale:
        return np.full(np.shape(x), 1.0), np.zeros(np.shape(x))
    zx = (scene.height(x + h_um, y) - scene.height(x - h_um, y)) / (2 * h_um) * height_scale
    zy = (scene.height(x, y + h_um) - scene.height(x, y - h_um)) / (2 * h_um) * height_scale
    t = np.deg2rad(tilt_deg)
    # beam/detector direction in the material frame: d = (-sin t, 0, cos t)
    cos_inc = (zx * np.sin(t) + np.cos(t)) / np.sqrt(1 + zx ** 2 + zy ** 2)
    yld = 1.0 / np.clip(cos_inc, 0.25, None) * np.cos(t)  # flat surface -> 1 at any tilt
    z0 = scene.height(x, y)
    lap = (scene.height(x + h_um, y) + scene.height(x - h_um, y) + scene.height(x, y + h_um)
           + scene.height(x, y - h_um) - 4 * z0) / h_um ** 2 * height_scale
    edge = np.clip(-lap * 0.004, 0.0, 0.3)  # convex edges (negative Laplacian) brighten
    return yld, edge


def render(scene, shape, tilt_deg=0.0, center_px=None, height_scale=1.0, disp_fraction_left=0.0,
           contrast=1.0, blur_px=0.7, noise=0.01, gain=1.0, offset=0.0, shading=True, rng=None,
           drift=None):
    """Render one SEM image of the scene.

    Parameters
    ----------
    scene : Scene
    shape : (H, W)
    tilt_deg : float
        Stage tilt about the image y axis (0 = frontal).
    center_px : (cx, cy), optional
        Pixel position of the tilt axis; default the image centre.
    height_scale : float
        Multiplies z (``g_n`` for series frames; 1 for the end state).
    disp_fraction_left : float
        ``1 − f_n``: the fraction of the total displacement still to come at this frame
        (0 for the end state).
    contrast : float
        Scale of the fine texture and particles (low for early, nearly featureless frames).
    blur_px, noise : float
        Gaussian beam blur sigma (px) and additive noise sigma (relative to mean ~0.45).
    gain, offset : float
        Detector brightness/contrast drift.
    shading : bool
        Topographic contrast (incidence-angle yield and edge brightening); False renders the
        material texture alone (for geometry tests).
    drift : dict, optional
        Stage and scan drift of this image (one item of :func:`stage_drift`): the image is
        rendered in the drifted pixel geometry (see :func:`drift_pixel_map`).

    Returns
    -------
    image : (H, W) float array, about 0..1
    x_um, y_um : (H, W) arrays
        The end-state material coordinates seen at each pixel.
    """
    center_px = image_center(shape) if center_px is None else center_px
    s = scene.pixel_size_um
    pix = None if drift is None else drift_pixel_map(drift, shape)
    x, y = _solve_view(scene, shape, tilt_deg, s, center_px, height_scale, disp_fraction_left,
                       pixel_xy=pix)
    tex = scene.texture_at(x, y, contrast)
    yld, edge = _se_yield(scene, x, y, tilt_deg, height_scale if shading else 0.0)
    img = 0.45 * tex * yld + edge
    if blur_px:
        img = ndimage.gaussian_filter(img, blur_px)
    if noise:
        rng = np.random.default_rng() if rng is None else rng
        img = img + rng.normal(0, noise, img.shape)
    img = gain * img + offset
    return img, x, y


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


def project_points(scene, xy_um, tilt_deg, shape, center_px=None, height_scale=1.0):
    """Pixel positions of end-state material points in a view at ``tilt_deg`` (end state).

    Parameters
    ----------
    xy_um : (N, 2) array of end-state material (x, y) in µm.

    Returns
    -------
    (N, 2) array of (x, y) pixels.
    """
    center_px = image_center(shape) if center_px is None else center_px
    xy = np.asarray(xy_um, float)
    z = height_scale * scene.height(xy[:, 0], xy[:, 1])
    t = np.deg2rad(tilt_deg)
    s = scene.pixel_size_um
    return np.column_stack([center_px[0] + (xy[:, 0] * np.cos(t) + z * np.sin(t)) / s,
                            center_px[1] + xy[:, 1] / s])


def frame_positions(scene, xy_um, disp_fraction_left, shape, center_px=None):
    """Pixel positions, in a frontal series frame, of end-state material points.

    A point at end-state ``x`` is at ``x − (1 − f_n) U(x)`` in frame n
    (``disp_fraction_left`` = ``1 − f_n``).
    """
    center_px = image_center(shape) if center_px is None else center_px
    xy = np.asarray(xy_um, float)
    ux, uy = scene.displacement(xy[:, 0], xy[:, 1])
    s = scene.pixel_size_um
    return np.column_stack([center_px[0] + (xy[:, 0] - disp_fraction_left * ux) / s,
                            center_px[1] + (xy[:, 1] - disp_fraction_left * uy) / s])


# ---------------------------------------------------------------------------------------------
# Stage drift between frames and scan drift within a frame

#: Columns of ``truth/drift.csv``.
DRIFT_TRUTH_COLUMNS = ("frame", "dx_px", "dy_px", "rotation_deg", "scale", "scan_dx_px",
                       "scan_dy_px")


def stage_drift(n_frames, shift_px=0.0, rotation_deg=0.0, scale=0.0, scan_px=0.0, rng=None):
    """Random stage drift of each frame of a series, the last frame being the reference.

    Every frame but the last is placed independently (a stage moved and brought back): a
    shift of the image centre of length uniform in ``[0.5, 1] × shift_px`` in a random
    direction, a rotation about the centre uniform in ``±rotation_deg`` and a magnification
    ``1 + uniform(±scale)``. ``scan_px`` adds a slow drift while the frame is scanned: row
    ``v`` sees the sample shifted by ``(scan_dx, scan_dy) · (t + 0.3 t²) / 1.3`` with
    ``t = v / (H − 1)``, ``(scan_dx, scan_dy)`` uniform in ``±scan_px``. The last frame is
    neither drifted nor scan-drifted (truth positions there are the end-state pixels).

    Returns
    -------
    list of n_frames dicts with ``dx_px, dy_px, rotation_deg, scale, scan_dx_px, scan_dy_px``.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    out = []
    for n in range(n_frames):
        a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 1.0) * shift_px
        d = {"dx_px": r * np.cos(a), "dy_px": r * np.sin(a),
             "rotation_deg": rng.uniform(-1, 1) * rotation_deg, "scale": 1 + rng.uniform(-1, 1) * scale,
             "scan_dx_px": rng.uniform(-1, 1) * scan_px, "scan_dy_px": rng.uniform(-1, 1) * scan_px}
        if n == n_frames - 1:
            d = {k: (1.0 if k == "scale" else 0.0) for k in d}
        out.append({k: float(v) for k, v in d.items()})
    return out


def _stage_matrix(drift, shape):
    """(3, 3) map of undrifted pixels to drifted pixels (before the scan drift)."""
    h, w = shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    t = np.deg2rad(drift["rotation_deg"])
    A = drift["scale"] * np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    m = np.eye(3)
    m[:2, :2] = A
    m[:2, 2] = c + np.array([drift["dx_px"], drift["dy_px"]]) - A @ c
    return m


def _scan_offset(drift, v, h):
    t = np.asarray(v, float) / max(h - 1, 1)
    f = (t + 0.3 * t * t) / 1.3
    return drift["scan_dx_px"] * f, drift["scan_dy_px"] * f


def drift_pixel_map(drift, shape):
    """Undrifted pixel (x, y) seen at every pixel of a drifted image: (2, H, W) array.

    Pixel ``q`` of the drifted image, scanned at row ``q_y``, shows the undrifted position
    ``D⁻¹(q − s(q_y))`` with ``D`` the stage similarity and ``s`` the scan offset.
    """
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(float)
    sx, sy = _scan_offset(drift, vv, h)
    mi = np.linalg.inv(_stage_matrix(drift, shape))
    x, y = uu - sx, vv - sy
    return np.stack([mi[0, 0] * x + mi[0, 1] * y + mi[0, 2], mi[1, 0] * x + mi[1, 1] * y + mi[1, 2]])


def drifted_positions(drift, pts_px, shape):
    """Where undrifted pixel positions ``(N, 2)`` appear in the drifted image (inverse of
    :func:`drift_pixel_map`; the scan offset depends on the row reached, solved by
    fixed-point iteration)."""
    p = np.asarray(pts_px, float)
    m = _stage_matrix(drift, shape)
    q0 = p @ m[:2, :2].T + m[:2, 2]
    q = q0.copy()
    for _ in range(20):
        sx, sy = _scan_offset(drift, q[:, 1], shape[0])
        q = q0 + np.column_stack([sx, sy])
    return q


def strain_fields(scene, x_um, y_um, h_um=1e-3):
    """True deformation of the total displacement at end-state points.

    Returns a dict of arrays shaped like ``x_um``: ``ux_um, uy_um`` and, with respect to the
    earliest-frame (reference) configuration, the displacement gradient ``H = F − I``
    (``dux_dX, dux_dY, duy_dX, duy_dY``), the small strain ``exx, eyy, exy`` and the
    Green–Lagrange strain ``Exx, Eyy, Exy``.
    """
    ux, uy = scene.displacement(x_um, y_um)
    uxp, uyp = scene.displacement(x_um + h_um, y_um)
    uxm, uym = scene.displacement(x_um - h_um, y_um)
    g11 = (uxp - uxm) / (2 * h_um)
    g21 = (uyp - uym) / (2 * h_um)
    uxp, uyp = scene.displacement(x_um, y_um + h_um)
    uxm, uym = scene.displacement(x_um, y_um - h_um)
    g12 = (uxp - uxm) / (2 * h_um)
    g22 = (uyp - uym) / (2 * h_um)
    # X = x - U(x)  =>  dX/dx = I - G, F = dx/dX = (I - G)^-1
    a, b, c, d = 1 - g11, -g12, -g21, 1 - g22
    det = a * d - b * c
    f11, f12, f21, f22 = d / det, -b / det, -c / det, a / det
    h11, h12, h21, h22 = f11 - 1, f12, f21, f22 - 1
    return {
        "ux_um": ux, "uy_um": uy,
        "dux_dX": h11, "dux_dY": h12, "duy_dX": h21, "duy_dY": h22,
        "exx": h11, "eyy": h22, "exy": 0.5 * (h12 + h21),
        "Exx": 0.5 * (f11 * f11 + f21 * f21 - 1), "Eyy": 0.5 * (f12 * f12 + f22 * f22 - 1),
        "Exy": 0.5 * (f11 * f12 + f21 * f22),
    }


def to_uint16(img, lo=0.0, hi=1.2):
    """Quantise a relative image (about 0..1) to 16-bit counts."""
    return np.clip((img - lo) / (hi - lo) * 65535.0, 0, 65535).round().astype(np.uint16)


# ---------------------------------------------------------------------------------------------
# Calibration block (perspective camera, vanishing-point lines)

BOX_DIMS = (40.0, 30.0, 20.0)
#: Fractions of a face at which grid lines are ruled on the block.
GRID_FRACTIONS = tuple(np.linspace(0.1, 0.9, 9))


def block_camera(tilt_deg, shape, focal_px=None):
    """True K, R, t of the block view at stage tilt ``tilt_deg``.

    World frame: the box's edges along x, y, z (z up out of the stage). The base orientation
    looks at a corner so that three faces are visible; the stage tilt is a rotation about the
    camera's y axis applied after it.
    """
    h, w = shape
    # a short focal length (strong perspective) puts the vanishing points near the image, which
    # is what makes them measurable; the box fills most of the image
    focal_px = 1.37 * w if focal_px is None else focal_px
    K = np.array([[focal_px, 0, (w - 1) / 2 + 0.014 * w], [0, focal_px, (h - 1) / 2 + 0.045 * h],
                  [0, 0, 1.0]])
    r_base = (rotation_about_axis([1, 0, 0], np.deg2rad(-120.0))
              @ rotation_about_axis([0, 0, 1], np.deg2rad(35.0)))
    R = rotation_about_axis([0, 1, 0], np.deg2rad(tilt_deg)) @ r_base
    centre = np.array(BOX_DIMS) / 2
    t = np.array([0.0, 0.0, 92.0]) - R @ centre
    return K, R, t


def _box_geometry():
    lx, ly, lz = BOX_DIMS
    corners = np.array([[i * lx, j * ly, k * lz] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    edges = {"x": [], "y": [], "z": []}
    for a in range(8):
        for b in range(a + 1, 8):
            d = np.abs(corners[a] - corners[b])
            if np.count_nonzero(d) == 1:
                edges["xyz"[int(np.argmax(d))]].append((a, b))
    faces = []
    for axis in range(3):
        for val in (0, 1):
            idx = [i for i in range(8) if (corners[i][axis] > 0) == bool(val)]
            # order the 4 corners around the face
            other = [k for k in range(3) if k != axis]
            ring = sorted(idx, key=lambda i: np.arctan2(corners[i][other[1]] - BOX_DIMS[other[1]] / 2,
                                                        corners[i][other[0]] - BOX_DIMS[other[0]] / 2))
            normal = np.zeros(3)
            normal[axis] = 1 if val else -1
            faces.append((ring, normal))
    return corners, edges, faces


def render_block(tilt_deg, shape, line_noise_px=1.0, rng=None):
    """Render the calibration block and return its visible edges grouped by direction.

    Returns
    -------
    image : (H, W) uint8
    families : dict name -> (M, 4) array of noisy segments (x1, y1, x2, y2) in pixels
    K, R, t : true camera
    """
    import cv2

    rng = np.random.default_rng() if rng is None else rng
    K, R, t = block_camera(tilt_deg, shape)
    corners, edges, faces = _box_geometry()
    img_pts = project_perspective(corners, K, R, t)
    cam_centre = -R.T @ t
    visible_faces = []
    img = np.full(shape, 40, np.uint8)
    for ring, normal in faces:
        face_centre = corners[ring].mean(axis=0)
        if np.dot(normal, cam_centre - face_centre) > 0:
            visible_faces.append(set(ring))
            shade = int(110 + 120 * abs(normal @ np.array([0.3, 0.5, 0.8])))
            cv2.fillPoly(img, [np.round(img_pts[ring] * 16).astype(np.int32)], shade,
                         lineType=cv2.LINE_AA, shift=4)
    # visible edges, plus a grid ruled on the visible faces (as on a real calibration block):
    # every segment is the image of a 3D line along x, y or z
    segs3d = {name: [(corners[a], corners[b]) for a, b in pairs
                     if any(a in f and b in f for f in visible_faces)]
              for name, pairs in edges.items()}
    dims = np.array(BOX_DIMS)
    for ring, normal in faces:
        if set(ring) not in visible_faces:
            continue
        axis = int(np.argmax(np.abs(normal)))
        level = dims[axis] if normal[axis] > 0 else 0.0
        b_ax, c_ax = [k for k in range(3) if k != axis]
        for along, across in ((b_ax, c_ax), (c_ax, b_ax)):
            for frac in GRID_FRACTIONS:
                p = np.zeros(3)
                p[axis] = level
                p[across] = frac * dims[across]
                q = p.copy()
                q[along] = dims[along]
                segs3d["xyz"[along]].append((p, q))
    families = {}
    for name, lst in segs3d.items():
        out = []
        for p3, q3 in lst:
            p, q = project_perspective(np.array([p3, q3]), K, R, t)
            cv2.line(img, tuple(np.round(p * 16).astype(int)), tuple(np.round(q * 16).astype(int)),
                     255, 1, cv2.LINE_AA, shift=4)
            # clicked end points: a little inside the ends, with click noise
            p_in = p + 0.05 * (q - p)
            q_in = q - 0.05 * (q - p)
            out.append(np.concatenate([p_in, q_in]) + rng.normal(0, line_noise_px, 4))
        families[name] = np.array(out)
    return img, families, K, R, t


# ---------------------------------------------------------------------------------------------
# A whole experiment folder


def _series_schedule(n_frames, cycles_end=20000):
    cycles = np.round(np.linspace(0, cycles_end, n_frames)).astype(int)
    f = (cycles / cycles_end) ** 0.8 if n_frames > 1 else np.ones(1)
    g = f ** 1.5
    return cycles, f, g


def make_experiment(out_dir, seed=0, size=(384, 512), pixel_size_um=0.03, tilts_deg=(-5.0, 5.0),
                    n_frames=6, n_clicks=50, click_noise_px=0.5, line_noise_px=1.0,
                    slip_um=0.15, uniform_strain=(0.0, 0.0, 0.0), band_angle_deg=35.0,
                    noise=0.01, frame_noise=0.012, early_contrast=0.3, write_block=True,
                    block_size=(768, 1024), tilt_in_toml=True, tilt_in_metadata=True,
                    name=None, overwrite=False, progress=True, texture="speckle", detector=None,
                    scene=None, blur_px=0.7, shading=True, drift_shift_px=0.0,
                    drift_rotation_deg=0.0, drift_scale=0.0, scan_drift_px=0.0):
    """Write a complete synthetic experiment folder with ground truth.

    Parameters
    ----------
    out_dir : str or Path
        New folder (must not exist or be empty unless ``overwrite``).
    seed : int
    size : (H, W) pixels
    pixel_size_um : float
    tilts_deg : sequence of float
        Stage tilts of the end-state views (2 or more; empty for a series-only experiment).
    n_frames : int
        Frontal series frames, earliest first (0 for a stereo-only experiment).
    n_clicks : int
        Hand-click-like correspondences (true positions + ``click_noise_px`` Gaussian noise);
        0: no correspondences file (automatic matching only).
    line_noise_px : float
        Click noise of the block's line end points.
    block_size : (H, W)
        Size of the calibration-block images (a separate, larger image than the views).
    tilt_in_toml, tilt_in_metadata : bool
        Where the stage tilts are written (both False: tilts unknown, to be estimated).
    slip_um, uniform_strain, band_angle_deg
        See :func:`make_scene`.
    noise, frame_noise : float
        Image noise of the views and of the series frames (relative to mean ~0.45).
    early_contrast : float
        Texture contrast of frame 0 (it grows linearly with f_n to 1 at the end).
    texture : {"speckle", "polished", "featureless"}
        Texture regime of the scene (:data:`TEXTURES`).
    detector : Detector, "low", "realistic" or None
        None: additive Gaussian noise (``noise``, ``frame_noise``) and 16-bit images. Otherwise
        the secondary-electron model of :func:`detect` (shot noise for a dose, per-image
        gain/offset, optional scan-line jitter, 8-bit counts with saturation); ``noise`` and
        ``frame_noise`` are then unused.
    scene : Scene, optional
        Use this scene instead of drawing one (``seed`` still seeds the noise; ``texture``,
        ``slip_um``, ``uniform_strain``, ``band_angle_deg`` are then ignored). Used by
        :mod:`semlab.realtex` for real-image textures.
    blur_px, shading
        Passed to :func:`render` for every view and frame.
    drift_shift_px, drift_rotation_deg, drift_scale, scan_drift_px : float
        Stage drift of every series frame but the last (see :func:`stage_drift`): shift up
        to ``drift_shift_px``, rotation up to ``±drift_rotation_deg``, magnification change up
        to ``±drift_scale`` (0.003 = 0.3 %), and a slow scan drift up to ``scan_drift_px``
        over a frame. All 0 (default): no drift, and no ``truth/drift.csv``.

    Returns
    -------
    Path of the written ``experiment.toml``.

    Files written (``truth/``)
    -------------------------
    ``points.csv``: point_id, x_um, y_um, z_um (end state), v{i}_x_px, v{i}_y_px per view,
    f{n}_x_px, f{n}_y_px per frame (in the frame's own, drifted pixels), is_particle.
    ``drift.csv`` (with drift): per frame the stage drift (columns
    :data:`DRIFT_TRUTH_COLUMNS`; shift of the image centre, rotation about it, scale) and
    the scan drift reached at the last row.
    ``height_view0.npy``: (H, W) float32 z (µm) of the material seen at each view-0 pixel;
    ``view0_material.npz``: x_um, y_um, z_um maps for view 0.
    ``fields.npz``: on every other pixel of the last frame (1D ``x_px``, ``y_px`` give the grid),
    the true displacement from frame 0 to the end (ux_um, uy_um), the small strain
    (exx, eyy, exy) and Green–Lagrange strain (Exx, Eyy, Exy) with respect to frame 0 (see
    :func:`strain_fields`), end-state heights z_um, and
    the per-frame fractions ``f`` (displacement) and ``g`` (height), ``cycles``.
    ``block.json``: true K and, per view, R and t of the calibration block.
    ``scene.json``: the scene parameters.
    """
    from .io import write_tiff

    out = Path(out_dir)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise SemlabError(f"{out}: folder exists and is not empty; choose a new folder "
                          "(semlab never overwrites data) or pass overwrite=True")
    tilts = [float(t) for t in tilts_deg]
    if len(tilts) == 1:
        raise SemlabError("tilts_deg needs 2 or more stage tilts (or none for a series-only experiment)")
    if not tilts and n_frames < 1:
        raise SemlabError("nothing to make: give tilts_deg (2+) or n_frames (>= 1)")
    h, w = size
    rng = np.random.default_rng(seed + 1000)
    det = as_detector(detector)
    if scene is None:
        scene = make_scene(seed=seed, size=size, pixel_size_um=pixel_size_um,
                           band_angle_deg=band_angle_deg, slip_um=slip_um,
                           uniform_strain=uniform_strain, texture=texture)
    elif not np.isclose(scene.pixel_size_um, pixel_size_um):
        raise SemlabError(f"scene.pixel_size_um = {scene.pixel_size_um} differs from "
                          f"pixel_size_um = {pixel_size_um}; pass the scene's pixel size")

    def digitise(img):
        return to_uint16(img) if det is None else detect(img, det, rng)
    centre = image_center(size)
    s = pixel_size_um
    for sub in ("end_state", "series", "annotations", "calibration", "truth"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    from tqdm.auto import tqdm

    bar = tqdm(total=len(tilts) + n_frames, desc="rendering", disable=not progress)
    view_files = []
    for i, t in enumerate(tilts):
        img, x, y = render(scene, size, t, noise=0.0 if det else noise, rng=rng, blur_px=blur_px,
                           shading=shading)
        f = out / "end_state" / f"view_{i}.tif"
        write_tiff(f, digitise(img), pixel_size_um=s, tilt_deg=t if tilt_in_metadata else None,
                   overwrite=overwrite)
        view_files.append(f.relative_to(out).as_posix())
        if i == 0:
            z0 = scene.height(x, y)
            np.save(out / "truth" / "height_view0.npy", z0.astype(np.float32))
            np.savez_compressed(out / "truth" / "view0_material.npz", x_um=x.astype(np.float32),
                                y_um=y.astype(np.float32), z_um=z0.astype(np.float32))
        bar.update()

    cycles, f_frac, g_frac = _series_schedule(n_frames)
    drifts = stage_drift(n_frames, drift_shift_px, drift_rotation_deg, drift_scale, scan_drift_px,
                         np.random.default_rng(seed + 2000))
    drifted = any((drift_shift_px, drift_rotation_deg, drift_scale, scan_drift_px))
    frame_files = []
    for n in range(n_frames):
        contrast = early_contrast + (1 - early_contrast) * f_frac[n]
        gain = 1.0 + 0.08 * np.sin(1.7 * n + seed)
        offset = 0.04 * np.cos(2.3 * n + seed)
        img, _, _ = render(scene, size, 0.0, height_scale=g_frac[n],
                           disp_fraction_left=1.0 - f_frac[n], contrast=contrast,
                           noise=0.0 if det else frame_noise, gain=gain, offset=offset, rng=rng,
                           blur_px=blur_px, shading=shading, drift=drifts[n] if drifted else None)
        fpath = out / "series" / f"frame_{n:03d}.tif"
        write_tiff(fpath, digitise(img), pixel_size_um=s, tilt_deg=0.0, overwrite=overwrite)
        frame_files.append(fpath.relative_to(out).as_posix())
        bar.update()
    bar.close()

    # --- truth points: particles and a regular grid of material points --------------------
    hx, hy = (w - 1) / 2 * s, (h - 1) / 2 * s
    gx, gy = np.meshgrid(np.linspace(-0.9 * hx, 0.9 * hx, 24), np.linspace(-0.9 * hy, 0.9 * hy, 18))
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    parts = scene.particles_um
    inside = (np.abs(parts[:, 0]) < 0.92 * hx) & (np.abs(parts[:, 1]) < 0.92 * hy)
    parts = parts[inside]
    pts_um = np.vstack([parts, grid])
    is_particle = np.r_[np.ones(len(parts), bool), np.zeros(len(grid), bool)]
    z_true = scene.height(pts_um[:, 0], pts_um[:, 1])
    cols = {"point_id": np.arange(len(pts_um)), "x_um": pts_um[:, 0], "y_um": pts_um[:, 1],
            "z_um": z_true}
    view_px = [project_points(scene, pts_um, t, size) for t in tilts]
    for i, p in enumerate(view_px):
        cols[f"v{i}_x_px"], cols[f"v{i}_y_px"] = p[:, 0], p[:, 1]
    for n in range(n_frames):
        p = frame_positions(scene, pts_um, 1.0 - f_frac[n], size)
        p = drifted_positions(drifts[n], p, size) if drifted else p
        cols[f"f{n}_x_px"], cols[f"f{n}_y_px"] = p[:, 0], p[:, 1]
    cols["is_particle"] = is_particle.astype(int)
    _write_csv(out / "truth" / "points.csv", cols)
    if drifted:
        _write_csv(out / "truth" / "drift.csv",
                   {"frame": np.arange(n_frames),
                    **{k: np.array([d[k] for d in drifts]) for k in DRIFT_TRUTH_COLUMNS[1:]}})

    if n_frames:
        # every other pixel of the last frame (f = 1 there, so pixel position = end state)
        ys_px, xs_px = np.arange(0, h, 2, dtype=float), np.arange(0, w, 2, dtype=float)
        xe, ye = np.meshgrid((xs_px - centre[0]) * s, (ys_px - centre[1]) * s)
        fields = strain_fields(scene, xe, ye)
        keep = ("ux_um", "uy_um", "exx", "eyy", "exy", "Exx", "Eyy", "Exy")
        fields = {k: fields[k].astype(np.float32) for k in keep}
        np.savez_compressed(out / "truth" / "fields.npz", **fields, x_px=xs_px, y_px=ys_px,
                            z_um=scene.height(xe, ye).astype(np.float32), f=f_frac, g=g_frac,
                            cycles=cycles, pixel_size_um=s)

    # --- hand-click-like correspondences ----------------------------------------------------
    toml = {"name": name or f"synthetic fatigue sample (seed {seed})",
            "description": "made by semlab synth; ground truth in truth/"}
    stereo_lines = []
    if tilts:
        if n_clicks > 0:
            clicks = _choose_clicks(scene, parts, n_clicks, size, tilts, rng)
            ccols = {"point_id": np.arange(len(clicks["xy_um"]))}
            for i, t in enumerate(tilts):
                p = project_points(scene, clicks["xy_um"], t, size)
                p = p + rng.normal(0, click_noise_px, p.shape)
                ccols[f"x{i}_px"], ccols[f"y{i}_px"] = np.round(p[:, 0], 2), np.round(p[:, 1], 2)
            ccols["crack_id"] = clicks["crack_id"]
            _write_csv(out / "annotations" / "correspondences.csv", ccols,
                       blank_negative="crack_id")
        stereo_lines += ["[stereo]", f"views = {json.dumps(view_files)}",
                         *([f"tilt_deg = {json.dumps(tilts)}"] if tilt_in_toml else []),
                         'camera = "affine"',
                         *(['correspondences = "annotations/correspondences.csv"']
                           if n_clicks > 0 else [])]
        if write_block:
            views_json, block_truth = [], {"box_dims": list(BOX_DIMS), "views": []}
            for i, t in enumerate(tilts):
                img, fam, K, R, tt = render_block(t, block_size, line_noise_px, rng)
                import cv2

                bpath = out / "calibration" / f"block_{i}.png"
                cv2.imwrite(str(bpath), img)
                views_json.append({"view": i, "image": bpath.relative_to(out).as_posix(),
                                   "families": {k: np.round(v, 2).tolist() for k, v in fam.items()}})
                block_truth["K"] = K.tolist()
                block_truth["views"].append({"tilt_deg": t, "R": R.tolist(), "t": tt.tolist()})
            with open(out / "annotations" / "lines.json", "w") as fh:
                json.dump({"schema": "semlab-lines/1", "views": views_json}, fh, indent=1)
            with open(out / "truth" / "block.json", "w") as fh:
                json.dump(block_truth, fh, indent=1)
            stereo_lines.append('lines = "annotations/lines.json"')

    scene_info = {"seed": seed, "size": list(size), "pixel_size_um": s, "tilts_deg": tilts,
                  "band_angle_deg": scene.band_angle_deg,
                  "band_offsets_um": scene.band_offsets_um.tolist(),
                  "band_amplitudes_um": scene.band_amplitudes_um.tolist(),
                  "band_slip_um": scene.band_slip_um.tolist(),
                  "crack_offsets_um": scene.crack_offsets_um.tolist(),
                  "cycles": cycles.tolist(), "f": f_frac.tolist(), "g": g_frac.tolist(),
                  "click_noise_px": click_noise_px, "line_noise_px": line_noise_px,
                  "texture": scene.texture_kind,
                  "detector": None if det is None else dataclasses.asdict(det)}
    with open(out / "truth" / "scene.json", "w") as fh:
        json.dump(scene_info, fh, indent=1)

    lines = [f"name = {json.dumps(toml['name'])}", f"description = {json.dumps(toml['description'])}",
             "# pixel_size_um comes from the images' SEM metadata (Zeiss tag 34118)", ""]
    lines += stereo_lines
    if n_frames:
        lines += ["", "[series]", 'frames = "series/frame_*.tif"',
                  f"cycles = {json.dumps(cycles.tolist())}"]
    toml_path = out / "experiment.toml"
    toml_path.write_text("\n".join(lines) + "\n")
    return toml_path


def _choose_clicks(scene, parts, n_clicks, size, tilts, rng):
    """Material points a person would click: distinct particles, and points along a crack."""
    h, w = size
    s = scene.pixel_size_um
    hx, hy = (w - 1) / 2 * s, (h - 1) / 2 * s
    ok = (np.abs(parts[:, 0]) < hx - 25 * s) & (np.abs(parts[:, 1]) < hy - 25 * s)
    cand = parts[ok]
    # keep particles apart from each other
    order = rng.permutation(len(cand))
    chosen = []
    for i in order:
        if all(np.hypot(*(cand[i] - cand[j])) > 12 * s for j in chosen):
            chosen.append(i)
    n_crack = min(10, n_clicks // 5) if len(scene.crack_offsets_um) else 0
    cpts = np.zeros((0, 2))
    if n_crack:
        a = np.deg2rad(scene.band_angle_deg)
        along_dir = np.array([np.cos(a), np.sin(a)])
        normal = np.array([-np.sin(a), np.cos(a)])
        a0, a1 = scene.crack_extent_um[0]
        along = np.linspace(a0 + 0.4, a1 - 0.4, 200)
        line = (along[:, None] * along_dir + (scene.crack_offsets_um[0] + 2.5 * scene.crack_width_um)
                * normal)
        inside = (np.abs(line[:, 0]) < hx - 25 * s) & (np.abs(line[:, 1]) < hy - 25 * s)
        line = line[inside]
        if len(line) >= n_crack:
            cpts = line[np.linspace(0, len(line) - 1, n_crack).round().astype(int)]
    # particles make up the rest, so that n_clicks points are written whenever possible
    sel = cand[chosen[: n_clicks - len(cpts)]]
    # sparse-particle regimes: band edges make up the rest (speckle keeps its particle clicks
    # only, as it always did, so that its experiments are unchanged)
    n_edge = n_clicks - len(cpts) - len(sel) if scene.texture_kind in ("polished", "featureless") \
        else 0
    edge = _band_edge_points(scene, n_edge, hx - 25 * s, hy - 25 * s, 12 * s, rng) \
        if n_edge > 0 else np.zeros((0, 2))
    pts = [sel, edge, cpts]
    crack_id = [-1] * (len(sel) + len(edge)) + [1] * len(cpts)
    return {"xy_um": np.vstack(pts), "crack_id": np.array(crack_id)}


def _band_edge_points(scene, n, hx, hy, min_sep_um, rng):
    """Up to ``n`` points on band-ribbon edges inside ``|x| < hx, |y| < hy`` (µm): what a person
    clicks where the surface has too few particles (``polished``, ``featureless``)."""
    a = np.deg2rad(scene.band_angle_deg)
    along_dir = np.array([np.cos(a), np.sin(a)])
    normal = np.array([-np.sin(a), np.cos(a)])
    lines = [c + sgn * w / 2 for c, w in zip(scene.band_offsets_um, scene.band_widths_um)
             for sgn in (-1.0, 1.0)]
    if not lines:
        return np.zeros((0, 2))
    span = np.hypot(hx, hy)
    cand = np.vstack([np.linspace(-span, span, 400)[:, None] * along_dir + c * normal
                      for c in lines])
    cand = cand[(np.abs(cand[:, 0]) < hx) & (np.abs(cand[:, 1]) < hy)]
    chosen = []
    for i in rng.permutation(len(cand)):
        if all(np.hypot(*(cand[i] - cand[j])) > min_sep_um for j in chosen):
            chosen.append(i)
            if len(chosen) == n:
                break
    return cand[chosen]


def _write_csv(path, cols, blank_negative=None):
    keys = list(cols)
    n = len(cols[keys[0]])
    with open(path, "w") as fh:
        fh.write(",".join(keys) + "\n")
        for r in range(n):
            row = []
            for k in keys:
                v = cols[k][r]
                if blank_negative == k and v < 0:
                    row.append("")
                elif isinstance(v, (int, np.integer)):
                    row.append(str(int(v)))
                else:
                    row.append(repr(float(v)))
            fh.write(",".join(row) + "\n")


def read_truth_points(path):
    """Read ``truth/points.csv`` as a dict of 1D arrays (column name -> values)."""
    path = Path(path)
    if path.is_dir():
        path = path / "points.csv" if path.name == "truth" else path / "truth" / "points.csv"
    data = np.genfromtxt(path, delimiter=",", names=True)
    return {k: np.asarray(data[k]) for k in data.dtype.names}
