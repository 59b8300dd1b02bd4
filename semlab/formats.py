"""Writers (and readers, for checks) of height maps in the formats metrology tools open.

- float32 TIFF (µm, NaN = not measured), with the pixel size as TIFF resolution and a
  JSON description (``tifffile``);
- ISO 25178-72 ``.x3p`` via the maintained ``x3pio`` package (lateral spacing = pixel size,
  heights in **metres** as the standard says, NaN = not measured);
- Gwyddion Simple Field ``.gsf`` (a text header padded with NUL bytes to a multiple of 4,
  then little-endian float32 heights, metres; http://gwyddion.net/documentation/user-guide-en/gsf.html);
- ``.ply`` point cloud (x, y, z in µm, plus ``sigma_um``) via ``plyfile``.

Maps are ``(H, W)`` arrays indexed ``[row, col]``; row 0 is the top of the image (y down),
pixel ``[i, j]`` at ``(x, y) = (j, i) · pixel_size_um``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .errors import SemlabError

__all__ = ["write_float_tiff", "read_float_tiff", "write_x3p", "read_x3p_um", "write_gsf",
           "read_gsf", "write_ply"]

_GSF_MAGIC = b"Gwyddion Simple Field 1.0\n"


def _as_map(z, name="z_um"):
    a = np.asarray(z)
    if a.ndim != 2 or a.size == 0:
        raise SemlabError(f"{name} must be a non-empty 2D map, got shape {a.shape}")
    return a


def _check_pixel(pixel_size_um):
    if pixel_size_um is None or not np.isfinite(pixel_size_um) or pixel_size_um <= 0:
        raise SemlabError(f"pixel_size_um must be a positive number, got {pixel_size_um!r}")
    return float(pixel_size_um)


def write_float_tiff(path, z_um, pixel_size_um, title="height (um)", metadata=None):
    """Write a float32 map (µm) as a TIFF; NaN kept as NaN.

    The pixel size goes into the TIFF resolution (pixels per centimetre) and, with
    ``title`` and ``metadata`` (JSON-ready dict), into the ImageDescription as JSON.
    """
    import tifffile

    z = _as_map(z_um).astype(np.float32)
    s = _check_pixel(pixel_size_um)
    desc = {"title": title, "unit": "um", "pixel_size_um": s, "nan": "not measured"}
    if metadata:
        desc["semlab"] = metadata
    per_cm = 1e4 / s
    tifffile.imwrite(Path(path), z, description=json.dumps(desc), metadata=None,
                     resolution=(per_cm, per_cm), resolutionunit="CENTIMETER")
    return Path(path)


def read_float_tiff(path):
    """Read a map written by :func:`write_float_tiff`: ``(z, description dict)``."""
    import tifffile

    with tifffile.TiffFile(Path(path)) as tf:
        z = tf.pages[0].asarray()
        try:
            desc = json.loads(tf.pages[0].description)
        except (ValueError, TypeError):
            desc = {}
    return z, desc


def write_x3p(path, z_um, pixel_size_um):
    """Write an ISO 25178-72 ``.x3p`` surface (heights in metres, float64, NaN = not measured).

    Heights are stored as float64 metres ``z_um · 1e-6`` so that reading back and converting
    to float32 µm gives the float32 map exactly (:func:`read_x3p_um`).
    """
    import x3pio

    z = _as_map(z_um).astype(np.float64) * 1e-6
    s = _check_pixel(pixel_size_um) * 1e-6
    x3pio.write(Path(path), z, x_scale=s, y_scale=s)
    return Path(path)


def read_x3p_um(path):
    """Read an ``.x3p`` surface: ``(z_um (H, W) float array, pixel_size_um)``."""
    import x3pio

    f = x3pio.read(Path(path))
    z = np.asarray(f.layers[0].z, float) * 1e6
    return z, float(f.header.x.increment) * 1e6


def write_gsf(path, z_um, pixel_size_um, title="height"):
    """Write a Gwyddion Simple Field ``.gsf`` (float32 metres; NaN marks missing data,
    which Gwyddion masks on import)."""
    z = _as_map(z_um).astype("<f4") * np.float32(1e-6)
    s = _check_pixel(pixel_size_um) * 1e-6
    hgt, wid = z.shape
    head = (_GSF_MAGIC + (f"XRes = {wid}\nYRes = {hgt}\nXReal = {wid * s!r}\n"
                          f"YReal = {hgt * s!r}\nXYUnits = m\nZUnits = m\n"
                          f"Title = {title}\n").encode("ascii"))
    pad = 4 - len(head) % 4            # 1..4 NUL bytes, as the format requires
    with open(path, "wb") as fh:
        fh.write(head + b"\0" * pad)
        fh.write(np.ascontiguousarray(z).tobytes())
    return Path(path)


def read_gsf(path):
    """Read a ``.gsf`` file: ``(z_um (H, W) float32 array, header dict)``."""
    raw = Path(path).read_bytes()
    if not raw.startswith(_GSF_MAGIC):
        raise SemlabError(f"{path}: not a Gwyddion Simple Field file (bad magic line)")
    end = raw.index(b"\0")
    head = {}
    for line in raw[len(_GSF_MAGIC):end].decode("ascii").splitlines():
        if "=" in line:
            k, v = line.split("=", 1)
            head[k.strip()] = v.strip()
    wid, hgt = int(head["XRes"]), int(head["YRes"])
    start = end + 4 - end % 4          # the header is NUL-padded to a multiple of 4
    if len(raw) - start != 4 * wid * hgt:
        raise SemlabError(f"{path}: {len(raw) - start} data bytes, expected {4 * wid * hgt} "
                          f"for XRes = {wid}, YRes = {hgt}")
    data = np.frombuffer(raw[start:], "<f4").reshape(hgt, wid)
    return data * np.float32(1e6), head


def write_ply(path, z_um, pixel_size_um, sigma_um=None, origin_px=(0, 0), binary=True):
    """Write the measured pixels of a map as a ``.ply`` point cloud (``plyfile``).

    Vertices ``x, y, z`` (float32 µm; x right, y down in the image, so z up makes it a
    left-handed frame: ``y`` is written as ``-y`` to keep ``z > 0`` extrusions pointing
    out of the surface in a right-handed viewer) and ``sigma_um`` when given.
    Only pixels with a finite height are written.
    """
    from plyfile import PlyData, PlyElement

    z = _as_map(z_um).astype(np.float64)
    s = _check_pixel(pixel_size_um)
    ii, jj = np.nonzero(np.isfinite(z))
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if sigma_um is not None:
        fields.append(("sigma_um", "f4"))
    v = np.empty(len(ii), dtype=fields)
    v["x"] = (jj + origin_px[0]) * s
    v["y"] = -(ii + origin_px[1]) * s
    v["z"] = z[ii, jj]
    if sigma_um is not None:
        v["sigma_um"] = np.asarray(sigma_um, float)[ii, jj]
    PlyData([PlyElement.describe(v, "vertex")], text=not binary,
            comments=["semlab height map, units um, y = -image row"]).write(str(path))
    return Path(path)
