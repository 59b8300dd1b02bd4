import numpy as np
import pytest

from semlab.errors import ImageError
from semlab.io import read_image, write_tiff, zeiss_metadata_text

from conftest import shared_path


def test_fei_tiff_pixel_size_and_databar():
    p = shared_path("real_sem", "fei_tiff", "P33_scale2s3_detectorA.tif")
    im = read_image(p)
    assert im.source == "fei"
    assert im.pixel_size_um == pytest.approx(0.0651042, rel=1e-6)  # 65.1 nm
    assert im.shape == (1024, 1536)  # data bar removed (stored 1103 rows)
    assert im.databar_rows == 1103 - 1024
    assert im.bit_depth == 16
    assert abs(im.tilt_deg) < 0.01  # StageT 5e-5 rad


def test_zeiss_roundtrip(tmp_path):
    data = (np.arange(60 * 50) % 65535).reshape(50, 60).astype(np.uint16)
    f = write_tiff(tmp_path / "z.tif", data, pixel_size_um=0.0275, tilt_deg=-4.5)
    im = read_image(f)
    assert im.source == "zeiss"
    assert im.pixel_size_um == pytest.approx(0.0275)
    assert im.tilt_deg == pytest.approx(-4.5)
    np.testing.assert_array_equal(im.data, data.astype(float))


def test_zeiss_databar_removed(tmp_path):
    import tifffile

    data = np.zeros((70, 60), np.uint16)
    data[50:] = 65535  # a "data bar"
    text = zeiss_metadata_text(0.01, 0.0, (60, 50))
    tifffile.imwrite(tmp_path / "bar.tif", data, extratags=[(34118, "s", 0, text, True)])
    im = read_image(tmp_path / "bar.tif")
    assert im.shape == (50, 60) and im.databar_rows == 20 and im.data.max() == 0


def test_png_and_plain_tiff_have_no_calibration(tmp_path):
    import cv2
    import tifffile

    img = (np.random.default_rng(0).random((20, 30)) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.png"), img)
    tifffile.imwrite(tmp_path / "b.tif", np.stack([img, img]))  # multi-page: first page
    a, b = read_image(tmp_path / "a.png"), read_image(tmp_path / "b.tif")
    assert a.pixel_size_um is None and a.source == "none"
    np.testing.assert_array_equal(a.data, img)
    np.testing.assert_array_equal(b.data, img)


def test_quartz_png_reads():
    im = read_image(shared_path("real_sem", "quarz", "Quarz_01.png"))
    assert im.shape == (1200, 1200) and im.pixel_size_um is None


def test_errors(tmp_path):
    with pytest.raises(ImageError, match="not found"):
        read_image(tmp_path / "missing.tif")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(ImageError, match="unsupported"):
        read_image(tmp_path / "x.txt")
    (tmp_path / "bad.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(ImageError, match="cannot read"):
        read_image(tmp_path / "bad.tif")
    f = write_tiff(tmp_path / "ok.tif", np.zeros((4, 4), np.uint8))
    with pytest.raises(ImageError, match="overwrite"):
        write_tiff(f, np.zeros((4, 4), np.uint8))
