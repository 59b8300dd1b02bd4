"""Tests of semlab.noise: noise measured from images."""

import numpy as np
import pytest
from scipy import ndimage

from semlab.errors import ImageError
from semlab.noise import calibrated_noise_sigma, filter_noise_gain, image_noise_sigma


@pytest.mark.parametrize("sigma", [1.0, 3.0, 6.0])
def test_noise_of_textured_image(sigma):
    rng = np.random.default_rng(0)
    tex = ndimage.gaussian_filter(rng.normal(0, 40, (300, 300)), 2.0) * 4   # std ~ 22
    assert tex.std() > 3.5 * sigma
    img = 100 + tex + rng.normal(0, sigma, tex.shape)
    assert image_noise_sigma(img) == pytest.approx(sigma, rel=0.08)
    # outliers (hot pixels) and a few edges do not inflate it
    img[rng.integers(0, 300, 200), rng.integers(0, 300, 200)] = 255
    img[:, 150:] += 80
    assert image_noise_sigma(img) == pytest.approx(sigma, rel=0.12)
    m = np.zeros(img.shape, bool)
    m[10:100, 10:100] = True
    assert image_noise_sigma(img, mask=m) == pytest.approx(sigma, rel=0.15)


def test_noise_errors_and_gain():
    assert image_noise_sigma(np.full((20, 20), 3.0)) == 0.0
    with pytest.raises(ImageError):
        image_noise_sigma(np.zeros(5))
    with pytest.raises(ImageError):
        image_noise_sigma(np.full((5, 5), np.nan))
    with pytest.raises(ImageError, match="mask"):
        image_noise_sigma(np.zeros((5, 5)), mask=np.ones((4, 4), bool))
    assert filter_noise_gain(lambda a: a) == 1.0
    assert filter_noise_gain(lambda a: ndimage.uniform_filter(a, 3)) == pytest.approx(1 / 9)


@pytest.mark.parametrize("level", ["low", "realistic"])
def test_noise_of_a_poisson_8bit_sem_view(level):
    """Known answer on the detector model of semlab.synth (Poisson shot noise for a dose,
    gain, 8-bit quantisation): the estimate is the RMS of the per-pixel noise σ, on a
    speckle and on a low-texture (polished) scene."""
    from semlab import synth

    det = synth.as_detector(level)
    for texture in ("speckle", "polished"):
        scene = synth.make_scene(seed=0, size=(128, 160), texture=texture)
        clean, _, _ = synth.render(scene, (128, 160), -5.0, noise=0)
        img = synth.detect(clean, det, np.random.default_rng(1), gain=1.0, offset=0.0)
        top = (2 ** det.bits - 1) / det.full_scale
        true = np.sqrt(np.mean(top ** 2 * np.clip(clean, 0, None) / det.dose_e_per_px + 1 / 12))
        assert image_noise_sigma(img) == pytest.approx(true, rel=0.08), texture


def _fine_pair(shape=(120, 160), shift=0.3, noise=0.05, seed=0):
    """A texture sharp at the pixel scale (Gaussian of 1 px on white noise, std 1), view 1
    shifted by ``shift`` px in x, white noise ``noise`` on both."""
    rng = np.random.default_rng(seed)
    t = ndimage.gaussian_filter(rng.normal(size=shape), 1.0)
    t /= t.std()
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    t1 = ndimage.map_coordinates(t, [yy, xx - shift], order=3, mode="reflect")
    return t + rng.normal(0, noise, shape), t1 + rng.normal(0, noise, shape)


def test_calibrated_noise_of_a_fine_texture_is_the_true_noise():
    """Known answer: Immerkær's estimate counts the pixel-scale texture as noise (~2x the
    true 0.05); the calibration at matched subsets (the matcher's) brings it to the truth."""
    a, b = _fine_pair()
    assert image_noise_sigma(a) > 1.6 * 0.05
    gy, gx = np.mgrid[15:105:8, 15:145:8]
    pts = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    pts[3] = np.nan                                   # skipped
    s0, s1 = calibrated_noise_sigma(a, b, pts, pts + [0.3, 0.0])
    assert s0 == pytest.approx(0.05, rel=0.15) and s1 == pytest.approx(0.05, rel=0.15)
    # the same number as icgn_refine's own default at those matches
    from semlab.subset import icgn_refine

    ok = np.all(np.isfinite(pts), 1)
    r = icgn_refine(a, b, pts[ok], pts[ok] + [0.3, 0.0], half_window=10)
    np.testing.assert_allclose((s0, s1), r.noise_sigma, rtol=1e-12)
    # no usable match: Immerkær's values
    assert calibrated_noise_sigma(a, b, np.full((2, 2), np.nan), np.zeros((2, 2))) == \
        (image_noise_sigma(a), image_noise_sigma(b))
    with pytest.raises(ImageError, match="one length"):
        calibrated_noise_sigma(a, b, pts, pts[:5])
