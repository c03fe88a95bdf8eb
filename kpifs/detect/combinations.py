"""A companion's contrasts in channel combinations, reported per channel (issue 39).

A spectral-differential search (`kpifs.detect.sdk`, and its rotating form in
`kpifs.detect.blocks`) fits one contrast scale per channel combination: the
companion's spectrum shape ``a`` (flat by default) times that scale in every
channel. The combinations measure the same scale, so the channels' contrasts
are the inverse-variance mean of the combinations' scales times ``a``, with its
error.
"""
import numpy as np
from astropy import units as u

__all__ = ["combination_contrasts", "combination_table", "distinct_contrasts",
           "nominal_wavelengths"]


def nominal_wavelengths(mixing, wavelengths):
    """Each combination's nominal wavelength (k,): the centre of its squared weights
    *mixing* (k, q) on the channels' *wavelengths* (labels only; the signatures are
    made at the channels' own).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.detect.combinations import nominal_wavelengths
    >>> nominal_wavelengths(np.array([[1.0, -1.0], [1.0, 0.0]]), [1.6, 2.2] * u.um)
    <Quantity [1.9, 1.6] um>
    """
    mix = np.asarray(mixing, float)
    wts = mix ** 2 / np.sum(mix ** 2, axis=1, keepdims=True)
    return wts @ u.Quantity(wavelengths, u.um).value * u.um


def distinct_contrasts(contrast, spectrum, n_comb):
    """The channels' contrasts of each distinct scale in *contrast* (one per combination,
    or one for all), ``(u, q)``, and which row each of the *n_comb* combinations takes: a
    companion model computed once per distinct scale (a fit's combinations share one,
    `~kpifs.detect._blockfit.refine_stack`), not once per combination.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.combinations import distinct_contrasts
    >>> ca, at = distinct_contrasts(0.01, np.array([1.0, 0.5]), 3)
    >>> ca.tolist(), at.tolist()
    ([[0.01, 0.005]], [0, 0, 0])
    """
    c = np.broadcast_to(np.asarray(contrast, float), (n_comb,))
    scales, at = np.unique(c, return_inverse=True)
    return scales[:, None] * np.asarray(spectrum, float)[None, :], at


def _mean(c, err, axis):
    """Inverse-variance mean of *c* over *axis* and its error (NaN or non-positive errors
    carry no weight)."""
    good = np.isfinite(err) & (err > 0)
    wt = np.where(good, 1 / np.where(good, err, 1) ** 2, 0.0)
    tot = wt.sum(axis=axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sum(wt * np.nan_to_num(c), axis=axis) / tot, 1 / np.sqrt(tot)


def combination_contrasts(spectrum, c, cerr):
    """The combinations' contrast maps and errors (k, ny, nx) as the channels' (q, ny, nx):
    their inverse-variance mean times the *spectrum* shape (q,).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.combinations import combination_contrasts
    >>> c = np.array([1.0, 3.0]).reshape(2, 1, 1)
    >>> e = np.array([1.0, 1.0]).reshape(2, 1, 1)
    >>> m, s = combination_contrasts(np.array([1.0, 0.5, 2.0]), c, e)
    >>> m.ravel().tolist(), np.round(s.ravel(), 3).tolist()
    ([2.0, 1.0, 4.0], [0.707, 0.354, 1.414])
    """
    mean, err = _mean(np.asarray(c, float), np.asarray(cerr, float), 0)
    a = np.asarray(spectrum, float)[:, None, None]
    return a * mean[None], a * err[None]


def combination_table(spectrum, n_comb, cands):
    """The candidates' per-combination contrast columns from the grid's peak
    (``contrast`` and its error, *n_comb* values per row) as per-channel ones, in place:
    their weighted mean (the companion's one scale) times the *spectrum* shape, which
    is also the spectrum within the search's model (``contrast_model``). A fit's
    columns are per channel already (`~kpifs.detect._blockfit.refine_stack`); an empty
    table gets per-channel columns too.

    Examples
    --------
    >>> import numpy as np
    >>> from astropy.table import QTable
    >>> from kpifs.detect.combinations import combination_table
    >>> t = QTable({"contrast": [[1.0, 3.0]], "contrast_err": [[1.0, 1.0]]})
    >>> combination_table(np.array([1.0, 2.0, 1.0]), 2, t)
    >>> t["contrast"][0].tolist(), t["contrast_model"][0].tolist()
    ([2.0, 4.0, 2.0], [2.0, 4.0, 2.0])
    """
    a = np.asarray(spectrum, float)
    if not len(cands):
        for col in cands.colnames:
            if col.startswith(("contrast", "fit_contrast")) and cands[col].ndim == 2:
                cands[col] = np.zeros((0, len(a)))
        return
    if "contrast" not in cands.colnames or "contrast_err" not in cands.colnames:
        return
    c = np.asarray(cands["contrast"], float).reshape(len(cands), -1)
    e = np.asarray(cands["contrast_err"], float).reshape(len(cands), -1)
    if c.shape[1] != n_comb:
        return
    mean, sig = _mean(c, e, 1)
    cands["contrast"] = mean[:, None] * a[None]
    cands["contrast_err"] = sig[:, None] * a[None]
    cands["contrast_model"] = cands["contrast"].copy()
