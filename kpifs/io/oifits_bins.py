"""The default search of OIFITS closure phases: its field, and the spectral channels
binned to what a search over that field resolves.

**Field.** The aperture's ``0.95 lambda_min / D`` (`kpifs.io.oifits`), bounded
so that the default search handles at most `SEARCH_BUDGET` grid positions x
channels (the null's draws loop over channels, each a product over every
position): a long-baseline
array whose apertures are small against its baselines (VLTI's 1.8 m
telescopes on 130 m baselines: ``lambda / D`` is 70 resolution elements) and
whose spectrograph has a thousand channels would otherwise need hours and
gigabytes. Where the bound acts, a note says which field was searched and
what the aperture allows (``--max-sep`` searches that).

**Channels.** Data within the budget as they are keep every channel. Beyond
it, the channels are binned first: a spectrograph behind an interferometer
(GRAVITY: 1628 channels over the K band) samples its spectrum far more finely
than the closure phases of a companion anywhere in the field change. The phase of a
companion at separation ``rho`` on a baseline ``B`` turns by ``B rho dlambda
/ lambda^2`` fringes across a channel of width ``dlambda``. With
``binning='auto'`` adjacent channels are averaged while that turn, for the
longest baseline and the field's edge, stays within `BIN_SMEAR` of a fringe;
a companion inside the field then keeps at least ``1 - (pi BIN_SMEAR)^2 / 6``
(98 %) of its closure-phase signal in a bin. Channels already coarser than
that are kept as they are.

The closure phases of a bin are the circular mean of its channels, weighted
by each channel's mean ``1 / T3PHIERR^2``; its covariance is that of the
weighted mean of channels taken as independent (as the file's T3PHIERR takes
them), and its wavelength the weighted mean of theirs.
"""
import numpy as np

from ..exceptions import KpifsError

__all__ = ["search_field", "channel_bins", "bin_closure_phases", "BIN_SMEAR", "BINNING",
           "SEARCH_BUDGET"]

MAS = np.pi / 180 / 3600 / 1000

#: Largest turn of a companion's fringe across one bin, at the field's edge on the longest
#: baseline (fraction of a fringe).
BIN_SMEAR = 0.1

#: Values of the readers' *binning*.
BINNING = ("auto", "none")

#: Most grid positions x channels of the default search: each of the null's 5000 draws
#: costs several products of that size (`kpifs.detect.null`); 1.5e5 keeps a closure-phase
#: search to seconds (`benchmarks/bench_gravity.py`).
SEARCH_BUDGET = 1.5e5


def channel_bins(wl, longest, field, *, binning="auto"):
    """Bin index of each channel, or None when nothing is binned: adjacent channels (by
    wavelength) while a companion at *field* (rad) turns by at most `BIN_SMEAR` fringe
    on baseline *longest* (m) across the bin.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.io.oifits_bins import channel_bins, MAS
    >>> wl = np.linspace(2.0e-6, 2.4e-6, 1000)
    >>> b = channel_bins(wl, longest=130.0, field=50 * MAS)
    >>> int(b.max()) + 1, int(np.bincount(b).max())
    (26, 45)
    """
    if binning not in BINNING:
        raise KpifsError(f"binning must be one of {BINNING}, got {binning!r}")
    wl = np.asarray(wl, float)
    if binning == "none" or len(wl) < 2 or not field > 0:
        return None
    order = np.argsort(wl)
    out = np.empty(len(wl), int)
    k, start = 0, wl[order[0]]
    for i in order:
        # fringes turned across [start, wl]: B rho (1 / start - 1 / wl)
        if longest * field * (1 / start - 1 / wl[i]) > BIN_SMEAR:
            k, start = k + 1, wl[i]
        out[i] = k
    return None if k + 1 == len(wl) else out


def search_field(wl, longest, aperture_field, n_kp, *, binning="auto"):
    """The default search's field (rad), the channels' bins (or None) and a note (or None).

    *aperture_field* (rad) is what the aperture allows; the field is reduced until
    ``positions x channels <= SEARCH_BUDGET`` (positions: the default grid's, a quarter
    of ``lambda_min / longest`` apart). *n_kp* is kept for the caller's note.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.io.oifits_bins import search_field, MAS
    >>> wl = np.linspace(1.97e-6, 2.4e-6, 1625)
    >>> field, bins, note = search_field(wl, 130.0, 214 * MAS, 3)
    >>> round(field / MAS), int(bins.max()) + 1
    (33, 20)
    """
    wl = np.asarray(wl, float)
    res = wl.min() / longest
    field = float(aperture_field)
    if (2 * np.floor(field / (res / 4)) + 1) ** 2 * len(wl) <= SEARCH_BUDGET:
        return field, None, None                     # within the budget as they are
    bins = None
    for _ in range(60):
        bins = channel_bins(wl, longest, field, binning=binning)
        nb = len(wl) if bins is None else int(bins.max()) + 1
        side = 2 * np.floor(field / (res / 4)) + 1
        cost = side ** 2 * nb
        if cost <= SEARCH_BUDGET or field <= 2 * res:
            break
        field *= max(0.5, 0.98 * (SEARCH_BUDGET / cost) ** (1 / 3))
    note = None
    if field < aperture_field * (1 - 1e-9):
        note = (f"default search field {field / MAS:.0f} mas ({field / res:.0f} lambda / B_max; "
                f"the aperture allows {aperture_field / MAS:.0f} mas, --max-sep searches "
                f"it): bounded to {SEARCH_BUDGET:.1e} positions x channels")
    return field, bins, note


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
