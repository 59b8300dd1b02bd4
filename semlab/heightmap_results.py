"""What is made of a dense height map (:class:`semlab.heightmap.HeightMap`): its hill-shaded
relief, its metrology (ISO 25178 parameters, band profiles) and its result files (TIFF, X3P,
GSF, PLY, CSV).

Every name is re-exported by :mod:`semlab.heightmap`.
"""

from __future__ import annotations

import numpy as np

from .errors import SemlabError

__all__ = ["hillshade", "measure_map", "write_heightmap_results"]


def hillshade(z_um, pixel_size_um, azimuth_deg=315.0, altitude_deg=45.0, z_factor=1.0):
    """Hill-shaded relief (0..1) of a height map, NaN where the map is NaN.

    Lambertian shading of the surface normal under a light from ``azimuth_deg`` (clockwise
    from image up) at ``altitude_deg`` above the surface; ``z_factor`` exaggerates heights.
    """
    z = np.asarray(z_um, float) * float(z_factor)
    if z.ndim != 2:
        raise SemlabError(f"z_um must be a 2D map, got shape {z.shape}")
    gy, gx = np.gradient(z, float(pixel_size_um))
    az = np.deg2rad(azimuth_deg)
    alt = np.deg2rad(altitude_deg)
    # light direction in (x right, y down, z up)
    lx, ly, lz = np.sin(az) * np.cos(alt), -np.cos(az) * np.cos(alt), np.sin(alt)
    n = np.sqrt(1 + gx ** 2 + gy ** 2)
    shade = np.clip((-gx * lx - gy * ly + lz) / n, 0.0, 1.0)
    return np.where(np.isfinite(z), shade, np.nan)


def measure_map(result, regions=None, bands=None):
    """The metrology of a height map: ISO 25178 areal parameters and profiles across bands.

    Parameters
    ----------
    result : HeightMap
    regions : dict name -> (x0, y0, x1, y1) or (H, W) bool mask, optional
        Named regions on the map's pixel grid (:func:`semlab.metrology.regions_on_map`).
    bands : list of semlab.metrology.Band, optional
        Default: detected in the map (:func:`semlab.metrology.map_bands`).

    Returns
    -------
    dict
        ``surface_parameters``: the rows of :func:`semlab.metrology.surface_parameters`
        (``"map"`` first, then each region); ``bands``: the bands; ``band_profiles``: one
        :func:`semlab.metrology.band_profile` per band, in the same order.
    """
    from . import metrology

    s = result.pixel_size_um
    if bands is None:
        bands = metrology.map_bands(result.z_um, s, sigma_um=result.sigma_um)
    return {"surface_parameters": metrology.surface_parameters(result.z_um, s, regions=regions),
            "bands": list(bands),
            "band_profiles": [metrology.band_profile(result.z_um, result.sigma_um, s, b)
                              for b in bands]}


def write_heightmap_results(result, out_dir, overwrite=False, regions=None, bands=None,
                            measured=None):
    """Write the dense map and its metrology into ``out_dir``.

    Files: ``heightmap.tif`` (float32 µm, NaN = not measured), ``heightmap_sigma.tif``
    (1σ µm), ``heightmap.x3p`` (ISO 25178-72, metres), ``heightmap.gsf`` (Gwyddion),
    ``heightmap.ply`` (point cloud with σ), ``surface_parameters.csv`` (ISO 25178 areal
    parameters of the map and of ``regions``), ``bands.csv`` (profiles across each band).

    Parameters
    ----------
    result : HeightMap
    out_dir : path
    regions : dict name -> (x0, y0, x1, y1) or (H, W) bool mask, optional
    bands : list of semlab.metrology.Band, optional
        Default: detected in the map (:func:`semlab.metrology.map_bands`; pass the clicked
        cracks' bands from :func:`semlab.metrology.map_bands` with ``pts_px, crack_id``).
    measured : dict, optional
        The map's metrology already computed by :func:`measure_map` (then ``regions`` and
        ``bands`` are not used); default: :func:`measure_map` of ``regions`` and ``bands``.

    Returns
    -------
    dict name -> Path
    """
    from pathlib import Path

    from . import formats, metrology

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    names = ["heightmap.tif", "heightmap_sigma.tif", "heightmap.x3p", "heightmap.gsf",
             "heightmap.ply", "surface_parameters.csv", "bands.csv"]
    paths = {n: out / n for n in names}
    if not overwrite:
        for pth in paths.values():
            if pth.exists():
                raise SemlabError(f"{pth}: exists already; write results to a new folder")
    s = result.pixel_size_um
    meta = result.metadata()
    formats.write_float_tiff(paths["heightmap.tif"], result.z_um, s, "height z (um)", meta)
    formats.write_float_tiff(paths["heightmap_sigma.tif"], result.sigma_um, s,
                             "height 1 sigma (um)", meta)
    formats.write_x3p(paths["heightmap.x3p"], result.z_um, s)
    formats.write_gsf(paths["heightmap.gsf"], result.z_um, s, title="semlab height map")
    formats.write_ply(paths["heightmap.ply"], result.z_um, s, sigma_um=result.sigma_um,
                      origin_px=result.roi[:2])
    if measured is None:
        measured = measure_map(result, regions=regions, bands=bands)
    metrology.write_surface_parameters_csv(paths["surface_parameters.csv"],
                                           measured["surface_parameters"])
    metrology.write_bands_csv(paths["bands.csv"], measured["band_profiles"])
    return paths
