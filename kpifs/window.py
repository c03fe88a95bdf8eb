"""The extraction window: a square cut-out around the star, apodised by a super-Gaussian.

One `ExtractionWindow` describes it everywhere: extraction cuts and weights
the images with it, the kernel-phase data carry it (header cards ``WINSIZE``,
``WINRAD``, ``WINORD``), and detection uses it for the attenuation of a
companion's signal at its separation.
"""
from dataclasses import dataclass

import numpy as np

from .exceptions import KpifsError

__all__ = ["ExtractionWindow", "super_gaussian", "DEFAULT_WINDOW_RADIUS",
           "DEFAULT_MAX_WINDOW"]

#: Default super-Gaussian radius, as a fraction of the half-width of the
#: cut-out: wide enough that a companion at half the field radius keeps ~90 %
#: of its flux (w = exp(-(0.5/0.8)**4) = 0.86), narrow enough that the window
#: is ~0.1 at the cut-out's edge.
DEFAULT_WINDOW_RADIUS = 0.8

#: Largest default cut-out (pixels): the image's smaller side up to this. A
#: 64-pixel cut-out is ~1 arcsec for CHARIS and keeps each DFT matrix ~40 MB.
DEFAULT_MAX_WINDOW = 64


def super_gaussian(r, radius, order=4):
    """Super-Gaussian window ``exp(-(r / radius) ** order)``.

    Examples
    --------
    >>> from kpifs.window import super_gaussian
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
        return super_gaussian(np.hypot(dx, dy), self.radius, self.order)

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
