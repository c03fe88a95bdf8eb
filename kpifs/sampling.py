"""Which channels the detector samples too coarsely for their uv points.

A pixelated image's Fourier transform is the true one plus copies shifted by
multiples of ``1 / p`` (``p`` the pixel scale). The true transform, the optical
transfer function, reaches ``D / lam`` (``D`` the pupil's extent), so a uv
point ``b / lam`` is free of the copies only while it lies farther than ``D /
lam`` from every shifted origin ``(k, l) / p``. Dropping uv points beyond the
Nyquist limit ``1 / (2 p)`` (`kpifs.kernel.nyquist_usable`) is not enough when
``p > lam / (2 D)``: the points between ``lam / p - D`` and the Nyquist limit
then carry a piece of the star's aliased transfer function, which the binary
model does not contain. A companion's kernel phases there are biased (its
fitted contrast in those channels is not to be trusted), while the star's
aliased part varies with the aberrations like any residual and is measured by
the frames' covariance (the search stays honest).

`aliased_uv` marks those points, `aliased_channels` gives each channel's
share of them; detection flags the channels where the share is not zero
(`kpifs.detect.detect`'s ``aliased`` option).
"""
import numpy as np
from astropy import units as u
from scipy.spatial.distance import pdist

from ._utils import to_quantity

__all__ = ["aliased_uv", "aliased_channels", "pupil_extent"]

MAS = np.pi / 180 / 3600 / 1000


def pupil_extent(pupil):
    """The extent ``D`` of a discrete pupil: its longest baseline plus one cell.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import make_pupil
    >>> from kpifs.sampling import pupil_extent
    >>> round(float(pupil_extent(make_pupil("subaru", step=0.5 * u.m)).value), 1)
    8.6
    """
    xy = np.asarray(u.Quantity(pupil.xy, u.m).value, float)
    d = float(pdist(xy).max()) if len(xy) > 1 else 0.0
    step = 0.0 if pupil.step is None else float(pupil.step.to_value(u.m))
    return (d + step) * u.m


def aliased_uv(uv, wavelengths, pixscale, *, diameter):
    """Which uv points see a copy of the transfer function at each wavelength.

    Parameters
    ----------
    uv : `~astropy.units.Quantity`, shape (nuv, 2)
        Baselines (m).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
    diameter : `~astropy.units.Quantity`
        Extent of the pupil (the transfer function's reach times the wavelength).

    Returns
    -------
    ndarray of bool, shape (nwave, nuv)

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.sampling import aliased_uv
    >>> aliased_uv([[7.0, 0.0], [3.0, 0.0]] * u.m, [1.16, 1.6] * u.um, 16.2 * u.mas,
    ...            diameter=8.2 * u.m)
    array([[ True, False],
           [False, False]])
    """
    f = to_quantity(uv, u.m, name="uv").value
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
    g = 1.0 / (to_quantity(pixscale, u.mas, name="pixel scale").value * MAS)
    d = to_quantity(diameter, u.m, name="diameter").value
    out = np.zeros((len(wl), len(f)), bool)
    for i, lam in enumerate(wl):
        fx, fy = f[:, 0] / lam, f[:, 1] / lam
        for k in (-1, 0, 1):
            for m in (-1, 0, 1):
                if k or m:
                    out[i] |= np.hypot(fx - k * g, fy - m * g) < d / lam
    return out


def aliased_channels(kernel_model, wavelengths, pixscale):
    """Fraction of the model's uv points, per channel, that the sampling aliases.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.sampling import aliased_channels
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.5 * u.m))
    >>> frac = aliased_channels(km, [1.16, 1.6] * u.um, 16.2 * u.mas)
    >>> bool(frac[0] > 0), float(frac[1])
    (True, 0.0)
    """
    if kernel_model.pupil is None or len(kernel_model.pupil.xy) < 2:
        return np.zeros(len(np.atleast_1d(wavelengths)))
    hit = aliased_uv(kernel_model.uv, wavelengths, pixscale,
                     diameter=pupil_extent(kernel_model.pupil))
    return hit.mean(axis=1)
