"""Detection limits at a chosen ``(P_FA, P_D)`` and converters to "n sigma" conventions.

For a companion spectrum shape ``a_i`` (normalised to mean 1, so that the limit
is the mean contrast over channels) the whitened signal at a position is
``x = c (a_i s_i)``, of norm ``c ||s_a||`` with ``||s_a||^2 = sum_i a_i^2 ||s_i||^2``:

- Neyman-Pearson: ``c_lim = (Q^-1(P_FA) - Q^-1(P_D)) / ||s_a||``;
- energy detector: ``c_lim = sqrt(lambda) / ||s_a||`` with ``lambda`` solving
  ``ncx2.sf(xi, dof, lambda) = P_D``;
- binary test: the contrast at which ``P(sum_i max(z_i, 0)^k > xi) = P_D`` with
  ``z_i ~ N(c a_i ||s_i||, 1)`` and ``xi`` the (grid-search) threshold: each of a
  fixed set of Latin-hypercube draws is solved for the contrast at which it
  crosses ``xi``, and the limit is their ``P_D`` quantile.

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
from .._utils import thread_map

from ._elementwise import crossing_sums, newton_crossings
from ._laws import chi2_cdf, chi2_ppf, chi2_sf, lhs_normal, norm_isf, norm_sf, order_quantile
from .spectral import spectrum_shape
from .stats import check_probability, energy_threshold

special = lazy_module("scipy.special")

__all__ = ["limit_np", "energy_lambda", "limit_energy", "limit_binary",
           "limit_binary_correlated_forms", "limit_energy_correlated", "energy_crossing_limits",
           "mirror_half_map",
           "radial_curves",
           "pfa_to_sigma", "sigma_to_pfa", "chi2_ratio_sigma"]


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
        return (norm_isf(pfa) - norm_isf(pd)) / _norm_a(norm2, a)


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
    if chi2_sf(xi, dof) >= pd:
        return 0.0
    return float(special.chndtrinc(xi, dof, 1 - pd))      # the inverse of chndtr in lambda


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

    Solves ``P(T_B > threshold) = P_D`` for the contrast at every position. Up
    to 8 channels ``P_D`` comes from one fixed set of Latin-hypercube normal
    draws (common random numbers make the limit a smooth function of position),
    each solved exactly for the contrast at which it crosses the threshold: the
    limit is their ``P_D`` quantile, within 0.4 % (rms) of that of 65 536 draws;
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
    if correlation is None and q > 8:
        good = np.all(np.isfinite(m), axis=1) & (m.sum(axis=1) > 0)
        out = np.full(len(m), np.nan)
        out[good] = _moment_guess(m[good], np.ones((good.sum(), q)), threshold, power, pd)
        return out.reshape(shape)
    corr = None if correlation is None else correlation.reshape(-1, q, q)
    return _limit_binary_draws(m, corr, [threshold], pd, [power], n_draws,
                               seed)[0].reshape(shape)


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
    maps = _limit_binary_draws(m, np.asarray(correlation).reshape(-1, q, q),
                               [thresholds[f] for f in forms], pd,
                               [2 if f == "B" else 1 for f in forms], n_draws, seed)
    return {f: v.reshape(shape) for f, v in zip(forms, maps)}


def _limit_binary_draws(m, corr, thresholds, pd, powers, n_draws, seed):
    """Binary limits from draws of the ``z_i``: independent (*corr* None, *n_draws*
    draws) or correlated, ``z = L eps`` at each position (*corr* (npos, q, q), at
    most 1024 draws).

    Positions are taken in blocks, side by side on the cores; each block's draws
    serve every (threshold, power) through their crossing contrasts (`_crossings`).
    """
    npos, q = m.shape
    n = n_draws if corr is None else min(n_draws, 1024)
    eps = lhs_normal(n, q, seed).T.astype(np.float32)                   # (q, N)
    good = np.all(np.isfinite(m), axis=1) & (m.sum(axis=1) > 0)
    if corr is not None:
        good &= np.all(np.isfinite(corr.reshape(npos, -1)), axis=1)
    outs = [np.full(npos, np.nan) for _ in thresholds]
    todo = np.flatnonzero(good)
    # independent channels: the starts of every position at once (position by position
    # the same numbers; a few calls on long arrays, not one per block and form);
    # correlated: each draw starts from its own bound (`_draw_starts`)
    starts = [None] * len(thresholds) if corr is not None else \
        [_moment_guess(m[todo], np.ones((len(todo), q)), t, p, pd)
         for t, p in zip(thresholds, powers)]

    def block(at):
        sl = todo[at]
        if corr is None:
            z = np.broadcast_to(eps, (len(sl),) + eps.shape)
        else:
            # single precision: P_D from ~1e3 draws does not need more
            z = np.matmul(np.linalg.cholesky(corr[sl] + 1e-9 * np.eye(q)).astype(np.float32),
                          eps)
        return [order_quantile(_crossings(z, m[sl], threshold, power,
                                          start[at] if start is not None else
                                          _draw_starts(z, m[sl], threshold, power)), pd)
                for threshold, power, start in zip(thresholds, powers, starts)]
    blocks = [slice(a, a + 64) for a in range(0, len(todo), 64)]
    for at, lims in zip(blocks, thread_map(block, blocks)):
        for out, lim in zip(outs, lims):
            out[todo[at]] = lim
    return outs


def _draw_starts(z, m, threshold, power):
    """Per draw of *z* (k, q, N), where Newton's steps of `_crossings` start (k, N): the
    crossing of a bound of ``T(c) = sum_i max(z_i + c m_i, 0)^power`` with every channel
    on (one pass over the channels; no per-position search of a start). Power 1:
    ``T >= sum_i (z_i + c m_i)``, crossing right of the draw's; power 2: ``T <= sum_i
    (z_i + c m_i)^2``, whose larger crossing is left of it (the first step lands right of
    the crossing, as from any start), or where that stays above the threshold,
    ``T >= (sum_i (z_i + c m_i))^2 / q`` (Cauchy-Schwarz), right of it. At least 0."""
    q = z.shape[1]
    m32 = m.astype(np.float32)
    total, zsum = m32.sum(axis=1)[:, None], z.sum(axis=1)
    if power == 1:
        return np.maximum((np.float32(threshold) - zsum) / total, 0)
    lin = np.matmul(m32[:, None, :], z)[:, 0]                   # sum m z
    quad = np.sum(m32 ** 2, axis=1)[:, None]
    disc = lin * lin - quad * (np.einsum("kqn,kqn->kn", z, z) - np.float32(threshold))
    with np.errstate(invalid="ignore"):
        low = (np.sqrt(disc) - lin) / quad
    high = (np.float32(np.sqrt(q * threshold)) - zsum) / total
    return np.maximum(np.where(disc >= 0, low, high), 0)


def _moment_guess(m, sigma, threshold, power, pd):
    """Contrast at which the binary statistic, taken as Gaussian, is above *threshold*
    with probability *pd*: its mean minus ``Phi^-1(pd)`` standard deviations reaches
    the threshold, channels independent ``N(c m, sigma^2)`` (exact moments of
    ``max(z, 0)^power``). The limit for many channels, and where the exact
    per-draw solution starts otherwise."""
    k = -special.ndtri(pd)

    def excess(c):
        mean, var = _clipped_moments(c[:, None] * m / sigma, power)
        spread = np.sqrt(np.sum(sigma ** (2 * power) * var, 1))
        return np.sum(sigma ** power * mean, 1) + k * spread - threshold
    lo, hi = np.zeros(len(m)), np.ones(len(m)) / np.maximum(m.max(axis=1), 1e-300)
    for _ in range(60):                       # bracket, then bisect: cheap (k, q) arrays
        grow = excess(hi) < 0
        if not grow.any():
            break
        lo, hi = np.where(grow, hi, lo), np.where(grow, 2 * hi, hi)
    for _ in range(16):                       # a start: 1e-5 of the bracket is plenty
        mid = 0.5 * (lo + hi)
        up = excess(mid) >= 0
        lo, hi = np.where(up, lo, mid), np.where(up, mid, hi)
    return hi


def _crossings(z, m, threshold, power, start, n_iter=12, rtol=1e-4, chunk=4):
    """Per draw, the contrast at which the binary statistic crosses *threshold*.

    For draws *z* (k, q, N) and the signal per unit contrast *m* (k, q) (``m >= 0``),
    ``T(c) = sum_i max(z_i + c m_i, 0)^power`` is convex and non-decreasing in
    ``c``, so Newton's method from *start* (k,) or (k, N) lands right of the crossing in one
    step and then falls monotonically onto it (at most a few steps where ``T`` is
    piecewise polynomial). Returns (k, N), 0 for draws above the threshold
    without a companion. ``P_D(c)`` is the fraction of draws crossing below ``c``
    (`~kpifs.detect._laws.order_quantile`): no root finding on a Monte-Carlo ``P_D``.
    The steps go *chunk* positions at a time, whose work arrays stay in the
    processor's cache, and a chunk stops once all its draws have converged.
    """
    k, q, n = z.shape
    m32 = m.astype(np.float32)
    c = np.array(np.broadcast_to(np.asarray(start, np.float32).reshape(k, -1), (k, n)))
    threshold = float(threshold)
    if newton_crossings(z, m32, c, threshold, power, n_iter=n_iter, rtol=rtol, chunk=chunk):
        return c                                    # the same steps, compiled
    u = np.empty((min(chunk, k), q, n), z.dtype)
    zero = np.zeros_like(u)          # max(u, zero), not max(u, 0): numpy's faster loop
    todo = list(range(0, k, chunk))
    for _ in range(n_iter):
        left = []
        for a in todo:
            sl = slice(a, a + chunk)
            n_sl = len(c[sl])
            new = _newton_step(z[sl], m32[sl], c[sl], threshold, power, u[:n_sl], zero[:n_sl])
            if not np.all(np.abs(new - c[sl]) <= rtol * np.maximum(new, 1e-30)):
                left.append(a)
            c[sl] = new
        todo = left
        if not todo:
            break
    return c


def _newton_step(z, m32, c, threshold, power, u, zero):
    """One Newton step of `_crossings` from contrasts *c* (k, N); *u* a work array and
    *zero* zeros of its shape (for numpy's loops, ``kpifs.detect._elementwise.crossing_sums``)."""
    f, g = crossing_sums(z, m32, c, power, u=u, zero=zero)
    f = f - threshold
    if power == 2:
        g = 2 * g
    with np.errstate(divide="ignore", invalid="ignore"):
        new = np.maximum(c - f / g, 0)
        off = g <= 0
        if off.any():
            # every channel off: go to where the first channel alone would reach
            # the threshold, which is right of the crossing (T is at least that term)
            alone = np.where(m32[:, :, None] > 0,
                             (threshold ** (1 / power) - z) / m32[:, :, None], np.inf)
            new = np.where(off, np.maximum(alone.min(axis=1), c), new)
    return new


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
    return energy_crossing_limits(lambda a, b: np.asarray(signal_proj[:, a:b], float).T,
                                  signal_norm2, noise_energy, threshold, pd)


def energy_crossing_limits(projections, signal_norm2, noise_energy, threshold, pd):
    """`limit_energy_correlated` with the draws' projections made on demand:
    ``projections(a, b)`` gives those of positions ``a:b`` (b - a, N), 256 at a time (no
    (N, npos) array of them all).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.limits import energy_crossing_limits
    >>> noise = np.random.default_rng(0).standard_normal((20000, 30))
    >>> energy = np.sum(noise ** 2, axis=1)
    >>> x = np.eye(30)[:, :2]                       # two unit-norm signal directions
    >>> lim = energy_crossing_limits(lambda a, b: (noise @ x[:, a:b]).T, np.ones(2), energy,
    ...                              np.quantile(energy, 0.99), 0.5)
    >>> bool(np.all(np.abs(lim - 4.66) < 0.2))      # sqrt(lambda) of ncx2 with 30 dof
    True
    """
    pd = check_probability(pd, "P_D")

    # T_E(c) = thr is a quadratic in c per draw: its larger root is where that draw
    # crosses (the draws already above the threshold alone, a fraction P_FA, at 0)
    x2 = np.asarray(signal_norm2, float)
    slack = threshold - np.asarray(noise_energy, float)
    below = slack <= 0

    def chunk(a):
        # positions by rows, draws along them (their order statistic on contiguous rows)
        proj = projections(a, min(a + 256, len(x2)))
        x2a = x2[a:a + 256, None]
        # (sqrt(max(proj^2 + x2 slack, 0)) - proj) / x2, in place
        root = np.multiply(proj, proj, out=np.empty(proj.shape))
        root += x2a * slack
        with np.errstate(invalid="ignore", divide="ignore"):
            np.maximum(root, 0, out=root)
            np.sqrt(root, out=root)
            root -= proj
            root /= x2a
        np.maximum(root, 0, out=root)
        root[:, below] = 0.0
        return order_quantile(root, pd)
    out = np.concatenate([np.zeros(0)] + thread_map(chunk, range(0, len(x2), 256)))
    return np.where(x2 > 0, out, np.nan)


def _clipped_moments(mu, power):
    """Mean and variance of ``max(z, 0) ** power`` for ``z ~ N(mu, 1)`` (power 1 or 2)."""
    cdf, pdf = special.ndtr(mu), np.exp(-0.5 * mu ** 2) / np.sqrt(2 * np.pi)
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
    return norm_isf(pfa)


def sigma_to_pfa(n_sigma):
    """False-alarm probability of a one-sided Gaussian "n sigma": ``Q(n)``.

    Examples
    --------
    >>> from kpifs.detect.limits import sigma_to_pfa
    >>> float(f"{sigma_to_pfa(5):.4e}")
    2.8665e-07
    """
    return norm_sf(n_sigma)


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
    p = chi2_cdf(ndof * np.asarray(chi2r_test, float) / chi2r_true, ndof)
    return np.sqrt(chi2_ppf(p, 1))
