"""Real SEM textures carried by a known surface: synthetic truth on textures nobody here designed.

The DIC Challenge made its samples 14 and 15 this way: a real image is taken as the view at
one tilt, and the other views (and a frontal series) are rendered from it by a *known*
geometry, so the truth is exact while the texture is whatever the microscope saw.

Model
-----
The real image ``S`` (the *source*, e.g. the FEI BSE image of ``../shared/data/real_sem``
with its data bar dropped) is the material texture seen at stage tilt ``θs``
(``source_tilt_deg``): a material point ``(x, y)`` with end-state height ``z(x, y)`` carries
the source value at

    ``col = cs + (x cosθs + z sinθs) / step``,   ``row = rs + y / step``

where ``(cs, rs)`` is the source centre and ``step = source_px · s`` the material length of
one source pixel (``source_px = 0.5``: the source is sampled twice as finely as the views,
an upsampled grid). The heights, the displacement field and the projection of every view are
those of :mod:`semlab.synth` (a :class:`~semlab.synth.Scene` drawn from ``seed``: slip-band
ribbons, a crack, a plane trend, slip steps), so a view at tilt θ shows, at pixel ``(u, v)``,
the material point solving ``u = cx + (x cosθ + z sinθ)/s``, ``v = cy + y/s`` (the README's
affine camera) and the frame ``n`` of the series the point displaced by ``(1 − f_n) U``. The
view at ``θs`` is the source itself, rescaled by ``source_px``.

Rendering and its error
-----------------------
Inverse warping: every view pixel is mapped exactly to its source position (fixed-point
solution of the projection, residual < 1e-8 px) and the source is interpolated there by a
cubic B-spline. The source is first low-pass filtered by a Gaussian of
``antialias_px`` source pixels (default 1.0, i.e. a 0.5 view-pixel beam), which removes the
content above the views' Nyquist frequency and most of the source's own noise; what
remains is smooth on the source grid, where the cubic spline is accurate. Measured error of
the rendering itself (``tests/test_realtex.py``): a zero-height scene gives the pure
x-scaling of the source to < 1e-9 and isolated blobs land on the projections of their
material points within 1e-4 px; on a band-limited test pattern (periods ≥ 5 source px) with
relief the rendered values differ from the exact function by 0.15 % of its amplitude at most;
on the real textures the cubic and the quintic spline renderings differ by 0.08 % (FEI),
0.23 % (quartz) and 0.12 % (pollen) of the texture's standard deviation (RMS), far below the
detector noise. With relief, a blob lying across a curved band edge is not mapped affinely:
its centroid sits up to a few hundredths of a pixel (median 0.05 px at −5°/+8°) off the
projection of its centre, as it would in a real microscope. Topographic
contrast changes between views are not modelled (``shading=False``): the source already
holds the microscope's own contrast, and only the geometry and the noise differ between views.

Noise: the same :class:`semlab.synth.Detector` model as the synthetic regimes (Poisson shot
noise for a dose, per-image gain/offset, 8-bit counts), so every view, including the one at
``θs``, gets independent noise.

:func:`make_experiment` writes a complete experiment folder with ``truth/`` (the files of
:func:`semlab.synth.make_experiment`, plus ``truth/realtex.json``).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from . import synth
from .errors import SemlabError

__all__ = ["SOURCES", "RealTextureScene", "load_source", "make_real_scene", "source_position",
           "material_at_source", "make_experiment"]

#: Real SEM images under ``../shared/data/real_sem`` usable as textures.
SOURCES = {
    "fei": "fei_tiff/P33_scale2s3_detectorA.tif",   # FEI Nova NanoSEM BSE, data bar dropped
    "quartz": "quarz/Quarz_01.png",                  # quartz grain, first view of its series
    "pollen": "pollen_pot1/pot1_00.jpg",             # pollen grain on a grooved substrate
}


@dataclass(frozen=True)
class RealTextureScene(synth.Scene):
    """A :class:`semlab.synth.Scene` whose texture is a real image seen at ``source_tilt_deg``.

    Attributes (beyond the Scene's)
    -------------------------------
    source_coeffs : (Hs, Ws) array
        Cubic B-spline coefficients of the anti-aliased source, normalised to mean 1.
    source_tilt_deg : float
        Stage tilt at which the source shows the material.
    source_step_um : float
        Material length of one source pixel (µm).
    source_center_px : (col, row)
        Source pixel that shows the material origin (the views' tilt-axis centre).
    """

    source_coeffs: np.ndarray = field(default=None, repr=False)
    source_tilt_deg: float = 0.0
    source_step_um: float = 0.015
    source_center_px: tuple = (0.0, 0.0)

    def texture_at(self, x, y, contrast=1.0):
        """Source value (relative, mean about 1) carried by material points (x, y) in µm.

        ``contrast`` scales the deviation from the mean (1 keeps the real texture).
        """
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        cols, rows = source_position(self, x, y)
        hs, ws = self.source_coeffs.shape
        if (cols.min() < 0 or rows.min() < 0 or cols.max() > ws - 1 or rows.max() > hs - 1):
            raise SemlabError(
                f"the rendered field of view needs source pixels outside the {ws}x{hs} source "
                f"(cols {cols.min():.0f}..{cols.max():.0f}, rows {rows.min():.0f}..{rows.max():.0f});"
                " choose a smaller size, a smaller slip or a finer source_px")
        v = ndimage.map_coordinates(self.source_coeffs, [rows.ravel(), cols.ravel()], order=3,
                                    prefilter=False, mode="mirror").reshape(x.shape)
        return 1.0 + contrast * (v - 1.0)


def source_position(scene, x_um, y_um):
    """Source pixel (col, row) arrays that show the material points (x, y) (µm)."""
    t = np.deg2rad(scene.source_tilt_deg)
    z = scene.height(x_um, y_um)
    cs, rs = scene.source_center_px
    return (cs + (np.asarray(x_um) * np.cos(t) + z * np.sin(t)) / scene.source_step_um,
            rs + np.asarray(y_um) / scene.source_step_um)


def material_at_source(scene, cols, rows, n_iter=50):
    """End-state material points (N, 2) of (x, y) in µm shown at source pixels (cols, rows).

    Inverts :func:`source_position` (fixed-point iteration on the height term).
    """
    t = np.deg2rad(scene.source_tilt_deg)
    cs, rs = scene.source_center_px
    a = (np.asarray(cols, float) - cs) * scene.source_step_um
    y = (np.asarray(rows, float) - rs) * scene.source_step_um
    x = a / np.cos(t)
    for _ in range(n_iter):
        x = (a - scene.height(x, y) * np.sin(t)) / np.cos(t)
    return np.column_stack([x, y])


def load_source(source, data_root=None):
    """A real SEM image as a float array (data bar removed).

    Parameters
    ----------
    source : str, Path or (H, W) array
        A key of :data:`SOURCES` (looked up under ``data_root``), an image file, or an array.
    data_root : Path, optional
        Folder holding the ``real_sem`` images; default ``../shared/data/real_sem`` beside the
        package's repository.

    Returns
    -------
    (H, W) float64 array, indexed ``[row, col]``.
    """
    if isinstance(source, np.ndarray):
        img = np.asarray(source, float)
        if img.ndim != 2:
            raise SemlabError(f"source array must be 2D (H, W), got shape {img.shape}")
        return img
    from .io import read_image

    if isinstance(source, str) and source in SOURCES:
        root = (Path(__file__).resolve().parents[2] / "shared" / "data" / "real_sem"
                if data_root is None else Path(data_root))
        path = root / SOURCES[source]
        if not path.is_file():
            raise SemlabError(f"{path}: real texture {source!r} not found; pass data_root= (the "
                              "folder holding real_sem's images) or an image path")
    else:
        path = Path(source)
    return read_image(path).data


def make_real_scene(source, seed=0, size=None, pixel_size_um=0.03, source_tilt_deg=0.0,
                    source_px=0.5, antialias_px=1.0, margin_px=40, slip_um=0.15,
                    uniform_strain=(0.0, 0.0, 0.0), band_angle_deg=35.0, flat=False,
                    n_landmarks=400, data_root=None):
    """A scene with synth's heights and displacement and a real image's texture.

    Parameters
    ----------
    source : str, Path or (Hs, Ws) array
        See :func:`load_source`.
    seed : int
        Seeds the surface (heights, bands, slip), as :func:`semlab.synth.make_scene`.
    size : (H, W), optional
        View size in pixels; default the largest that fits the source with ``margin_px``,
        at most 384×512.
    pixel_size_um : float
    source_tilt_deg : float
        Stage tilt at which the source shows the material (that view is the source).
    source_px : float
        Size of one source pixel in view pixels (0.5: the source is twice as fine as the views).
    antialias_px : float
        Gaussian low-pass of the source, in source pixels, before interpolation (0: none).
    margin_px : int
        Source pixels kept free on every side for parallax and displacement.
    slip_um, uniform_strain, band_angle_deg, flat
        As :func:`semlab.synth.make_scene`.
    n_landmarks : int
        Distinct texture points (Shi–Tomasi corners of the view at ``source_tilt_deg``), stored
        as the scene's ``particles_um``: the points synth's clicks and truth use.

    Returns
    -------
    scene : RealTextureScene
    size : (H, W) the view size
    """
    img = load_source(source, data_root)
    hs, ws = img.shape
    fit = (int((hs - 2 * margin_px) * source_px), int((ws - 2 * margin_px) * source_px))
    if size is None:
        size = (min(384, fit[0]), min(512, fit[1]))
    size = (int(size[0]), int(size[1]))
    if size[0] > fit[0] or size[1] > fit[1] or min(size) < 16:
        raise SemlabError(f"size {size[0]}x{size[1]} does not fit the {ws}x{hs} source with "
                          f"source_px={source_px} and margin_px={margin_px} (at most "
                          f"{fit[0]}x{fit[1]})")
    if not 0 < source_px <= 2:
        raise SemlabError(f"source_px must be in (0, 2], got {source_px!r}")
    src = ndimage.gaussian_filter(img, antialias_px) if antialias_px else img.copy()
    mean = float(src.mean())
    if not mean > 0:
        raise SemlabError("the source image has no positive mean signal; is it an SEM image?")
    coeffs = ndimage.spline_filter(src / mean, order=3)
    base = synth.make_scene(seed=seed, size=size, pixel_size_um=pixel_size_um,
                            band_angle_deg=band_angle_deg, slip_um=slip_um,
                            uniform_strain=uniform_strain, flat=flat, texture="featureless")
    kw = {f.name: getattr(base, f.name) for f in dataclasses.fields(synth.Scene)}
    kw.update(texture_kind=f"real:{source if isinstance(source, str) else 'array'}")
    scene = RealTextureScene(**kw, source_coeffs=coeffs, source_tilt_deg=float(source_tilt_deg),
                             source_step_um=source_px * pixel_size_um,
                             source_center_px=((ws - 1) / 2, (hs - 1) / 2))
    if n_landmarks:
        scene = dataclasses.replace(scene, particles_um=_landmarks(scene, src, size, n_landmarks))
    return scene, size


def _landmarks(scene, src, size, n):
    """Shi–Tomasi corners of the source inside the view at the source tilt, as material points."""
    import cv2

    h, w = size
    s = scene.pixel_size_um
    cs, rs = scene.source_center_px
    step = scene.source_step_um
    # the source window that the view at source_tilt_deg shows
    half_c, half_r = (w - 1) / 2 * s / step, (h - 1) / 2 * s / step
    c0, c1 = int(cs - half_c), int(cs + half_c) + 1
    r0, r1 = int(rs - half_r), int(rs + half_r) + 1
    win = src[r0:r1, c0:c1]
    win8 = np.clip((win - win.min()) / (np.ptp(win) + 1e-12) * 255, 0, 255).astype(np.uint8)
    pts = cv2.goodFeaturesToTrack(win8, maxCorners=int(n), qualityLevel=0.01,
                                  minDistance=max(3.0, 8 * s / step), blockSize=7)
    if pts is None:
        return np.zeros((0, 2))
    pts = pts.reshape(-1, 2)
    return material_at_source(scene, pts[:, 0] + c0, pts[:, 1] + r0)


def make_experiment(out_dir, source="fei", seed=0, size=None, pixel_size_um=0.03,
                    tilts_deg=(-5.0, 5.0), source_tilt_deg=None, n_frames=6, detector="realistic",
                    source_px=0.5, antialias_px=1.0, slip_um=0.15, uniform_strain=(0.0, 0.0, 0.0),
                    early_contrast=1.0, data_root=None, **kwargs):
    """Write an experiment folder (views, series, clicks, ``truth/``) on a real texture.

    Parameters
    ----------
    out_dir : str or Path
        New folder.
    source : str, Path or array
        See :func:`load_source` (``"fei"``, ``"quartz"``, ``"pollen"`` or an image).
    seed : int
        Seeds the surface and the noise.
    size : (H, W), optional
        View size (default: the largest fitting the source, at most 384×512).
    tilts_deg : sequence of float
        Stage tilts of the end-state views (2+, or empty).
    source_tilt_deg : float, optional
        Tilt at which the source is the view; default ``tilts_deg[0]`` (view 0 is the real
        image) or 0 without views.
    n_frames : int
        Frontal series frames (the displacement field of :mod:`semlab.synth`).
    detector : Detector, "low", "realistic" or None
        Noise of every image (:func:`semlab.synth.detect`); None: synth's additive Gaussian.
    source_px, antialias_px, slip_um, uniform_strain
        See :func:`make_real_scene`.
    early_contrast : float
        Texture contrast of frame 0 (1: the real texture throughout the series).
    **kwargs
        Passed to :func:`semlab.synth.make_experiment` (``n_clicks``, ``click_noise_px``,
        ``write_block``, ``tilt_in_toml``, ``name``, ``overwrite``, ``progress``, ...).

    Returns
    -------
    Path of the written ``experiment.toml``. ``truth/realtex.json`` records the source and
    its placement.
    """
    tilts = [float(t) for t in tilts_deg]
    if source_tilt_deg is None:
        source_tilt_deg = tilts[0] if tilts else 0.0
    scene, size = make_real_scene(source, seed=seed, size=size, pixel_size_um=pixel_size_um,
                                  source_tilt_deg=source_tilt_deg, source_px=source_px,
                                  antialias_px=antialias_px, slip_um=slip_um,
                                  uniform_strain=uniform_strain, data_root=data_root)
    kwargs.setdefault("write_block", False)
    kwargs.setdefault("name", f"real texture {scene.texture_kind[5:]} on a synthetic surface "
                              f"(seed {seed})")
    toml = synth.make_experiment(out_dir, seed=seed, size=size, pixel_size_um=pixel_size_um,
                                 tilts_deg=tilts, n_frames=n_frames, detector=detector,
                                 scene=scene, blur_px=0.0, shading=False,
                                 early_contrast=early_contrast, **kwargs)
    info = {"source": source if isinstance(source, str) else "array",
            "source_file": (SOURCES.get(source, str(source)) if isinstance(source, str) else None),
            "source_shape": list(scene.source_coeffs.shape),
            "source_tilt_deg": scene.source_tilt_deg, "source_px": source_px,
            "source_step_um": scene.source_step_um,
            "source_center_px": list(scene.source_center_px), "antialias_px": antialias_px,
            "surface": "semlab.synth.make_scene(seed, size, pixel_size_um, slip_um=...)",
            "seed": seed, "size": list(size), "slip_um": slip_um,
            "uniform_strain": list(uniform_strain)}
    with open(Path(out_dir) / "truth" / "realtex.json", "w") as fh:
        json.dump(info, fh, indent=1)
    return toml
