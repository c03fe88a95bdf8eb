"""Spectral channels of OIFITS closure phases binned to what a companion search resolves.

A spectrograph behind an interferometer (GRAVITY: 1628 channels over the K
band) samples its spectrum far more finely than the closure phases of a
companion anywhere in the searched field change. The phase of a companion at
separation ``rho`` on a baseline ``B`` turns by ``B rho dlambda / lambda^2``
fringes across a channel of width ``dlambda``. With ``binning='auto'`` the
adjacent channels are averaged while that turn, for the longest baseline and
the edge of the default field (``0.95 lambda_min / D``, the aperture of
`kpifs.io.oifits`), stays within `BIN_SMEAR` of a fringe; a companion inside
the field then keeps at least ``1 - (pi BIN_SMEAR)^2 / 6`` (98 %) of its
closure-phase signal in a bin. Channels already coarser than that are kept as
they are.

The closure phases of a bin are the circular mean of its channels, weighted
by each channel's mean ``1 / T3PHIERR^2``; its covariance is that of the
weighted mean of channels taken as independent (as the file's T3PHIERR takes
them), and its wavelength the weighted mean of theirs.
"""
import numpy as np

from ..exceptions import KpifsError

__all__ = ["channel_bins", "bin_closure_phases", "BIN_SMEAR", "BINNING"]

#: Largest turn of a companion's fringe across one bin, at the default field's edge on
#: the longest baseline (fraction of a fringe).
BIN_SMEAR = 0.1

#: Values of the readers' *binning*.
BINNING = ("auto", "none")


def channel_bins(wl, longest, diameter, *, binning="auto"):
    """Bin index of each channel (sorted by wavelength), or None when nothing is binned.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.io.oifits_bins import channel_bins
    >>> wl = np.linspace(2.0e-6, 2.4e-6, 1000)
    >>> b = channel_bins(wl, longest=130.0, diameter=1.8)
    >>> int(b.max()) + 1, int(np.bincount(b).max())
    (118, 9)
    """
    if binning not in BINNING:
        raise KpifsError(f"binning must be one of {BINNING}, got {binning!r}")
    wl = np.asarray(wl, float)
    if binning == "none" or len(wl) < 2 or not diameter > 0:
        return None
    frac = BIN_SMEAR * diameter / (0.95 * longest)          # dlambda / lambda allowed
    order = np.argsort(wl)
    out = np.empty(len(wl), int)
    k, start = 0, wl[order[0]]
    for i in order:
        if wl[i] - start > frac * start:
            k, start = k + 1, wl[i]
        out[i] = k
    return None if k + 1 == len(wl) else out


def bin_closure_phases(phi, err, per, wl, band, bins):
    """Closure phases ``(ntri, nw)``, errors, per-channel covariance ``(nw, ntri, ntri)``,
    wavelengths and bandwidths of the channels averaged in *bins*."""
    nb = int(bins.max()) + 1
    weight = 1.0 / np.mean(err ** 2, axis=0)                         # per channel
    total = np.bincount(bins, weights=weight, minlength=nb)
    w = weight / total[bins]                                         # sums to 1 in a bin
    z = np.zeros((phi.shape[0], nb), complex)
    np.add.at(z.T, bins, (w * np.exp(1j * phi)).T)
    cov = np.zeros((nb,) + per.shape[1:])
    np.add.at(cov, bins, (w ** 2)[:, None, None] * per)
    lam = np.bincount(bins, weights=w * wl, minlength=nb)
    lo = np.full(nb, np.inf)
    hi = np.full(nb, -np.inf)
    np.minimum.at(lo, bins, wl - np.nan_to_num(band, nan=0.0) / 2)
    np.maximum.at(hi, bins, wl + np.nan_to_num(band, nan=0.0) / 2)
    return np.angle(z), np.sqrt(np.diagonal(cov, axis1=1, axis2=2)).T, cov, lam, hi - lo
