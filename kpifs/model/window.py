"""The extraction window: a square cut-out around the star, apodised by a super-Gaussian.

One `ExtractionWindow` describes it everywhere: extraction cuts and weights
the images with it, the kernel-phase data carry it (header cards ``WINSIZE``,
``WINRAD``, ``WINORD``), and detection uses it for the attenuation of a
companion's signal at its separation.
"""
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..exceptions import KpifsError

__all__ = ["ExtractionWindow", "super_gaussian", "DEFAULT_WINDOW_RADIUS",
           "DEFAULT_MAX_WINDOW", "WINDOW_QUANTUM"]

#: Default super-Gaussian radius, as a fraction of the half-width of the
#: cut-out: wide enough that a companion at half the field radius keeps ~90 %
#: of its flux (w = exp(-(0.5/0.8)**4) = 0.86), narrow enough that the window
#: is ~0.1 at the cut-out's edge.
DEFAULT_WINDOW_RADIUS = 0.8

#: Largest default cut-out (pixels): the image's smaller side up to this. A
#: 64-pixel cut-out is ~1 arcsec for CHARIS and keeps each DFT matrix ~40 MB.
DEFAULT_MAX_WINDOW = 64

#: Extraction computes windows at the star's sub-pixel offset rounded to this
#: fraction of a pixel (cached, with their gradients) and corrects each frame's
#: to first order (`ExtractionWindow.apply`): windows are computed once per
#: sequence and kernel phases differ from exact windows by ~1e-8 rad
#: (rounding alone, without the correction, would add up to 5e-5 rad).
WINDOW_QUANTUM = 1 / 32

#: Memory budget of the cache of quantised windows (bytes).
WINDOW_CACHE_BYTES = 64 * 2 ** 20

_window_cache = OrderedDict()
_window_lock = threading.Lock()
_window_nbytes = [0]


def super_gaussian(r, radius, order=4):
    """Super-Gaussian window ``exp(-(r / radius) ** order)``.

    Examples
    --------
    >>> from kpifs.model.window import super_gaussian
    >>> round(float(super_gaussian(10.0, 10.0)), 4)
    0.3679
    """
    return np.exp(-(np.asarray(r, float) / radius) ** order)


@dataclass(frozen=True)
class ExtractionWindow:
    """Square cut-out of *size* pixels weighted by ``exp(-(r / radius) ** order)``.

    Parameters
    ----------
    size : int
        Side of the square cut-out around the star (pixels).
    radius : float
        Super-Gaussian radius (pixels).
    order : float
        Super-Gaussian exponent (``np.inf`` would be a hard disk).

    Examples
    --------
    >>> from kpifs import ExtractionWindow
    >>> win = ExtractionWindow.default((40, 40))
    >>> win
    ExtractionWindow(size=40, radius=16.0, order=4.0)
    >>> round(float(win.at(100.0, 10.42)), 3)          # attenuation at 100 mas
    0.879
    """

    size: int
    radius: float
    order: float = 4.0

    def __post_init__(self):
        try:
            size, radius, order = int(self.size), float(self.radius), float(self.order)
        except (TypeError, ValueError):
            raise KpifsError(f"window size, radius and order must be numbers, got "
                             f"{self.size!r}, {self.radius!r}, {self.order!r}") from None
        if size != self.size or size < 4:
            raise KpifsError(f"window of {self.size} pixels is too small (at least 4)")
        if not radius > 0 or not np.isfinite(radius):
            raise KpifsError(f"window radius must be > 0, got {self.radius}")
        if not order > 0:
            raise KpifsError(f"window order must be > 0, got {self.order}")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "radius", radius)
        object.__setattr__(self, "order", order)

    @classmethod
    def default(cls, image_shape, *, size=None, radius=None, order=4.0):
        """The window kpifs uses for images of *image_shape* (ny, nx).

        *size* defaults to the image's smaller side (even), at most
        `DEFAULT_MAX_WINDOW`; *radius* to ``DEFAULT_WINDOW_RADIUS * size / 2``.
        A size larger than the image is refused.

        Examples
        --------
        >>> from kpifs import ExtractionWindow
        >>> ExtractionWindow.default((201, 201), radius=20)
        ExtractionWindow(size=64, radius=20.0, order=4.0)
        """
        ny, nx = image_shape[-2:]
        if size is None:
            size = min(ny, nx, DEFAULT_MAX_WINDOW)
            size -= size % 2
        if int(size) > min(ny, nx):
            raise KpifsError(f"window of {size} pixels is larger than the {ny}x{nx} image")
        if radius is None:
            radius = DEFAULT_WINDOW_RADIUS * int(size) / 2
        return cls(size, radius, order)

    def weights(self, delta):
        """Windows for cut-outs whose star sits at sub-pixel offsets *delta* (n, 2).

        The star's integer pixel is at index ``size // 2``. Returns shape
        (n, size, size), or (1, size, size) when every *delta* is the same.

        Examples
        --------
        >>> from kpifs import ExtractionWindow
        >>> w = ExtractionWindow(8, 3.0).weights([[0.0, 0.0]])
        >>> w.shape, float(w[0, 4, 4])
        ((1, 8, 8), 1.0)
        """
        delta = np.atleast_2d(np.asarray(delta, float))
        off = np.arange(self.size) - self.size // 2
        if np.all(delta == delta[0]):
            delta = delta[:1]          # one window serves every frame
        dy = off[None, :, None] - delta[:, 1][:, None, None]
        dx = off[None, None, :] - delta[:, 0][:, None, None]
        r2 = (dx * dx + dy * dy) / (self.radius * self.radius)
        return np.exp(-(r2 ** (self.order / 2)))

    def _weights_and_slopes(self, delta):
        """Windows at *delta* (n, 2) and their derivatives along delta_x and delta_y:
        shape (n, 3, size, size). For orders >= 2."""
        off = np.arange(self.size) - self.size // 2
        dy = off[None, :, None] - delta[:, 1][:, None, None]
        dx = off[None, None, :] - delta[:, 0][:, None, None]
        r2 = 1.0 / (self.radius * self.radius)
        s = (dx * dx + dy * dy) * r2
        p = self.order / 2
        out = np.empty((len(delta), 3, self.size, self.size))
        out[:, 0] = w = np.exp(-(s ** p))
        # dw/d(delta_x) = 2 p w s^(p-1) (x - delta_x) / radius^2, likewise along y (p >= 1)
        g = 2 * p * r2 * w * s ** (p - 1)
        out[:, 1] = g * dx
        out[:, 2] = g * dy
        return out

    def apply(self, cuts, delta, *, quantum=WINDOW_QUANTUM, out=None):
        """Multiply cut-outs *cuts* (n, size, size) by their windows, in place or into *out*.

        Windows are computed at each frame's *delta* rounded to *quantum*
        pixels and kept, with their first derivatives, in a bounded
        module-level cache; each frame's window is then the first-order
        expansion ``w(q) + (delta - q) . grad w(q)``, so a sequence of frames
        computes each window once and the result differs from the exact
        window (*quantum* None or 0) by ~``(quantum / 2)**2`` times the
        window's curvature (1e-7 relative for the default window). With
        *out* (an array of the shape of *cuts*) the products go there and
        *cuts* (a view of the images, say) is left alone; *out* is returned.

        Examples
        --------
        >>> import numpy as np
        >>> from kpifs import ExtractionWindow
        >>> win = ExtractionWindow(8, 3.0)
        >>> d = [[0.01, 0.0], [0.25, -0.49]]
        >>> out = win.apply(np.ones((2, 8, 8)), d)
        >>> bool(np.allclose(out, win.weights(d), rtol=0, atol=1e-4))
        True
        """
        delta = np.atleast_2d(np.asarray(delta, float))
        if out is None:
            out = cuts
        if not quantum or not 2 <= self.order < np.inf:
            # exact windows; so too for orders below 2 (a cusp at the centre) and a hard
            # disk (a step at the edge), where a first-order expansion is not good enough
            np.multiply(cuts, self.weights(delta), out=out)
            return out
        q = np.rint(delta / quantum).astype(np.int64)
        keys, inverse = np.unique(q, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        base = (self.size, self.radius, self.order, float(quantum))
        found = {}
        with _window_lock:
            for k in map(tuple, keys):
                w = _window_cache.get(base + k)
                if w is not None:
                    _window_cache.move_to_end(base + k)
                    found[k] = w
        missing = [k for k in map(tuple, keys) if k not in found]
        if missing:
            new = self._weights_and_slopes(np.array(missing, float) * quantum)
            with _window_lock:
                for k, w in zip(missing, new):
                    found[k] = _window_cache[base + k] = w
                    _window_nbytes[0] += w.nbytes
                while _window_nbytes[0] > WINDOW_CACHE_BYTES and len(_window_cache) > 1:
                    _window_nbytes[0] -= _window_cache.popitem(last=False)[1].nbytes
        # each frame's window is (1, ex, ey) @ (w, dw/dx, dw/dy): one small product
        windows = [found[k].reshape(3, -1) for k in map(tuple, keys)]
        coef = np.empty((len(delta), 3))
        coef[:, 0] = 1.0
        coef[:, 1:] = delta - q * quantum
        buf = np.empty(self.size * self.size)
        buf2 = buf.reshape(self.size, self.size)
        for i, j in enumerate(inverse):     # one product per image: no stack of windows
            np.dot(coef[i], windows[j], out=buf)
            np.multiply(cuts[i], buf2, out=out[i])
        return out

    def at(self, separation, pixscale):
        """The window's value at *separation* (mas) for images of *pixscale* (mas).

        A companion there keeps this fraction of its flux in the windowed image.
        """
        ps = float(getattr(pixscale, "value", pixscale))
        return super_gaussian(np.asarray(separation, float) / ps, self.radius, self.order)

    def to_header(self, header):
        """Write the window as header cards ``WINSIZE``, ``WINRAD``, ``WINORD``."""
        header["WINSIZE"] = (self.size, "[pix] side of the extraction cut-out")
        header["WINRAD"] = (self.radius, "[pix] radius of the super-Gaussian window")
        header["WINORD"] = (self.order, "exponent of the super-Gaussian window")
        return header

    @classmethod
    def from_header(cls, header):
        """The window written by `to_header`, or None when the cards are absent.

        Examples
        --------
        >>> from astropy.io import fits
        >>> from kpifs import ExtractionWindow
        >>> win = ExtractionWindow(32, 12.8)
        >>> ExtractionWindow.from_header(win.to_header(fits.Header())) == win
        True
        """
        if "WINRAD" not in header:
            return None
        size = header.get("WINSIZE")
        if size is None:    # files from before the size was recorded
            size = max(4, int(np.ceil(2 * float(header["WINRAD"]) / DEFAULT_WINDOW_RADIUS)))
        return cls(int(size), float(header["WINRAD"]), float(header.get("WINORD", 4.0)))
