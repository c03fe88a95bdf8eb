"""Detection limits at a chosen ``(P_FA, P_D)`` and converters to "n sigma" conventions.

For a companion spectrum shape ``a_i`` (normalised to mean 1, so that the limit
is the mean contrast over channels) the whitened signal at a position is
``x = c (a_i s_i)``, of norm ``c ||s_a||`` with ``||s_a||^2 = sum_i a_i^2 ||s_i||^2``:

- Neyman-Pearson: ``c_lim = (Q^-1(P_FA) - Q^-1(P_D)) / ||s_a||``;
- energy detector: ``c_lim = sqrt(lambda) / ||s_a||`` with ``lambda`` solving
  ``ncx2.sf(xi, dof, lambda) = P_D``;
- binary test: the contrast at which ``P(sum_i max(z_i, 0)^k > xi) = P_D`` with
  ``z_i ~ N(c a_i ||s_i||, 1)`` and ``xi`` the (grid-search) threshold, found by
  bisection with a fixed set of Monte-Carlo draws.

When the data carry covariance rows (calibrated with kpifs), the binary and
energy limits are computed with the channels' correlations (per-position
correlation of the ``z_i``; energy from the same noise draws as its
threshold); otherwise the channels are taken as independent. The
Neyman-Pearson limit is exact at a known position.

Limits are always quoted with their ``(P_FA, P_D)``; `pfa_to_sigma`,
`sigma_to_pfa` and `chi2_ratio_sigma` translate to the "n sigma" other tools
print.
"""
import numpy as np
from astropy import units as u
from astropy.table import QTable

from .._lazy import lazy_module
from ..exceptions import KpifsError
from .stats import check_probability, energy_threshold

optimize = lazy_module("scipy.optimize")
stats = lazy_module("scipy.stats")

__all__ = ["spectrum_shape", "limit_np", "energy_lambda", "limit_energy", "limit_binary",
           "limit_binary_correlated_forms", "limit_energy_correlated", "mirror_half_map",
           "radial_curves",
           "pfa_to_sigma", "sigma_to_pfa", "chi2_ratio_sigma"]


def spectrum_shape(spectrum, n_channels):
    """Per-channel relative contrasts normalised to mean 1 (``None``: flat).

    Examples
    --------
    >>> from kpifs.detect.limits import spectrum_shape
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


def _norm_a(norm2, a):
    return np.sqrt(np.tensordot(a ** 2, norm2, axes=(0, 0)))


def limit_np(norm2, pfa, pd, spectrum=None):
    """Neyman-Pearson limit map from the signature norms ``||s_i||^2`` (q, ny, nx).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import limit_np
    >>> round(float(limit_np(np.full((1, 1, 1), 1e6), 0.01, 0.5)[0, 0]), 6)
    0.002326
    """
    pfa = check_probability(pfa, "P_FA")
    pd = check_probability(pd, "P_D")
    a = spectrum_shape(spectrum, len(norm2))
    with np.errstate(divide="ignore"):
        return (stats.norm.isf(pfa) - stats.norm.isf(pd)) / _norm_a(norm2, a)


def energy_lambda(pfa, pd, dof):
    """Non-centrality ``lambda`` with ``ncx2.sf(chi2.isf(P_FA, dof), dof, lambda) = P_D``.

    Examples
    --------
    >>> from kpifs.detect.limits import energy_lambda
    >>> round(float(energy_lambda(0.01, 0.5, 303) ** 0.5), 3)
    7.807
    """
    pfa = check_probability(pfa, "P_FA")
    pd = check_probability(pd, "P_D")
    xi = energy_threshold(pfa, dof)
    if stats.chi2.sf(xi, dof) >= pd:
        return 0.0
    hi = 1.0
    while stats.ncx2.sf(xi, dof, hi) < pd:
        hi *= 2
    return optimize.brentq(lambda lam: stats.ncx2.sf(xi, dof, lam) - pd, 0, hi, xtol=1e-10)


def limit_energy(norm2, pfa, pd, dof, spectrum=None):
    """Energy-detector limit map (``dof`` = total whitened dimension).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import limit_energy
    >>> round(float(limit_energy(np.ones((1, 1, 1)), 0.01, 0.5, 303)[0, 0]), 3)
    7.807
    """
    a = spectrum_shape(spectrum, len(norm2))
    with np.errstate(divide="ignore"):
        return np.sqrt(energy_lambda(pfa, pd, dof)) / _norm_a(norm2, a)


def limit_binary(norm2, threshold, pd, *, form="B", spectrum=None, n_draws=4096, seed=0,
                 correlation=None):
    """Binary-test limit map for a detection *threshold* on the (local) statistic.

    Solves ``P(T_B > threshold) = P_D`` for the contrast at every position by
    bisection. Up to 8 channels ``P_D`` comes from one fixed set of
    scrambled-Sobol normal draws (common random numbers make the limit a smooth
    function of position; quasi-random draws make ``P_D`` accurate to ~1e-3);
    with more channels the statistic, a sum of many independent terms, is
    taken as Gaussian with its exact mean and variance (truncated-normal
    moments of ``max(z_i, 0)``). With *correlation* (an array (ny, nx, q, q),
    the covariance of the ``z_i`` at each position, e.g. from the covariance
    rows), the draws are correlated accordingly at every position.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import limit_binary
    >>> round(float(limit_binary(np.ones((1, 1, 1)), 2.3263 ** 2, 0.5)[0, 0]), 2)
    2.33
    """
    pd = check_probability(pd, "P_D")
    a = spectrum_shape(spectrum, len(norm2))
    q = len(norm2)
    shape = norm2.shape[1:]
    m = (a[:, None] * np.sqrt(norm2.reshape(q, -1))).T           # (npos, q) signal per unit c
    power = 2 if form == "B" else 1
    if correlation is not None:
        return _limit_binary_correlated(m, correlation.reshape(-1, q, q), [threshold], pd,
                                        [power], n_draws, seed)[0].reshape(shape)
    if q > 8:
        def pdet(c, idx):
            mean, var = _clipped_moments(c[:, None] * m[idx], power)
            return stats.norm.sf((threshold - mean.sum(1)) / np.sqrt(var.sum(1)))
    else:
        z = _qmc_normal(n_draws, q, seed)

        def pdet(c, idx):
            out = np.empty(len(c))
            for s in range(0, len(c), 256):
                mu = c[s:s + 256, None] * m[idx[s:s + 256]]           # (n, q)
                t = np.sum(np.clip(z[None] + mu[:, None, :], 0, None) ** power, axis=2)
                out[s:s + 256] = np.mean(t > threshold, axis=1)
            return out

    total = m.sum(axis=1)
    ok = np.all(np.isfinite(m), axis=1) & (total > 0)
    hi = np.where(ok, (np.sqrt(threshold) + 6) / np.where(ok, total / np.sqrt(q), 1), np.nan)
    return _bisect(pdet, pd, hi).reshape(shape)


def _qmc_normal(n, d, seed):
    from scipy.stats import qmc
    n_pow2 = 1 << int(np.ceil(np.log2(max(n, 2))))
    u01 = qmc.Sobol(d=d, scramble=True, seed=seed).random(n_pow2)
    return stats.norm.ppf(np.clip(u01, 1e-12, 1 - 1e-12))


def _bisect(pdet, pd, hi, n_iter=40, rtol=1e-3):
    """Smallest c with pdet(c, idx) >= pd, for every position at once.

    A bracketing root finder on ``pdet(c) - pd`` (monotone in c): a regula-falsi
    step while the bracket's ends alternate, a bisection step when the same end
    has moved twice in a row (the safeguard of Illinois-type methods, needed
    here also because ``pdet`` from a finite set of draws is a fine staircase).
    On the smooth curves common random numbers give, each position needs about
    half the evaluations of a plain bisection. Positions stop as soon as their
    bracket is within *rtol*.
    """
    ok = np.isfinite(hi) & (hi > 0)
    n = len(hi)
    lo = np.zeros(n)
    hi = np.where(ok, hi, np.nan)
    f_lo = np.full(n, -pd)                 # bounds on pdet - pd at the ends
    f_hi = np.full(n, 1.0 - pd)
    last = np.zeros(n, int)                # end moved by the previous step: +1 hi, -1 lo
    again = np.ones(n, bool)               # the same end moved twice: bisect
    active = np.flatnonzero(ok)
    for _ in range(n_iter):
        if not len(active):
            break
        a, b, fa, fb = lo[active], hi[active], f_lo[active], f_hi[active]
        denom = fb - fa
        falsi = b - fb * (b - a) / np.where(denom > 0, denom, 1.0)
        c = np.where(again[active] | (denom <= 0), 0.5 * (a + b),
                     np.clip(falsi, a + 0.05 * (b - a), b - 0.05 * (b - a)))
        fc = pdet(c, active) - pd
        up = fc >= 0
        moved = np.where(up, 1, -1)
        again[active] = moved == last[active]
        last[active] = moved
        hi[active] = np.where(up, c, b)
        f_hi[active] = np.where(up, fc, fb)
        lo[active] = np.where(up, a, c)
        f_lo[active] = np.where(up, fa, fc)
        done = hi[active] - lo[active] <= rtol * hi[active]
        active = active[~done]
    out = np.full(n, np.nan)
    out[ok] = 0.5 * (lo[ok] + hi[ok])
    return out


def limit_binary_correlated_forms(norm2, thresholds, pd, *, spectrum=None, n_draws=4096,
                                  seed=0, correlation):
    """`limit_binary` with *correlation* for several forms at once: ``{form: map}``.

    *thresholds* maps each form ('B', 'B-paper') to its threshold; the correlated
    draws of every position are built once and serve all forms.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import limit_binary_correlated_forms
    >>> lim = limit_binary_correlated_forms(np.ones((1, 1, 1)), {"B": 2.3263 ** 2}, 0.5,
    ...                                     correlation=np.ones((1, 1, 1, 1)))
    >>> round(float(lim["B"][0, 0]), 2)
    2.33
    """
    pd = check_probability(pd, "P_D")
    a = spectrum_shape(spectrum, len(norm2))
    q = len(norm2)
    shape = norm2.shape[1:]
    m = (a[:, None] * np.sqrt(norm2.reshape(q, -1))).T
    forms = list(thresholds)
    maps = _limit_binary_correlated(m, np.asarray(correlation).reshape(-1, q, q),
                                    [thresholds[f] for f in forms], pd,
                                    [2 if f == "B" else 1 for f in forms], n_draws, seed)
    return {f: v.reshape(shape) for f, v in zip(forms, maps)}


def _limit_binary_correlated(m, corr, thresholds, pd, powers, n_draws, seed):
    """Binary limits with channel correlations: z = L eps at each position.

    Positions are taken in chunks; each chunk's correlated draws are built once
    and reused by every step of the root finding, for every (threshold, power).
    """
    npos, q = m.shape
    eps = _qmc_normal(min(n_draws, 1024), q, seed)                      # (N, q)
    good = np.all(np.isfinite(corr.reshape(npos, -1)), axis=1) & np.all(np.isfinite(m), axis=1)
    outs = [np.full(npos, np.nan) for _ in thresholds]
    total = np.where(good, m.sum(axis=1), np.nan)
    jitter = 1e-9 * np.eye(q)
    todo = np.flatnonzero(good)
    for a in range(0, len(todo), 128):
        sl = todo[a:a + 128]
        # single precision: P_D from ~1e3 draws does not need more
        z = np.einsum("kij,nj->kni", np.linalg.cholesky(corr[sl] + jitter),
                      eps).astype(np.float32)
        msl = m[sl].astype(np.float32)

        for out, threshold, power in zip(outs, thresholds, powers):
            def pdet(c, idx, z=z, msl=msl, threshold=threshold, power=power):
                t = z[idx] + (c.astype(np.float32)[:, None] * msl[idx])[:, None, :]
                np.maximum(t, 0, out=t)
                if power == 2:
                    t *= t
                return np.mean(t.sum(axis=2) > threshold, axis=1)

            tot = np.where(total[sl] > 0, total[sl], np.nan)
            hi = (np.sqrt(threshold) * np.sqrt(q) + 6 * q) / tot
            out[sl] = _bisect(pdet, pd, hi)
    return outs


def limit_energy_correlated(signal_proj, signal_norm2, noise_energy, threshold, pd):
    """Energy-detector limit when the noise has channel correlations.

    With noise draws ``n = a R_w`` (``a`` standard normal), ``T_E(c) = ||n||^2 +
    2 c n.x + c^2 ||x||^2`` for the unit-contrast signal ``x``: *noise_energy*
    holds ``||n||^2`` per draw (N,), *signal_proj* ``n.x`` per draw and position
    (N, npos), *signal_norm2* ``||x||^2`` per position; *threshold* is the
    energy threshold from the same draws.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import limit_energy_correlated
    >>> noise = np.random.default_rng(0).standard_normal((20000, 30))
    >>> energy = np.sum(noise ** 2, axis=1)
    >>> x = np.eye(30)[:, :1]                       # one unit-norm signal direction
    >>> lim = limit_energy_correlated(noise @ x, np.ones(1), energy,
    ...                               np.quantile(energy, 0.99), 0.5)
    >>> bool(abs(lim[0] - 4.66) < 0.2)             # sqrt(lambda) of ncx2 with 30 dof
    True
    """
    pd = check_probability(pd, "P_D")

    proj32 = np.asarray(signal_proj, np.float32)
    # T_E(c) > thr  <=>  2 c n.x > thr - ||n||^2 - c^2 ||x||^2: one (N, npos) product a call
    slack = (threshold - np.asarray(noise_energy, float)).astype(np.float32)[:, None]

    def pdet(c, idx):
        c32 = c.astype(np.float32)
        t = proj32[:, idx] * (2 * c32)[None, :]
        t += (c32 ** 2 * signal_norm2[idx].astype(np.float32))[None, :]
        return np.mean(t > slack, axis=0)

    hi = 2 * (np.sqrt(threshold) + 10) / np.sqrt(np.where(signal_norm2 > 0, signal_norm2,
                                                          np.nan))
    return _bisect(pdet, pd, hi)


def _clipped_moments(mu, power):
    """Mean and variance of ``max(z, 0) ** power`` for ``z ~ N(mu, 1)`` (power 1 or 2)."""
    cdf, pdf = stats.norm.cdf(mu), stats.norm.pdf(mu)
    m1 = mu * cdf + pdf
    m2 = (mu ** 2 + 1) * cdf + mu * pdf
    if power == 1:
        return m1, m2 - m1 ** 2
    m4 = (mu ** 4 + 6 * mu ** 2 + 3) * cdf + (mu ** 3 + 5 * mu) * pdf
    return m2, m4 - m2 ** 2


def mirror_half_map(values):
    """A limit map known on half a symmetric grid (NaN on the other half), completed.

    The signature at ``-pos`` is minus that at ``pos`` and the noise's law is
    symmetric, so the limit at ``-pos`` is that at ``pos``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import mirror_half_map
    >>> mirror_half_map(np.array([[np.nan, np.nan], [1.0, 2.0]])).tolist()
    [[2.0, 1.0], [1.0, 2.0]]
    """
    values = np.asarray(values, float)
    return np.where(np.isnan(values), values[::-1, ::-1], values)


def radial_curves(limits, grid, *, bin_width=None):
    """Radial contrast curves: min, median and max over azimuth of each limit map.

    Parameters
    ----------
    limits : dict
        ``{test name: map (ny, nx)}``.
    grid : `~kpifs.data.DetectionGrid`
    bin_width : float, optional
        Width of separation bins in mas (default: the grid step).

    Returns
    -------
    `~astropy.table.QTable`
        ``separation`` (mas) and, per test, ``<test>_min``, ``<test>_median``,
        ``<test>_max``.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect.limits import radial_curves
    >>> g = DetectionGrid.from_separation(50 * u.mas, 10 * u.mas)
    >>> tab = radial_curves({"NP": g.sep * 1e-5}, g)
    >>> tab.colnames
    ['separation', 'NP_min', 'NP_median', 'NP_max']
    """
    step = bin_width or abs(grid.step[0])
    sep = grid.sep[grid.valid]
    edges = np.arange(np.floor(sep.min() / step) * step, sep.max() + step, step)
    which = np.digitize(sep, edges) - 1
    used = np.unique(which)
    tab = QTable()
    tab["separation"] = np.array([sep[which == k].mean() for k in used]) * u.mas
    for name, lim in limits.items():
        vals = lim[grid.valid]
        for stat, fn in (("min", np.nanmin), ("median", np.nanmedian), ("max", np.nanmax)):
            col = []
            for k in used:
                v = vals[which == k]
                col.append(fn(v) if np.any(np.isfinite(v)) else np.nan)
            tab[f"{name}_{stat}"] = np.array(col)
    return tab


def pfa_to_sigma(pfa):
    """One-sided Gaussian "n sigma" of a false-alarm probability: ``Q^-1(P_FA)``.

    Examples
    --------
    >>> from kpifs.detect.limits import pfa_to_sigma
    >>> round(float(pfa_to_sigma(2.8665e-7)), 3)
    5.0
    """
    return stats.norm.isf(pfa)


def sigma_to_pfa(n_sigma):
    """False-alarm probability of a one-sided Gaussian "n sigma": ``Q(n)``.

    Examples
    --------
    >>> from kpifs.detect.limits import sigma_to_pfa
    >>> float(f"{sigma_to_pfa(5):.4e}")
    2.8665e-07
    """
    return stats.norm.sf(n_sigma)


def chi2_ratio_sigma(chi2r_test, chi2r_true, ndof):
    """The "n sigma" of the chi2-ratio convention used by interferometry tools.

    ``n sigma = sqrt(chi2_1.ppf(chi2_ndof.cdf(ndof * chi2r_test / chi2r_true)))``:
    the reduced chi2 of the null model (*chi2r_test*) against that of the best
    fit (*chi2r_true*) is turned into a probability with ``ndof`` degrees of
    freedom and then into the Gaussian sigma with the same two-sided
    probability. It is an energy-detector significance: with 303 kernel
    phases its "3 sigma" needs a signal of norm about 8.5, while the
    Neyman-Pearson "3 sigma" needs 3. Values saturate near 8 sigma in double
    precision.

    Examples
    --------
    >>> from kpifs.detect.limits import chi2_ratio_sigma
    >>> round(float(chi2_ratio_sigma(1 + 8.54 ** 2 / 303, 1.0, 303)), 1)
    3.0
    """
    p = stats.chi2.cdf(ndof * np.asarray(chi2r_test, float) / chi2r_true, ndof)
    return np.sqrt(stats.chi2.ppf(p, 1))
