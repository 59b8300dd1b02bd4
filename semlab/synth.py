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

from .camera import image_center
from .errors import SemlabError
from .synth_block import (BOX_DIMS, GRID_FRACTIONS, _box_geometry, block_camera,  # noqa: F401
                          render_block)
from .synth_drift import (DRIFT_TRUTH_COLUMNS, _scan_offset, _stage_matrix,  # noqa: F401
                          drift_pixel_map, drifted_positions, stage_drift)
from .synth_texture import (NOISE_LEVELS, TEXTURES, _TEXTURE_PARAMS, Detector,  # noqa: F401
                            _make_texture, _slip_lines, as_detector, detect, to_uint16)

# Texture regimes and the detector (synth_texture), stage drift (synth_drift) and the
# calibration block (synth_block) live in their own modules; every name stays importable here.

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
