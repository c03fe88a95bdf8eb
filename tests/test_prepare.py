import numpy as np
import pytest

from kpifs import KpifsError, KpifsWarning
from kpifs.extraction.prepare import cut_out, fill_bad_pixels, find_centres
from kpifs.model.window import ExtractionWindow


def gaussian_images(centres, shape=(32, 32), sigma=1.6):
    y, x = np.mgrid[:shape[0], :shape[1]]
    return np.array([np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma ** 2))
                     for cx, cy in centres])


@pytest.mark.parametrize("method, tol", [("com", 0.05), ("quadratic", 0.1), ("2dg", 0.01),
                                         ("peak", 0.5)])
def test_centroid_methods(method, tol):
    truth = np.array([[15.3, 16.7], [12.8, 14.1], [17.45, 15.05]])
    imgs = gaussian_images(truth)
    found = find_centres(imgs, method=method, box_size=9)
    np.testing.assert_allclose(found, truth, atol=tol)


def test_centroids_robust_to_bad_pixels():
    truth = np.array([[15.3, 16.7]])
    imgs = gaussian_images(truth)
    imgs[0, 16, 14] = np.nan
    imgs[0, 3, 3] = np.nan
    for method in ("com", "2dg"):
        np.testing.assert_allclose(find_centres(imgs, method=method, box_size=9), truth,
                                   atol=0.15)


def test_centroid_fallback_warns(monkeypatch):
    import photutils.centroids

    def failing(*args, **kwargs):
        raise ValueError("fit did not converge")

    monkeypatch.setattr(photutils.centroids, "centroid_2dg", failing)
    truth = np.array([[15.3, 16.7], [12.8, 14.1]])
    with pytest.warns(KpifsWarning, match="2dg centroid failed on 2 of 2"):
        xy = find_centres(gaussian_images(truth), method="2dg", box_size=9)
    np.testing.assert_allclose(xy, truth, atol=0.05)     # the centre of mass took over


def test_centroid_bad_input():
    with pytest.raises(KpifsError, match="entirely NaN"):
        find_centres(np.full((2, 8, 8), np.nan))
    with pytest.raises(KpifsError, match="unknown centroid method"):
        find_centres(np.ones((8, 8)), method="median")


def test_fill_bad_pixels_interpolates():
    img = gaussian_images([[10.0, 10.0]], shape=(21, 21), sigma=3.0)
    truth = img.copy()
    img[0, 10, 11] = np.nan
    img[0, 13, 14] = np.nan
    fill_bad_pixels(img)
    assert np.all(np.isfinite(img))
    # next to the peak a weighted mean of neighbours is biased low; on the slope it is close
    assert img[0, 10, 11] == pytest.approx(truth[0, 10, 11], rel=0.15)
    assert img[0, 13, 14] == pytest.approx(truth[0, 13, 14], rel=0.05)


def test_cut_out_and_windows():
    imgs = np.arange(2 * 10 * 10, dtype=float).reshape(2, 10, 10)
    cut, delta = cut_out(imgs, np.array([[4.3, 5.0], [1.0, 1.0]]), 4)
    assert cut[0, 2, 2] == imgs[0, 5, 4]
    assert cut[1, 0, 0] == 0 and cut[1, 2, 2] == imgs[1, 1, 1]   # outside the image: 0
    np.testing.assert_allclose(delta, [[0.3, 0.0], [0.0, 0.0]], atol=1e-12)
    w = ExtractionWindow(4, 2.0).weights(delta)
    assert w.shape == (2, 4, 4)
    assert w[1, 2, 2] == 1.0 and w[0, 2, 2] < 1.0


def test_extraction_window_checks_and_header_round_trip():
    from astropy.io import fits
    from kpifs import KpifsError
    with pytest.raises(KpifsError, match="radius"):
        ExtractionWindow(40, -3)
    with pytest.raises(KpifsError, match="too small"):
        ExtractionWindow(2, 1.0)
    with pytest.raises(KpifsError, match="larger than the 32x32 image"):
        ExtractionWindow.default((32, 32), size=40)
    win = ExtractionWindow.default((201, 201), radius=20.5, order=6)
    assert (win.size, win.radius, win.order) == (64, 20.5, 6.0)
    hdr = win.to_header(fits.Header())
    assert "[pix]" in hdr.comments["WINRAD"]
    assert ExtractionWindow.from_header(hdr) == win
    assert ExtractionWindow.from_header(fits.Header()) is None
    # the attenuation at the radius is 1/e, for any pixel scale
    assert float(win.at(20.5 * 16.2, 16.2)) == pytest.approx(np.exp(-1))
