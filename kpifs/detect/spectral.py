"""Spectral models of a companion's contrast: the subspace test between NP and B.

The seed paper's two multi-channel tests are the extremes of one family. The
matched filter (NP) knows the companion's spectrum shape; the binary test (B)
fits one free contrast per channel and pays for ``q`` degrees of freedom. A
companion's contrast spectrum is smooth over an IFS band (or lies close to a
family of physical shapes), so it is well described by ``c = A beta`` with a
basis ``A`` of ``r << q`` columns. The generalised likelihood ratio over the
position and ``beta`` is, with ``z_i = s_i^T y_i / ||s_i||`` and ``n_i =
||s_i||`` at a position,

.. math:: T_S = g^T A (A^T N A)^{-1} A^T g = \\|U^T z\\|^2,
          \\qquad g_i = n_i z_i,\\; N = {\\rm diag}(n_i^2),

``U = D A (A^T D^2 A)^{-1/2}`` (``D = diag(n_i)``) having orthonormal columns:
``T_S`` is ``chi2_r`` at a known position when the channels are independent.
``r = 1`` with ``A = a`` is the matched filter's square; ``r = q`` is the
unconstrained GLR (B without its positivity). Over a grid its law comes from
the same Monte-Carlo and sign-flip draws as B's
(`~kpifs.detect.null.NullCalibration`), channel correlations included.

Bases: `smooth_basis` (Legendre polynomials in wavelength, the default of
rank `DEFAULT_RANK`), `blackbody_contrasts` (a physical family: contrast
ratios of blackbodies), `read_spectra` (the user's own spectra) and
`template_basis` (the leading singular vectors of a bank of spectra).
"""
import logging
from pathlib import Path

import numpy as np
from astropy import units as u

from .._utils import to_quantity
from ..exceptions import KpifsError
from ._laws import lhs_normal, order_quantile

__all__ = ["spectrum_shape", "DEFAULT_RANK", "smooth_basis", "blackbody_contrasts",
           "template_basis",
           "read_spectra", "subspace_weights", "subspace_sign", "subspace_spectrum",
           "spectral_basis",
           "limit_subspace", "parse_spectrum"]

log = logging.getLogger(__name__)

#: Rank of the default smooth basis (a quadratic in wavelength): measured on CHARIS
#: simulations with blackbody and T-dwarf-like companion spectra (docs: choosing a test).
DEFAULT_RANK = 3


def spectrum_shape(spectrum, n_channels):
    """Per-channel relative contrasts normalised to mean 1 (``None``: flat).

    Examples
    --------
    >>> from kpifs.detect.spectral import spectrum_shape
    >>> spectrum_shape([2, 1, 0], 3)
    array([2., 1., 0.])
    """
    if spectrum is None or (isinstance(spectrum, str) and spectrum == "flat"):
        return np.ones(n_channels)
    a = np.asarray(spectrum, float).ravel()
    if a.size != n_channels:
        raise KpifsError(f"the spectrum has {a.size} values for {n_channels} channels")
    if not np.all(np.isfinite(a)) or np.any(a < 0) or a.sum() <= 0:
        raise KpifsError("the spectrum must be finite, non-negative and not all zero")
    return a / a.mean()


def _orthonormal(a):
    q, r = np.linalg.qr(np.asarray(a, float))
    keep = np.abs(np.diag(r)) > 1e-10 * np.max(np.abs(np.diag(r)))
    return q[:, keep]


def smooth_basis(wavelengths, rank=DEFAULT_RANK):
    """Orthonormal basis (q, r) of contrast spectra polynomial in wavelength (degree r - 1).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.detect.spectral import smooth_basis
    >>> a = smooth_basis(np.linspace(1.16, 2.37, 22) * u.um, 3)
    >>> a.shape, bool(np.allclose(a.T @ a, np.eye(3)))
    ((22, 3), True)
    """
    lam = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths").value)
    q = len(lam)
    try:
        r = int(rank)
    except (TypeError, ValueError):
        raise KpifsError(f"spectral rank must be a whole number, got {rank!r}") from None
    if r < 1:
        raise KpifsError(f"spectral rank must be at least 1, got {r}")
    r = min(r, q)
    span = lam.max() - lam.min()
    x = np.zeros(q) if span == 0 else 2 * (lam - lam.min()) / span - 1
    return _orthonormal(np.polynomial.legendre.legvander(x, r - 1))


def blackbody_contrasts(wavelengths, temperatures, *, star_temperature=5800 * u.K):
    """Contrast spectra of blackbody companions against a blackbody star, (q, n_temp).

    Each column is ``B_lambda(T_c) / B_lambda(T_star)`` normalised to mean 1: a
    physical family of shapes (e.g. 600-3000 K companions of a Sun-like star).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.detect.spectral import blackbody_contrasts
    >>> c = blackbody_contrasts([1.2, 1.6, 2.2] * u.um, [1000, 3000] * u.K)
    >>> c.shape, bool(c[2, 0] > c[0, 0])           # a cool companion is redder
    ((3, 2), True)
    """
    lam = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths").to_value(u.m))
    temps = np.atleast_1d(u.Quantity(temperatures, u.K).value)
    ts = u.Quantity(star_temperature, u.K).value
    if np.any(temps <= 0) or ts <= 0:
        raise KpifsError("temperatures must be positive")
    hc_k = 6.62607015e-34 * 2.99792458e8 / 1.380649e-23
    # ratio of Planck functions: the lambda^-5 factors cancel
    with np.errstate(over="ignore"):
        ratio = np.expm1(hc_k / (lam[:, None] * ts)) / np.expm1(hc_k / (lam[:, None] * temps))
    return ratio / ratio.mean(axis=0)


def template_basis(spectra, rank=None, *, fraction=0.999):
    """Orthonormal basis (q, r) spanning a bank of spectra (q, n) to *fraction* of its energy.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.detect.spectral import blackbody_contrasts, template_basis
    >>> bank = blackbody_contrasts(np.linspace(1.16, 2.37, 22) * u.um,
    ...                            np.linspace(600, 3000, 25) * u.K)
    >>> template_basis(bank).shape[1] <= 4
    True
    """
    s = np.asarray(spectra, float)
    if s.ndim == 1:
        s = s[:, None]
    if not np.all(np.isfinite(s)):
        raise KpifsError("template spectra must be finite")
    s = s / np.linalg.norm(s, axis=0)
    uu, sv, _ = np.linalg.svd(s, full_matrices=False)
    if rank is None:
        cum = np.cumsum(sv ** 2) / np.sum(sv ** 2)
        rank = int(np.searchsorted(cum, fraction) + 1)
    return uu[:, :max(1, min(int(rank), len(sv)))]


def read_spectra(path, wavelengths):
    """Contrast spectra from a file, interpolated at *wavelengths*: (q, n).

    ECSV (or any table astropy reads) with a ``wavelength`` column (a unit, or
    µm) and one column per spectrum; or a FITS image whose first axis runs
    over the data's channels.

    Examples
    --------
    >>> import tempfile, os, numpy as np, astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.detect.spectral import read_spectra
    >>> tmp = tempfile.TemporaryDirectory()
    >>> path = os.path.join(tmp.name, "s.ecsv")
    >>> QTable({"wavelength": [1.0, 2.5] * u.um, "flat": [1.0, 1.0]}).write(path)
    >>> read_spectra(path, [1.2, 1.6] * u.um).ravel().tolist()
    [1.0, 1.0]
    >>> tmp.cleanup()
    """
    lam = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths").value)
    p = Path(path)
    if not p.is_file():
        raise KpifsError(f"{path}: spectrum file not found")
    if p.suffix.lower() in (".fits", ".fit", ".fts"):
        from astropy.io import fits
        data = np.asarray(fits.getdata(p), float)
        data = data.reshape(len(data), -1) if data.ndim > 1 else data[:, None]
        if len(data) != len(lam):
            raise KpifsError(f"{path}: {len(data)} spectral values for {len(lam)} channels")
        return data
    from astropy.table import QTable
    try:
        tab = QTable.read(p)
    except Exception as exc:
        raise KpifsError(f"{path}: cannot read a spectrum table ({exc})") from None
    if "wavelength" not in tab.colnames:
        raise KpifsError(f"{path}: no 'wavelength' column")
    wl = tab["wavelength"]
    wl = wl.to_value(u.um) if hasattr(wl, "unit") and wl.unit is not None else np.asarray(wl)
    cols = [c for c in tab.colnames if c != "wavelength"]
    if not cols:
        raise KpifsError(f"{path}: no spectrum column beside 'wavelength'")
    if lam.min() < wl.min() - 1e-9 or lam.max() > wl.max() + 1e-9:
        raise KpifsError(f"{path}: covers {wl.min():.3f}-{wl.max():.3f} um, not the data's "
                         f"{lam.min():.3f}-{lam.max():.3f} um")
    order = np.argsort(wl)
    out = np.stack([np.interp(lam, wl[order], np.asarray(tab[c], float)[order])
                    for c in cols], axis=1)
    if not np.all(np.isfinite(out)):
        raise KpifsError(f"{path}: non-finite spectrum values")
    return out


def parse_spectrum(value, n_channels=None):
    """A companion spectrum shape from 'flat'/None, a sequence, a comma list or a text file.

    Examples
    --------
    >>> from kpifs.detect.spectral import parse_spectrum
    >>> parse_spectrum("1.3,1.0,0.7", 3)
    array([1.3, 1. , 0.7])
    """
    if value is None or (isinstance(value, str) and value == "flat"):
        return None
    if isinstance(value, (str, Path)) and Path(value).is_file():
        try:
            return np.loadtxt(value, ndmin=1)
        except ValueError as exc:
            raise KpifsError(f"{value}: cannot read a spectrum: {exc}") from None
    if isinstance(value, str):
        try:
            return np.array([float(v) for v in value.split(",")])
        except ValueError:
            raise KpifsError(f"spectrum: expected 'flat', comma-separated values or a file, "
                             f"got {value!r}") from None
    return np.asarray(value, float)


def spectral_basis(spec, wavelengths):
    """The basis (q, r) a search's *spec* names: None (default smooth rank), an integer
    rank, ``'smooth:R'``, ``'blackbody'``, a file of spectra, or an array (q, r).

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.detect.spectral import spectral_basis
    >>> spectral_basis("smooth:2", [1.2, 1.6, 2.2] * u.um).shape
    (3, 2)
    """
    q = len(np.atleast_1d(wavelengths))
    if spec is None:
        return smooth_basis(wavelengths, DEFAULT_RANK)
    if isinstance(spec, (int, np.integer)):
        return smooth_basis(wavelengths, spec)
    if isinstance(spec, str):
        s = spec.strip().lower()
        if s.startswith("smooth"):
            rank = s.split(":", 1)[1] if ":" in s else DEFAULT_RANK
            return smooth_basis(wavelengths, rank)
        if s == "blackbody":
            return template_basis(blackbody_contrasts(wavelengths,
                                                      np.linspace(500, 3500, 31) * u.K))
        if s.isdigit():
            return smooth_basis(wavelengths, int(s))
        return template_basis(read_spectra(spec, wavelengths))
    a = np.asarray(spec, float)
    a = a[:, None] if a.ndim == 1 else a
    if a.shape[0] != q:
        raise KpifsError(f"spectral basis of {a.shape[0]} rows for {q} channels")
    return _orthonormal(a)


def subspace_weights(norm2, basis):
    """Per-position orthonormal weights ``U`` (r, q, ...) of the subspace statistic.

    ``T_S = sum_j (sum_i U[j, i] z_i)^2`` with ``U = D A (A^T D^2 A)^{-1/2}``
    at each position (``D = diag(||s_i||)`` from *norm2* (q, ...)).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.spectral import subspace_weights
    >>> u = subspace_weights(np.array([1.0, 4.0, 9.0])[:, None], np.ones((3, 1)))
    >>> np.round(u[0, :, 0], 4).tolist()          # the matched filter of a flat spectrum
    [0.2673, 0.5345, 0.8018]
    """
    n2 = np.asarray(norm2, float)
    q = n2.shape[0]
    flat = n2.reshape(q, -1).T                                     # (npos, q)
    a = np.asarray(basis, float)
    d = np.sqrt(np.where(np.isfinite(flat), flat, 0.0))
    da = d[:, :, None] * a[None]                                   # (npos, q, r)
    g = np.matmul(da.transpose(0, 2, 1), da)                       # (npos, r, r)
    val, vec = np.linalg.eigh(g)
    good = val > 1e-12 * np.maximum(val[:, -1:], 1e-300)
    inv = np.where(good, 1 / np.sqrt(np.where(good, val, 1.0)), 0.0)
    isq = np.matmul(vec * inv[:, None, :], vec.transpose(0, 2, 1))  # (A^T D^2 A)^{-1/2}
    w = np.matmul(da, isq)                                         # (npos, q, r)
    return np.moveaxis(w, 0, -1).transpose(1, 0, 2).reshape((a.shape[1], q) + n2.shape[1:])


def subspace_sign(weights, norm2, basis):
    """Sign vectors ``h`` (r, ...): the fitted spectrum's mean is positive where ``h`` and
    ``W^T z`` have a positive dot product.

    With ``gamma = W^T z`` the fitted coefficients are ``beta = M gamma``, ``M =
    (W^T D A)^-1``, so ``mean(A beta) > 0`` is ``h . gamma > 0`` with ``h = M^T A^T 1``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.spectral import subspace_sign, subspace_weights
    >>> n2 = np.ones((3, 1))
    >>> w = subspace_weights(n2, np.ones((3, 1)) / 3 ** 0.5)
    >>> float(subspace_sign(w, n2, np.ones((3, 1)) / 3 ** 0.5)[0, 0]) > 0
    True
    """
    a = np.asarray(basis, float)
    q, r = a.shape
    n2 = np.asarray(norm2, float)
    ww = np.asarray(weights, float).reshape(r, q, -1).transpose(2, 1, 0)     # (npos, q, r)
    da = np.sqrt(np.nan_to_num(n2.reshape(q, -1).T))[:, :, None] * a
    m = np.matmul(ww.transpose(0, 2, 1), da)                               # (npos, r, r)
    ones = np.broadcast_to(a.sum(axis=0), (len(m), r))
    h = np.zeros_like(ones)
    ok = np.abs(np.linalg.det(m)) > 0
    h[ok] = np.linalg.solve(m[ok].transpose(0, 2, 1), ones[ok][..., None])[..., 0]
    return h.T.reshape((r,) + n2.shape[1:])


def subspace_spectrum(contrast, err, basis):
    """Contrast spectrum within the basis from free per-channel contrasts and their errors.

    The weighted least-squares projection ``A (A^T S^-1 A)^-1 A^T S^-1 c`` with
    ``S = diag(err^2)``, and its 1-sigma errors. Channels with a non-finite
    contrast or error are left out.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.spectral import subspace_spectrum
    >>> c, e = subspace_spectrum([1.0, 1.2, 0.8], [0.1, 0.1, 0.1], np.ones((3, 1)) / 3 ** 0.5)
    >>> np.round(c, 3).tolist(), np.round(e, 3).tolist()
    ([1.0, 1.0, 1.0], [0.058, 0.058, 0.058])
    """
    c = np.asarray(contrast, float)
    e = np.asarray(err, float)
    a = np.asarray(basis, float)
    ok = np.isfinite(c) & np.isfinite(e) & (e > 0)
    if not np.any(ok):
        return np.full_like(c, np.nan), np.full_like(c, np.nan)
    wa = a[ok] / e[ok, None]
    cov = np.linalg.pinv(wa.T @ wa)
    beta = cov @ (wa.T @ (c[ok] / e[ok]))
    return a @ beta, np.sqrt(np.einsum("ij,jk,ik->i", a, cov, a))


def _sum_squares(e):
    """``np.sum(e ** 2, axis=-1)`` for a short last axis: the same sums in the same order
    (numpy adds fewer than 8 terms one by one), a quarter of the time."""
    if e.shape[-1] >= 8:
        return np.sum(e ** 2, axis=-1)
    out = e[..., 0] ** 2
    for j in range(1, e.shape[-1]):
        out += e[..., j] ** 2
    return out


def limit_subspace(weights, norm2, threshold, pd, *, spectrum=None, correlation=None,
                   n_draws=1024, seed=0):
    """Limit map of the subspace test: the contrast detected with probability *pd*.

    At each position the statistic of a companion of contrast ``c`` and
    spectrum shape ``a`` is ``||c m + e||^2`` with ``m_j = sum_i U_ji a_i
    ||s_i||`` and ``e = U^T z`` the projected noise: unit normal with
    independent channels, ``N(0, U^T C U)`` with the per-position channel
    correlation *correlation* (ny, nx, q, q). Each of a fixed set of Latin-
    hypercube draws crosses *threshold* at the positive root of a quadratic in
    ``c``; the limit is their *pd* quantile (exact, up to the draws).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.spectral import limit_subspace, subspace_weights
    >>> n2 = np.full((3, 1, 1), 1e6)                 # ||s_i|| = 1000 in three channels
    >>> w = subspace_weights(n2, np.ones((3, 1)) / 3 ** 0.5)
    >>> lim = limit_subspace(w, n2, 3.0902 ** 2, 0.5)  # the NP limit at P_FA 1e-3
    >>> bool(abs(lim[0, 0] * 1000 * 3 ** 0.5 - 3.0902) < 0.01)
    True
    """
    n2 = np.asarray(norm2, float)
    q, shape = n2.shape[0], n2.shape[1:]
    w = np.asarray(weights, float).reshape(len(weights), q, -1)
    r = w.shape[0]
    a = spectrum_shape(spectrum, q)
    amp = a[:, None] * np.sqrt(np.where(np.isfinite(n2), n2, 0.0).reshape(q, -1))
    m = np.einsum("jik,ik->kj", w, amp)                             # (npos, r)
    xi = lhs_normal(n_draws, r, seed)                               # (N, r)
    out = np.full(m.shape[0], np.nan)
    corr = None if correlation is None else np.asarray(correlation, float).reshape(-1, q, q)
    # only where there is a limit: a signal, and the correlation known (half the grid
    # when it is symmetric); each position's draws are its own
    todo = np.sum(m ** 2, axis=1) > 0
    if corr is not None:
        todo &= np.all(np.isfinite(corr), axis=(1, 2))
    todo = np.flatnonzero(todo)
    for s in range(0, len(todo), 512):
        at = todo[s:s + 512]
        mm = m[at]
        if corr is None:
            e = np.broadcast_to(xi, (len(mm),) + xi.shape)
        else:
            wt = w[:, :, at].transpose(2, 1, 0)                       # (n, q, r)
            cov = np.matmul(wt.transpose(0, 2, 1), np.matmul(corr[at], wt))
            val, vec = np.linalg.eigh(np.nan_to_num(cov))
            # the symmetric square root: unique, so that the fixed draws map to the same
            # noise whatever signs (or basis of a repeated eigenvalue) eigh returns
            root = np.matmul(vec * np.sqrt(np.clip(val, 0, None))[:, None, :],
                             vec.transpose(0, 2, 1))
            e = np.matmul(xi[None], root)                               # (n, N, r)
        m2 = np.sum(mm ** 2, axis=1)[:, None]
        me = np.einsum("nkj,nj->nk", e, mm)
        slack = threshold - _sum_squares(e)
        with np.errstate(invalid="ignore", divide="ignore"):
            c = (np.sqrt(me ** 2 + m2 * np.maximum(slack, 0)) - me) / m2
        c = np.where(slack <= 0, 0.0, c)
        out[at] = order_quantile(c, pd)
    return out.reshape(shape)
