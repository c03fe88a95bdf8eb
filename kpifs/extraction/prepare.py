"""Slice preparation: star centres, bad pixels and cut-outs (the window is
`kpifs.model.window`).

Centres are in pixel coordinates ``(x, y)`` (0-based, x along columns), the
convention of photutils. The kernel phases are insensitive to a centring
error to first order (a tilt is a pupil phase that the kernel removes), but the
window follows the centre, so a sensible centre still matters.
"""
import logging
import warnings

import numpy as np

from ..exceptions import KpifsError, KpifsWarning

__all__ = ["find_centres", "fill_bad_pixels", "cut_out", "CENTROID_METHODS"]

log = logging.getLogger(__name__)

CENTROID_METHODS = ("com", "peak", "quadratic", "2dg")


def _peak_positions(data):
    flat = data.reshape(len(data), -1)
    if np.isnan(flat).any():
        flat = np.nan_to_num(flat, nan=-np.inf)
    idx = np.argmax(flat, axis=1)
    return np.column_stack(np.unravel_index(idx, data.shape[1:])[::-1]).astype(float)


def _com_around(data, xy, box):
    """Vectorised centre of mass in a ``box x box`` square around integer positions."""
    n, ny, nx = data.shape
    h = box // 2
    ix = np.clip(np.rint(xy[:, 0]).astype(int), h, nx - 1 - h) if nx > box else \
        np.full(n, nx // 2)
    iy = np.clip(np.rint(xy[:, 1]).astype(int), h, ny - 1 - h) if ny > box else \
        np.full(n, ny // 2)
    hb = min(h, (min(nx, ny) - 1) // 2)
    off = np.arange(-hb, hb + 1)
    yy = iy[:, None, None] + off[None, :, None]
    xx = ix[:, None, None] + off[None, None, :]
    sub = np.nan_to_num(data[np.arange(n)[:, None, None], yy, xx], nan=0.0)
    sub = np.clip(sub - np.min(sub, axis=(1, 2), keepdims=True), 0, None)
    tot = sub.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = (sub * xx).sum(axis=(1, 2)) / tot
        cy = (sub * yy).sum(axis=(1, 2)) / tot
    return np.column_stack([cx, cy])


def find_centres(images, *, method="com", box_size=7):
    """Star centre of every image, ``(x, y)`` in pixels.

    Parameters
    ----------
    images : array-like, shape (..., ny, nx)
        Images (NaN allowed for bad pixels).
    method : {'com', 'peak', 'quadratic', '2dg'}
        ``'peak'``: brightest pixel. ``'com'``: centre of mass in a box around
        the brightest pixel (vectorised, the default). ``'quadratic'`` and
        ``'2dg'``: photutils' `~photutils.centroids.centroid_quadratic` and
        `~photutils.centroids.centroid_2dg` in that box (slower: one fit per
        image). A fit that fails falls back to ``'com'`` with a warning.
    box_size : int
        Size of the box around the brightest pixel (odd).

    Returns
    -------
    ndarray, shape (..., 2)

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.extraction.prepare import find_centres
    >>> y, x = np.mgrid[:32, :32]
    >>> img = np.exp(-((x - 15.3) ** 2 + (y - 16.6) ** 2) / 8)
    >>> np.round(find_centres(img, box_size=9), 1)
    array([15.3, 16.6])
    """
    images = np.asarray(images, float)
    if images.ndim < 2:
        raise KpifsError(f"find_centres needs images of at least 2 dimensions, got {images.ndim}")
    if method not in CENTROID_METHODS:
        raise KpifsError(f"unknown centroid method {method!r}: use one of {CENTROID_METHODS}")
    lead = images.shape[:-2]
    data = images.reshape((-1,) + images.shape[-2:])
    bad = ~np.isfinite(data).any(axis=(1, 2))
    if bad.any():
        raise KpifsError(f"{bad.sum()} image(s) are entirely NaN: cannot find a centre")
    box_size = int(box_size) | 1
    xy = _peak_positions(data)
    if method != "peak":
        com = _com_around(data, xy, box_size)
        if method == "com":
            xy = com
        else:
            xy = _photutils_centres(data, xy, box_size, method, fallback=com)
    failed = ~np.all(np.isfinite(xy), axis=1)
    if failed.any():
        warnings.warn(f"centring failed on {failed.sum()} image(s); using the brightest pixel",
                      KpifsWarning, stacklevel=2)
        xy[failed] = _peak_positions(data[failed])
    return xy.reshape(lead + (2,))


def _photutils_centres(data, xy, box, method, fallback):
    from photutils.centroids import centroid_2dg, centroid_quadratic, centroid_sources
    func = centroid_2dg if method == "2dg" else centroid_quadratic
    out = np.empty_like(xy)
    nfail = 0
    for i, img in enumerate(data):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                cx, cy = centroid_sources(img, xy[i, 0], xy[i, 1], box_size=box,
                                          centroid_func=func)
                out[i] = cx[0], cy[0]
            except Exception:  # photutils raises various errors on degenerate boxes
                out[i] = np.nan
        if not np.all(np.isfinite(out[i])) or np.hypot(*(out[i] - xy[i])) > box:
            out[i] = fallback[i]
            nfail += 1
    if nfail:
        warnings.warn(f"{method} centroid failed on {nfail} of {len(data)} image(s); "
                      f"used the centre of mass instead", KpifsWarning, stacklevel=3)
    return out


def fill_bad_pixels(images, *, sigma=1.0):
    """Replace NaN pixels by a Gaussian-weighted interpolation of their neighbours.

    A normalised convolution image by image (only images that have NaN are
    touched): the kernel-weighted mean of the good neighbours, what
    `astropy.convolution.interpolate_replace_nans` computes (to the last bit),
    written as two convolutions of finite images so that it neither warns nor
    touches the warnings filters (the extraction runs it on several threads).
    Pixels with no good neighbour (holes much larger than *sigma*) become 0,
    i.e. they are excluded from Fourier sums.

    Parameters
    ----------
    images : ndarray, shape (..., ny, nx)
        Modified in place and returned.
    sigma : float
        Width of the Gaussian kernel in pixels.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.extraction.prepare import fill_bad_pixels
    >>> img = np.ones((1, 9, 9)); img[0, 4, 4] = np.nan
    >>> float(fill_bad_pixels(img)[0, 4, 4])
    1.0
    """
    from astropy.convolution import Gaussian2DKernel, convolve
    kernel = Gaussian2DKernel(sigma)
    flat = images.reshape((-1,) + images.shape[-2:])
    for i in np.flatnonzero(np.isnan(flat).any(axis=(1, 2))):
        bad = np.isnan(flat[i])
        num, den = (convolve(x, kernel, boundary="extend", normalize_kernel=False)
                    for x in (np.where(bad, 0.0, flat[i]), (~bad).astype(float)))
        with np.errstate(invalid="ignore", divide="ignore"):
            flat[i][bad] = (num / den)[bad]
    np.nan_to_num(flat, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return images


def cut_out(sl, centres, ws, *, copy=True):
    """``ws x ws`` cut-outs of images ``sl`` (n, ny, nx) around their star centres.

    Each cut-out is centred on the integer pixel nearest its centre ``(x, y)``
    (that pixel lands at index ``ws // 2``). Returns the cut-outs (a new
    array; with ``copy=False`` a view of *sl* where one plain slice serves
    every image) and the sub-pixel remainders ``delta`` (centre minus that
    pixel). Pixels outside the image are 0.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.extraction.prepare import cut_out
    >>> cut, delta = cut_out(np.arange(100.).reshape(1, 10, 10), [[4.3, 5.0]], 4)
    >>> float(cut[0, 2, 2]), delta
    (54.0, array([[0.3, 0. ]]))
    """
    nb, ny, nx = sl.shape
    h = ws // 2
    ic = np.rint(centres).astype(int)
    delta = centres - ic
    lo_x, lo_y = ic[:, 0] - h, ic[:, 1] - h
    inside = (lo_x >= 0) & (lo_y >= 0) & (lo_x + ws <= nx) & (lo_y + ws <= ny)
    if inside.all() and np.all(ic == ic[0]):
        # the usual case: one window for the whole batch, a plain slice
        view = sl[:, lo_y[0]:lo_y[0] + ws, lo_x[0]:lo_x[0] + ws]
        return (view.copy() if copy else view), delta
    # one slice copy per image (faster than a gather through a padded copy)
    out = np.zeros((nb, ws, ws), dtype=sl.dtype)
    xa, xb = np.maximum(lo_x, 0), np.minimum(lo_x + ws, nx)
    ya, yb = np.maximum(lo_y, 0), np.minimum(lo_y + ws, ny)
    for i in np.flatnonzero((xa < xb) & (ya < yb)):
        out[i, ya[i] - lo_y[i]:yb[i] - lo_y[i], xa[i] - lo_x[i]:xb[i] - lo_x[i]] = \
            sl[i, ya[i]:yb[i], xa[i]:xb[i]]
    return out, delta
