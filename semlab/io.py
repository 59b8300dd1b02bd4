"""Reading SEM images and the calibration their microscope wrote into them.

TIFF (8/16-bit, first page of a multi-page file) and PNG are read. The pixel size and the
stage tilt are taken from the file where the SEM wrote them:

- FEI / Thermo Fisher: TIFF tag 34682 (or 34680), an INI text parsed by tifffile as
  ``TiffFile.fei_metadata``; ``[Scan] PixelWidth`` in metres, ``[Stage] StageT`` in radians,
  ``[Image] ResolutionY`` the height of the image area above the data bar.
- Zeiss: TIFF tag 34118, parsed by tifffile as ``TiffFile.sem_metadata``;
  ``ap_image_pixel_size`` (value and unit), ``ap_stage_at_t`` (degrees), ``dp_image_store``
  ("W * H", the image area above the data bar).

The data bar that FEI and Zeiss microscopes append below the image is not sample surface and
is removed (``SEMImage.data`` holds the image area only; ``databar_rows`` says how many rows
were cut).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ImageError

#: File suffixes :func:`read_image` accepts.
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".bmp")

_LENGTH_UNITS_UM = {"m": 1e6, "mm": 1e3, "um": 1.0, "µm": 1.0, "μm": 1.0, "nm": 1e-3, "pm": 1e-6}


@dataclass(frozen=True)
class SEMImage:
    """An SEM image and the calibration found in its file.

    Attributes
    ----------
    data : (H, W) float64 array
        Image area (data bar removed) in the file's raw intensity units, indexed ``[row, col]``.
    path : Path
        The file it came from.
    pixel_size_um : float or None
        Pixel size in µm/px from the file's SEM metadata, None when the file holds none.
    tilt_deg : float or None
        Stage tilt in degrees from the file's SEM metadata, None when absent.
    source : str
        Where the calibration came from: ``"fei"``, ``"zeiss"`` or ``"none"``.
    bit_depth : int
        Bits per sample of the stored image (8 or 16 for SEM files).
    databar_rows : int
        Rows removed from the bottom of the stored image (the data bar).
    metadata : dict
        The raw parsed metadata (FEI sections or Zeiss keys), for reference.
    """

    data: np.ndarray
    path: Path
    pixel_size_um: float | None = None
    tilt_deg: float | None = None
    source: str = "none"
    bit_depth: int = 8
    databar_rows: int = 0
    metadata: dict = field(default_factory=dict, repr=False)

    @property
    def shape(self):
        """``(H, W)`` of the image area."""
        return self.data.shape


def _to_um(value, unit, path, key):
    unit = (unit or "").strip().replace("\u00b5", "µ")
    if unit not in _LENGTH_UNITS_UM:
        raise ImageError(
            f"{path}: SEM metadata {key} has an unknown length unit {unit!r}; "
            "give pixel_size_um in experiment.toml instead")
    return float(value) * _LENGTH_UNITS_UM[unit]


def _fei_calibration(meta, path):
    """Pixel size (µm), tilt (deg) and image-area height from FEI metadata sections."""
    scan = meta.get("Scan", {}) or {}
    stage = meta.get("Stage", {}) or {}
    image = meta.get("Image", {}) or {}
    px = scan.get("PixelWidth")
    pixel_size_um = float(px) * 1e6 if isinstance(px, (int, float)) and px > 0 else None
    t = stage.get("StageT")
    tilt_deg = float(np.rad2deg(t)) if isinstance(t, (int, float)) else None
    rows = image.get("ResolutionY")
    rows = int(rows) if isinstance(rows, (int, float)) and rows > 0 else None
    return pixel_size_um, tilt_deg, rows


def _zeiss_calibration(meta, path):
    """Pixel size (µm), tilt (deg) and image-area height from Zeiss SEM metadata."""
    pixel_size_um = tilt_deg = rows = None
    ps = meta.get("ap_image_pixel_size")
    if isinstance(ps, tuple) and len(ps) >= 2 and isinstance(ps[1], (int, float)):
        unit = ps[2] if len(ps) > 2 else "nm"
        pixel_size_um = _to_um(ps[1], unit, path, "ap_image_pixel_size")
    t = meta.get("ap_stage_at_t")
    if isinstance(t, tuple) and len(t) >= 2 and isinstance(t[1], (int, float)):
        tilt_deg = float(t[1])
        if len(t) > 2 and str(t[2]).lower().startswith("rad"):
            tilt_deg = float(np.rad2deg(t[1]))
    store = meta.get("dp_image_store")
    if isinstance(store, tuple) and len(store) >= 2:
        m = re.match(r"\s*(\d+)\s*\*\s*(\d+)", str(store[1]))
        if m:
            rows = int(m.group(2))
    return pixel_size_um, tilt_deg, rows


def _read_tiff(path):
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            data = page.asarray()
            source, meta = "none", {}
            calib = (None, None, None)
            fei = tif.fei_metadata if tif.is_fei else None
            sem = tif.sem_metadata if tif.is_sem else None
            if fei:
                source, meta = "fei", fei
                calib = _fei_calibration(fei, path)
            elif sem:
                source, meta = "zeiss", sem
                calib = _zeiss_calibration(sem, path)
    except ImageError:
        raise
    except Exception as exc:  # tifffile raises many types for corrupt files
        raise ImageError(f"{path}: cannot read this TIFF ({exc}); is it a complete image file?") from exc
    return data, source, meta, calib


def _read_other(path):
    import cv2

    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None:
        raise ImageError(f"{path}: cannot read this image; use TIFF or PNG")
    if data.ndim == 3:
        # OpenCV gives BGR(A); SEM images are grey, so average the colour channels.
        data = data[..., :3].mean(axis=2)
    return data, "none", {}, (None, None, None)


def read_image(path) -> SEMImage:
    """Read an SEM image and its calibration.

    Parameters
    ----------
    path : str or Path
        TIFF (8/16-bit; the first page of a multi-page file) or PNG file.

    Returns
    -------
    SEMImage
        ``data`` is a (H, W) float64 array of the image area (data bar removed), indexed
        ``[row, col]``; ``pixel_size_um`` and ``tilt_deg`` come from the SEM metadata when the
        file holds them (FEI tag 34682 / Zeiss tag 34118), else None.

    Raises
    ------
    ImageError
        Missing file, unsupported format, unreadable content, or an image that is not 2D.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: image file not found; check the path (relative paths in "
                         "experiment.toml are relative to the TOML file)")
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ImageError(f"{path}: unsupported image type {suffix!r}; use one of {IMAGE_SUFFIXES}")
    if suffix in (".tif", ".tiff"):
        data, source, meta, (pixel_size_um, tilt_deg, rows) = _read_tiff(path)
    else:
        data, source, meta, (pixel_size_um, tilt_deg, rows) = _read_other(path)
    data = np.asarray(data)
    if data.ndim == 3 and data.shape[-1] in (3, 4):
        data = data[..., :3].mean(axis=2)
    if data.ndim != 2:
        raise ImageError(f"{path}: expected a 2D grey image, got an array of shape {data.shape}")
    bit_depth = int(np.dtype(data.dtype).itemsize * 8) if data.dtype.kind in "ui" else 32
    databar_rows = 0
    if rows is not None and 0 < rows < data.shape[0]:
        databar_rows = data.shape[0] - rows
        data = data[:rows]
    data = data.astype(np.float64)
    if not np.all(np.isfinite(data)):
        raise ImageError(f"{path}: the image contains NaN or infinite values")
    return SEMImage(data=data, path=path, pixel_size_um=pixel_size_um, tilt_deg=tilt_deg,
                    source=source, bit_depth=bit_depth, databar_rows=databar_rows, metadata=meta)


def zeiss_metadata_text(pixel_size_um=None, tilt_deg=None, image_size=None):
    """Text of a Zeiss SEM TIFF tag 34118 holding pixel size, stage tilt and image size.

    Used by :mod:`semlab.synth` so that synthetic experiments carry their calibration the way a
    real Zeiss microscope writes it (tifffile parses it back as ``TiffFile.sem_metadata``).

    Parameters
    ----------
    pixel_size_um : float, optional
    tilt_deg : float, optional
    image_size : (W, H) tuple of int, optional
        Size of the image area (above any data bar).
    """
    lines = ["0", "0"]
    if pixel_size_um is not None:
        lines += ["AP_IMAGE_PIXEL_SIZE", f"Image Pixel Size = {pixel_size_um * 1e3:.6f} nm"]
    if tilt_deg is not None:
        lines += ["AP_STAGE_AT_T", f"Stage at T = {tilt_deg:.6f} deg"]
    if image_size is not None:
        lines += ["DP_IMAGE_STORE", f"Store resolution = {int(image_size[0])} * {int(image_size[1])}"]
    return "\r\n".join(lines) + "\r\n"


def write_tiff(path, data, pixel_size_um=None, tilt_deg=None, overwrite=False):
    """Write a grey image as TIFF, with Zeiss-style SEM metadata when calibration is given.

    Parameters
    ----------
    path : str or Path
    data : (H, W) array, uint8 or uint16
    pixel_size_um, tilt_deg : float, optional
        Written into tag 34118 so that :func:`read_image` finds them.
    overwrite : bool
        Refuse to replace an existing file unless True.
    """
    import tifffile

    path = Path(path)
    if path.exists() and not overwrite:
        raise ImageError(f"{path}: exists already; semlab does not overwrite data")
    extratags = []
    if pixel_size_um is not None or tilt_deg is not None:
        h, w = np.asarray(data).shape[:2]
        text = zeiss_metadata_text(pixel_size_um, tilt_deg, (w, h))
        extratags.append((34118, "s", 0, text, True))
    path.parent.mkdir(parents=True, exist_ok=True)
    tifffile.imwrite(path, np.asarray(data), extratags=extratags)
    return path
