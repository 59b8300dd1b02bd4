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

Text files (``experiment.toml``, ``correspondences.csv``, ``lines.json``) are read by one
reader, :func:`read_text`: UTF-8 with or without a byte-order mark; anything else (UTF-16,
Latin-1, binary data) is refused with the file, the encoding it seems to have and the command
that converts it. Files semlab writes go through :func:`atomic_write_bytes` /
:func:`atomic_write_text` (a temporary name in the same folder, then ``os.replace``, so a
reader never sees half a file) and, where they replace a user's file, :func:`write_with_backup`.
"""

from __future__ import annotations

import codecs
import contextlib
import logging
import os
import re
import shutil
import stat
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import ImageError, SemlabError

__all__ = [
    "IMAGE_SUFFIXES",
    "SEMImage",
    "read_image",
    "read_text",
    "quiet_loggers",
    "atomic_write_bytes",
    "atomic_write_text",
    "backup_path",
    "backup_file",
    "write_with_backup",
    "write_tiff",
    "zeiss_metadata_text",
]

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
    # kept as written (also zero, negative or NaN): semlab.experiment checks the range and
    # names the file when a value is impossible
    pixel_size_um = float(px) * 1e6 if isinstance(px, (int, float)) else None
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


@contextlib.contextmanager
def quiet_loggers(*names):
    """Silence libraries' loggers for a block (tifffile logs warnings on damaged files; the
    notebook machinery logs kernel noise): semlab raises its own one-line message instead."""
    logs = [logging.getLogger(n) for n in names]
    old = [lg.level for lg in logs]
    for lg in logs:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, lvl in zip(logs, old):
            lg.setLevel(lvl)


def _read_tiff(path):
    import tifffile

    try:
        with quiet_loggers("tifffile"), tifffile.TiffFile(path) as tif:
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


@contextlib.contextmanager
def _captured_c_stderr():
    """Capture what C libraries (libjpeg, libpng inside OpenCV) write to file descriptor 2.

    Yields a list that holds the captured text after the block. When descriptor 2 cannot be
    redirected (no such descriptor), the block runs unchanged and the list stays empty.
    """
    captured = []
    with _STDERR_LOCK:
        try:
            saved = os.dup(2)
        except OSError:
            yield captured
            return
        with tempfile.TemporaryFile() as tmp:
            try:
                os.dup2(tmp.fileno(), 2)
                yield captured
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                captured.append(tmp.read().decode("utf-8", "replace").strip())


_STDERR_LOCK = threading.Lock()
#: What libjpeg / libpng print about a damaged file (anything else captured is passed on).
_DECODER_DAMAGE = re.compile(r"JPEG|libpng|PNG|Corrupt|Premature end|CRC|IDAT", re.I)


def _read_other(path):
    import cv2

    with _captured_c_stderr() as decoder_messages:
        data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    text = "\n".join(m for m in decoder_messages if m)
    damage = " ".join(ln.strip() for ln in text.splitlines() if _DECODER_DAMAGE.search(ln))
    other = "\n".join(ln for ln in text.splitlines() if not _DECODER_DAMAGE.search(ln))
    if other:  # not the decoder's: someone else wrote to stderr meanwhile; pass it on
        sys.stderr.write(other + "\n")
    if data is not None and damage:
        # libjpeg fills a truncated file with grey and only prints a warning: refuse it
        raise ImageError(f"{path}: the image is damaged (the decoder says: {damage}); copy "
                         "it from the microscope again or re-export it as TIFF or PNG")
    if data is None:
        said = f"; the decoder says: {damage}" if damage else ""
        raise ImageError(f"{path}: cannot read this image (damaged, or not a {path.suffix} "
                         f"image{said}); re-export it as TIFF or PNG")
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
    if path.stat().st_size == 0:
        raise ImageError(f"{path}: the file is empty (0 bytes), not an image; copy the image "
                         "from the microscope again")
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
        raise ImageError(f"{path}: the image contains NaN or infinite values; export it as an "
                         "8/16-bit TIFF or PNG")
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


# ---------------------------------------------------------------------------- text files
_BOMS = ((codecs.BOM_UTF32_LE, "UTF-32"), (codecs.BOM_UTF32_BE, "UTF-32"),
         (codecs.BOM_UTF16_LE, "UTF-16"), (codecs.BOM_UTF16_BE, "UTF-16"))


def _guess_encoding(data):
    """What non-UTF-8 bytes seem to be: ``(name for people, iconv name or None)``."""
    for bom, name in _BOMS:
        if data.startswith(bom):
            return f"{name} (it starts with a {name} byte-order mark)", name
    head = data[:4096]
    if head and head.count(0) > len(head) // 8:
        even, odd = head[0::2].count(0), head[1::2].count(0)
        if max(even, odd) > 0.4 * (len(head) / 2) and min(even, odd) < 0.05 * (len(head) / 2):
            name = "UTF-16BE" if even > odd else "UTF-16LE"
            return f"{name} (every other byte is zero)", name
        return "binary data, not text", None
    # control bytes other than tab/newline/carriage return/form feed: not a text file
    ctrl = sum(b < 32 and b not in (9, 10, 12, 13) for b in head)
    if ctrl > max(2, len(head) // 100):
        return "binary data, not text", None
    return "Latin-1 / Windows-1252 (single-byte text, e.g. 'µ' stored as 0xB5)", "latin1"


def read_text(path, what="text file"):
    """Read a text file that must be UTF-8 (with or without a byte-order mark).

    The one reader of semlab's text inputs (``experiment.toml``, ``correspondences.csv``,
    ``lines.json``), so that every one of them accepts and refuses the same things.

    Parameters
    ----------
    path : str or Path
    what : str
        What the file is, for the message (e.g. ``"experiment.toml"``).

    Returns
    -------
    str
        The text, without a leading byte-order mark.

    Raises
    ------
    SemlabError
        The file cannot be read, or is not UTF-8: the message names the file, the encoding
        it seems to have (UTF-16, Latin-1, binary) and how to convert it
        (``iconv -f latin1 -t utf-8``).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SemlabError(f"{path}: {what} not found; check the path") from None
    except IsADirectoryError:
        raise SemlabError(f"{path}: is a folder, but a {what} (a text file) is expected") from None
    except OSError as exc:
        raise SemlabError(f"{path}: cannot read the {what} ({exc.strerror}); check the file's "
                          "permissions") from None
    if data.startswith(codecs.BOM_UTF8):
        data = data[len(codecs.BOM_UTF8):]
    bad = None
    if not any(data.startswith(bom) for bom, _ in _BOMS):
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            bad = exc.start
        else:
            if "\x00" not in text:
                return text
            bad = text.index("\x00")
    seems, enc = _guess_encoding(data)
    where = "" if bad is None else f" (byte {bad}, line {data[:bad].count(10) + 1})"
    if enc is None:
        fix = f"This is not a text file: check that it is the right {what}"
    else:
        fix = (f"Convert it to UTF-8, e.g. iconv -f {enc} -t utf-8 '{path}' > converted "
               f"&& mv converted '{path}' (or re-save it as UTF-8 in your editor)")
    raise SemlabError(f"{path}: the {what} is not UTF-8 text{where}; it looks like {seems}. "
                      f"{fix}")


# ---------------------------------------------------------------------------- writing files
def atomic_write_bytes(path, data):
    """Write ``data`` to ``path`` atomically: a temporary file beside it, then ``os.replace``.

    A reader (or a run that is interrupted) sees the old file or the complete new one, never
    half a file. An existing file is replaced (see :func:`write_with_backup` to keep it) and
    its permissions are kept; a new file gets those of the user's umask.

    Parameters
    ----------
    path : str or Path
    data : bytes

    Returns
    -------
    Path
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        _copy_mode(path, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    return path


def _copy_mode(path, tmp):
    """Give ``tmp`` the permissions (and, where allowed, the owner) of ``path``, or those of
    a new file under the user's umask when ``path`` does not exist: ``mkstemp`` creates
    ``-rw-------``, and colleagues sharing the folder would lose read access."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        return
    os.chmod(tmp, stat.S_IMODE(st.st_mode))
    if hasattr(os, "chown"):
        try:
            os.chown(tmp, st.st_uid, st.st_gid)
        except OSError:
            pass  # only root may give a file away; the group may still be set below
        else:
            return
        try:
            os.chown(tmp, -1, st.st_gid)
        except OSError:
            pass


def atomic_write_text(path, text, encoding="utf-8"):
    """Write ``text`` (UTF-8, newlines as given) atomically; see :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, str(text).encode(encoding))


def backup_path(path):
    """The first free backup name for ``path``: ``<stem>.bak<suffix>``, then ``.bak1``, ...

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    Path
        e.g. ``correspondences.bak.csv``, or ``correspondences.bak1.csv`` if that exists.
    """
    path = Path(path)
    k = 0
    while True:
        tag = ".bak" if k == 0 else f".bak{k}"
        cand = path.with_name(f"{path.stem}{tag}{path.suffix}")
        if not cand.exists():
            return cand
        k += 1


def backup_file(path):
    """Copy ``path`` to :func:`backup_path` if it exists; return the copy (or None)."""
    path = Path(path)
    if not path.exists():
        return None
    dst = backup_path(path)
    shutil.copy2(path, dst)
    return dst


def write_with_backup(path, data, backup=True):
    """Replace ``path`` atomically by ``data``, first copying an existing file to a backup.

    The one writer of files a user owns (annotations in an experiment folder): nothing is
    overwritten silently.

    Parameters
    ----------
    path : str or Path
    data : str (written as UTF-8) or bytes
    backup : bool
        Copy an existing ``path`` to :func:`backup_path` first (default). With False the
        file is replaced without a copy.

    Returns
    -------
    Path or None
        The backup written, or None when nothing was backed up.
    """
    bak = backup_file(path) if backup else None
    if isinstance(data, str):
        atomic_write_text(path, data)
    else:
        atomic_write_bytes(path, bytes(data))
    return bak
