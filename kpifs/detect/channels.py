"""The channels together: their correlation in the search, the limits and the noise scale.

Real IFS channels share their noise (one optical-path error is seen at every
wavelength). The error model's covariance rows carry that correlation: at
each grid position the ``z_i`` of the channels have covariance ``C = Z^T Z``
(`~kpifs.detect.maps.DetectionModel.correlate`). Here: the subspace test's
weights under ``C`` shrunk towards independence by cross-validation
(`channel_shrinkage`, `whiten_weights`), the known-spectrum reference limit
with ``C`` (`np_correlated`), and the variance scale the data show against
the model (`energy_spread`, `noise_scale`), applied to every test.
"""
import numpy as np

from ._laws import norm_isf
from .limits import energy_crossing_limits
from .quality import resolution_mas

__all__ = ["whiten_weights", "channel_shrinkage", "SHRINKAGE_GRID", "np_correlated",
           "energy_spread", "noise_scale", "map_noise", "map_expectation", "combined_scale",
           "subspace_scale", "annulus_noise", "ring_noise", "grid_rings", "NOISE_CONFIDENCE",
           "MIN_SCALE",
           "energy_null", "channel_correlation", "correlated_energy_limit", "scale_block_rows"]

#: One-sided confidence of the upper bound a conservative error model is scaled down to.
NOISE_CONFIDENCE = 0.023
#: Smallest noise scale applied (an error model ten times too conservative; degenerate
#: data, all zero, would otherwise divide by zero).
MIN_SCALE = 0.1


def whiten_weights(w, corr, alpha):
    """The subspace statistic's weights with the channels' correlation, per position.

    ``W = C^-1 U (U^T C^-1 U)^{-1/2}`` with ``C = (1 - alpha) C_rows + alpha mu
    I``: the GLR for a spectrum in ``span(U)`` when the ``z_i`` have covariance
    ``C`` (``W^T C W = I``), which uses every channel, signal or not, to cancel the
    noise they share. The target's variance ``mu`` is the rows' mean variance over
    the channels at that position, ``tr(C_rows) / q``, where it exceeds the
    whitening's 1: rows whitened by their own covariance hold 1 (a calibrated
    product's), and the target is the identity; 20 frames for hundreds of kernel
    phases, whitened by a shrunk covariance, hold several times 1 along
    companions' signatures at small separations, and the weights are normalised
    by it there. Never below 1: a few rows underestimate some directions (GPI's 8
    exposures with a Ledoit-Wolf covariance hold 0.16 of the whitening), and
    weights normalised by them would favour those. *w* (r, q, ny, nx), *corr*
    (ny, nx, q, q).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import whiten_weights
    >>> u = np.ones((1, 2, 1, 1)) / 2 ** 0.5              # a flat spectrum, two channels
    >>> corr = np.diag([4.0, 9.0])[None, None]            # independent, variances 4 and 9
    >>> w = whiten_weights(u, corr, 1.0)[0, :, 0, 0]
    >>> round(float(w @ corr[0, 0] @ w), 9)               # unit variance under the rows
    1.0
    """
    r, q = w.shape[:2]
    shape = w.shape[2:]
    ww = w.reshape(r, q, -1).transpose(2, 1, 0)                     # (npos, q, r)
    c = corr.reshape(-1, q, q)
    ok = np.all(np.isfinite(c), axis=(1, 2))
    out = np.zeros_like(ww)
    # the target's variance: the rows' own mean where they hold more than the whitening
    # (never less than the whitening's 1: few rows underestimate some directions, and
    # weights would favour them)
    mu = np.maximum(np.einsum("kqq->k", c[ok]) / q, 1.0)
    cs = (1 - alpha) * c[ok] + alpha * mu[:, None, None] * np.eye(q)
    ci_u = np.linalg.solve(cs, ww[ok])                              # C^-1 U
    g = np.matmul(ww[ok].transpose(0, 2, 1), ci_u)                  # U^T C^-1 U
    val, vec = np.linalg.eigh(g)
    good = val > 1e-9 * np.maximum(val[:, -1:], 1e-300)
    inv = np.where(good, 1 / np.sqrt(np.where(good, val, 1.0)), 0.0)
    out[ok] = np.matmul(ci_u, np.matmul(vec * inv[:, None, :], vec.transpose(0, 2, 1)))
    return out.transpose(2, 1, 0).reshape((r, q) + shape)


#: Shrinkage weights of the channels' correlation towards independence, tried by
#: `channel_shrinkage` (cross-validated on the error model's rows).
SHRINKAGE_GRID = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)


def channel_shrinkage(z, *, n_positions=48, folds=5, seed=0):
    """Weight ``alpha`` of the shrinkage ``(1 - alpha) C + alpha I`` of the channels'
    correlation, by cross-validated Gaussian likelihood of the rows' projections.

    *z* (npos, nrow, q): each row (scaled to one frame's worth) is a sample of
    the ``z_i`` at a position; folds of rows are held out in turn and the
    likelihood of the held-out rows under the shrunk correlation of the others
    is summed over *n_positions* positions. The frames rarely support the raw
    correlation (it has the rank of the frames), nor independence.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import channel_shrinkage
    >>> rng = np.random.default_rng(0)
    >>> common = rng.standard_normal((10, 200, 1))       # one noise shared by 4 channels
    >>> z = (0.9 * common + 0.44 * rng.standard_normal((10, 200, 4))) / 200 ** 0.5
    >>> channel_shrinkage(z) <= 0.1
    True
    """
    z = np.asarray(z, float)
    npos, m, q = z.shape
    if m < 2 * folds or q < 2:
        return 1.0
    rng = np.random.default_rng(seed)
    pick = rng.choice(npos, min(npos, n_positions), replace=False)
    parts = np.array_split(rng.permutation(m), folds)
    score = np.zeros(len(SHRINKAGE_GRID))
    for k in pick:
        x = z[k] * np.sqrt(m)
        if not np.all(np.isfinite(x)):
            continue
        for f in parts:
            train = np.delete(x, f, axis=0)
            c = train.T @ train / len(train)
            d = np.sqrt(np.clip(np.diag(c), 1e-300, None))
            c = c / np.outer(d, d)
            held = x[f] / d
            score -= _held_out_nll(c, held)
    return float(SHRINKAGE_GRID[int(np.argmax(score))])


def _held_out_nll(c, held):
    """Minus the log-likelihood (up to a constant) of rows *held* under the correlation
    *c* shrunk by each weight of `SHRINKAGE_GRID` (inf where that is not positive
    definite): every weight's matrix factorised in one batched call."""
    grid = np.asarray(SHRINKAGE_GRID, float)[:, None, None]
    shrunk = (1 - grid) * c + grid * np.eye(len(c))
    sign, logdet = np.linalg.slogdet(shrunk)
    out = np.full(len(shrunk), np.inf)
    ok = np.flatnonzero(sign > 0)
    sol = np.linalg.solve(shrunk[ok], np.broadcast_to(held.T, (len(ok),) + held.T.shape))
    for j, x in zip(ok, sol):
        out[j] = 0.5 * (len(held) * logdet[j] + np.sum(held * x.T))
    return out


def np_correlated(norm2, corr, a, pfa, pd):
    """Neyman-Pearson limit map with the channels' correlation ``C`` (ny, nx, q, q) of the
    ``z_i``: ``(Q^-1(P_FA) - Q^-1(P_D)) / sqrt(m^T C^+ m)``, ``m_i = a_i ||s_i||``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import np_correlated
    >>> corr = np.eye(2)[None, None]
    >>> round(float(np_correlated(np.full((2, 1, 1), 1e6), corr, np.ones(2), 1e-3, 0.5)[0, 0]
    ...             * 1e3 * 2 ** 0.5), 4)
    3.0902
    """
    q = len(norm2)
    m = (a[:, None] * np.sqrt(norm2.reshape(q, -1))).T                 # (npos, q)
    c = corr.reshape(-1, q, q)
    out = np.full(len(m), np.nan)
    ok = np.all(np.isfinite(c), axis=(1, 2)) & np.all(np.isfinite(m), axis=1)
    power = _pinv_power(c[ok], m[ok])
    with np.errstate(divide="ignore"):
        out[ok] = (norm_isf(pfa) - norm_isf(pd)) / np.sqrt(power)
    return out.reshape(norm2.shape[1:])


def energy_spread(rows, dof):
    """Relative standard deviation of the whitened energy under the error model.

    ``sqrt(2 tr G^2) / tr G`` with ``G`` the Gram matrix of the whitened
    covariance rows (channels correlated: fewer effective degrees of freedom),
    ``sqrt(2 / dof)`` without rows.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import energy_spread
    >>> rows = np.eye(50).reshape(50, 1, 50)
    >>> round(energy_spread(rows, 50), 4), round(energy_spread(None, 50), 4)
    (0.2, 0.2)
    """
    if rows is None:
        return float(np.sqrt(2.0 / max(dof, 1)))
    flat = rows.reshape(len(rows), -1)
    g = flat @ flat.T
    return float(np.sqrt(2 * np.sum(g * g)) / max(np.trace(g), 1e-300))


def noise_scale(kappa, spread):
    """Variance scale applied to the error model, from the reduced chi-square *kappa*.

    Up (the data scatter more than the model says: a calibration residual)
    by *kappa* itself; down (a conservative model wastes depth) only to the
    97.7 % upper confidence bound of the true scale, ``kappa / (1 - 2 spread)``
    with *spread* the energy's relative standard deviation under the model
    (`energy_spread`), never below *kappa* nor above 1.

    Examples
    --------
    >>> from kpifs.detect.channels import noise_scale
    >>> noise_scale(1.6, 0.07), round(noise_scale(0.4, 0.07), 3), noise_scale(0.9, 0.2)
    (1.6, 0.465, 1.0)
    """
    if kappa >= 1:
        return float(kappa)
    low = 1 - 2 * spread
    if low <= 0:
        return 1.0
    return float(min(1.0, kappa / low))


def map_noise(model, y, *, subspace=False):
    """Mean square of the normalised projections ``z_i`` of whitened data *y* over the
    grid and channels: 1 on average when the error model describes the data, more
    when a residual the model misses projects on companions' signatures (the
    map's own noise, as imaging pipelines judge a detection by).

    With *subspace*, the mean square ``||U^T z||^2 / r`` of the subspace test's
    projections (`DetectionModel.subspace <kpifs.detect.DetectionModel.subspace>`):
    a residual that is smooth across wavelength, as a static aberration's is,
    concentrates there while it is diluted among all the channels' ``z_i``.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.channels import map_noise
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> # its mean under H0: exactly its sum over an orthonormal basis of the data
    >>> round(sum(map_noise(dm, e[None]) for e in np.eye(km.n_kp)), 9)
    1.0
    """
    z = model.z_maps(y)[..., model.grid.valid]
    if subspace:
        sub = model.subspace[..., model.grid.valid]                     # (r, q, nvalid)
        z = np.einsum("rqk,qk->rk", sub, np.nan_to_num(z))
    z = z[np.isfinite(z)]
    return float(np.mean(z ** 2)) if z.size else float("nan")


def grid_rings(model):
    """Annulus index of every grid position (flat), one resolution element
    (`~kpifs.detect.quality.resolution_mas`) wide from the grid's inner edge.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.channels import grid_rings
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> int(grid_rings(dm).max())     # lambda / B_max = 43 mas: 20-100 mas in three
    2
    """
    if "_rings" not in model.__dict__:
        grid = model.grid
        sep = grid.sep.ravel()
        inner = sep[grid.valid.ravel()].min() if grid.valid.any() else 0.0
        width = resolution_mas(model.kernel_model, model.wavelengths)
        model._rings = np.clip(np.floor((sep - inner) / width), 0, None).astype(int)
    return model._rings


def _map_power(model, y, subspace):
    """Per valid position: the map's square ``sum z_i^2`` (or ``||U^T z||^2``) and its
    expectation under the error model."""
    v = model.grid.valid
    z = np.nan_to_num(model.z_maps(y)[..., v])                         # (q, nvalid)
    if subspace:
        num = np.sum(np.einsum("rqk,qk->rk", model.subspace[..., v], z) ** 2, axis=0)
    else:
        num = np.sum(z ** 2, axis=0)
    return num, _map_expectation(model, subspace)


def _map_expectation(model, subspace):
    """`_map_power`'s expectation, which depends on the model alone: kept on it, with the
    channels' correlation and subspace weights it was computed from (made again when
    those change)."""
    v = model.grid.valid
    corr = model.__dict__.get("_channel_corr")
    sub = model.subspace if subspace else None
    kept = model.__dict__.setdefault("_map_expectation", {}).get(subspace)
    if kept is not None and kept[0] is corr and kept[1] is sub:
        return kept[2]
    c = None if corr is None else np.nan_to_num(corr[v])                 # (nvalid, q, q)
    if subspace:
        s = sub[..., v]                                                   # (r, q, nvalid)
        expect = np.sum(s ** 2, axis=(0, 1)) if c is None else \
            np.einsum("rqk,kqp,rpk->k", s, c, s)
    else:
        expect = np.full(int(v.sum()), float(len(model.wavelengths))) if c is None else \
            np.einsum("kqq->k", c)
    model._map_expectation[subspace] = (corr, sub, expect)
    return expect


def map_expectation(model):
    """What `map_noise` reads on average under the error model: the mean, over the
    grid, of the channels' correlation's trace per channel (`DetectionModel.correlate
    <kpifs.detect.DetectionModel.correlate>`, from the covariance rows the null draws
    from). It is 1 when the rows are whitened by their own covariance (a calibrated
    product's modes) or not known; more when they hold more than the whitening
    along companions' signatures (few frames for many kernel phases, whitened by a
    shrunk covariance).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.channels import map_expectation
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> rows = np.eye(km.n_kp)[:, None]           # whitened by their own covariance
    >>> _ = dm.correlate(rows)
    >>> round(map_expectation(dm), 9)
    1.0
    >>> _ = dm.correlate(3 * rows)              # rows of three times the whitening's scale
    >>> round(map_expectation(dm), 9)
    9.0
    """
    if not model.grid.valid.any():
        return 1.0
    return float(np.mean(_map_expectation(model, False)) / len(model.wavelengths))


def annulus_noise(model, y, *, subspace=False):
    """Ratio, per annulus of the grid, of the map's mean square to its model
    expectation, as a map (ny, nx; NaN off the grid).

    The map is the normalised projections ``z_i`` of whitened data *y* (or,
    with *subspace*, the subspace test's ``U^T z``); their expectation comes
    from the channels' correlation (`DetectionModel.correlate
    <kpifs.detect.DetectionModel.correlate>`) when known; the annuli are
    `grid_rings`. A residual the error model misses
    rarely spreads evenly: a static aberration's lives at small separations,
    as the speckles of an image do.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.channels import annulus_noise
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> # data of twice the model's noise: its mean, the sum over an orthonormal basis, is 4
    >>> ratio = sum(annulus_noise(dm, 2 * e[None]) for e in np.eye(km.n_kp))
    >>> np.unique(np.round(ratio[np.isfinite(ratio)], 9)).tolist()
    [4.0]
    """
    grid = model.grid
    v = grid.valid
    ratio = np.full(grid.shape, np.nan)
    if not v.any():
        return ratio
    num, expect = _map_power(model, y, subspace)
    ring = grid_rings(model)[v.ravel()]
    top = np.bincount(ring, num)
    bottom = np.bincount(ring, expect)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio[v] = (top / bottom)[ring]
    return ratio


def ring_noise(model, y, peak, *, width, radius, subspace=False, min_positions=20):
    """The `annulus_noise` ratio around a candidate at *peak* ``(x, y)`` (mas): over
    the positions within *width* of its separation, leaving out those within
    *radius* of it and of its mirror ``(-x, -y)`` (where the odd kernel phases see
    its signal, sign reversed), so that it is judged by the noise around it and
    not by its own signal. The band widens until it holds *min_positions* and
    the exclusion leaves at least half of it; NaN when it never does (a grid
    a few resolution elements wide).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.channels import ring_noise
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> # its mean under H0: exactly its sum over an orthonormal basis of the data
    >>> round(sum(ring_noise(dm, e[None], (60.0, 0.0), width=20, radius=30)
    ...           for e in np.eye(km.n_kp)), 9)
    1.0
    """
    grid = model.grid
    v = grid.valid
    if not v.any():
        return float("nan")
    num, expect = _map_power(model, y, subspace)
    x, yy, sep = grid.X[v], grid.Y[v], grid.sep[v]
    away = (np.hypot(x - peak[0], yy - peak[1]) > radius) \
        & (np.hypot(x + peak[0], yy + peak[1]) > radius)
    if not away.any():
        return float("nan")
    d = np.abs(sep - np.hypot(*peak))
    band = float(width)
    while True:
        inside = d <= band
        keep = away & inside
        # most of the band, not a corner the exclusion left: else a wider band
        if keep.sum() >= min_positions and keep.sum() >= 0.5 * inside.sum():
            break
        if inside.all():
            return float("nan")
        band *= 1.5
    return float(np.sum(num[keep]) / np.sum(expect[keep]))


def subspace_scale(scale, kappa_sub, draws):
    """Noise scale of the subspace test: the common *scale*, or more when the mean
    square of its own projections (`map_noise` with ``subspace=True``) is above what
    the null's *draws* of it (`~kpifs.detect.null.NullCalibration.noise_draws`
    ``'G2'``) give on average.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import subspace_scale
    >>> subspace_scale(1.1, 1.5, np.full(100, 1.0)), subspace_scale(1.1, 0.9, np.ones(9))
    (1.5, 1.1)
    """
    ref = float(np.mean(draws)) if len(draws) else float("nan")
    if not (np.isfinite(kappa_sub) and np.isfinite(ref) and ref > 0):
        return float(scale)
    return float(max(scale, kappa_sub / ref))


def combined_scale(kappa, spread, kappa_map, map_low, map_mean=1.0):
    """Noise scale from both the residual's energy and its map (the larger).

    Each is scaled up by its own measure when above 1, down only to its
    upper confidence bound (`noise_scale`): *spread* for the energy, *map_low*
    (the `NOISE_CONFIDENCE` quantile of `~kpifs.detect.null.NullCalibration.noise_draws`)
    for the map's mean square *kappa_map*; never below `MIN_SCALE`. The map's is
    measured against the larger of the whitening's 1 and what the covariance rows
    the null draws from give it on average (*map_mean*, `map_expectation`): where
    they hold more than the whitening along companions' signatures (few frames for
    many kernel phases, a shrunk covariance), the threshold already holds that
    excess, and counting it in the scale too would count it twice. Where they hold
    less (an average over channels some of which the rows barely see, as ASDI's
    block departures), the whitening stays the reference.

    Examples
    --------
    >>> from kpifs.detect.channels import combined_scale
    >>> combined_scale(1.2, 0.1, 1.5, 0.8), combined_scale(0.5, 0.1, 0.6, 0.8)
    (1.5, 0.75)
    """
    if not np.isfinite(kappa_map):      # no valid position: the energy alone
        s = noise_scale(kappa, spread) if np.isfinite(kappa) else 1.0
    else:
        rel = kappa_map / max(map_mean, 1.0) if np.isfinite(map_mean) else kappa_map
        s_map = rel if rel >= 1 else min(1.0, kappa_map / max(map_low, 1e-12))
        s = s_map if not np.isfinite(kappa) else max(noise_scale(kappa, spread), s_map)
    return float(max(s, MIN_SCALE))


def _pinv_power(c, m, rcond=1e-9):
    """``m^T C^+ m`` for each symmetric matrix of *c* (n, q, q) and vector of *m* (n, q),
    ``C^+`` the pseudo-inverse of ``numpy.linalg.pinv(C, rcond, hermitian=True)``
    (eigenvalues below *rcond* times the largest, in absolute value, left out). Where
    none is left out ``C^+`` is the inverse: one solve (the eigenvalues alone say so, a
    third of the time of the decomposition ``pinv`` makes); elsewhere ``pinv``."""
    vals = np.abs(np.linalg.eigvalsh(c))
    full = np.all(vals > rcond * vals.max(axis=1, keepdims=True), axis=1)
    out = np.empty(len(c))
    if full.any():
        x = np.linalg.solve(c[full], m[full][:, :, None])[:, :, 0]
        out[full] = np.einsum("ni,ni->n", m[full], x)
    if not full.all():
        inv = np.linalg.pinv(c[~full], rcond=rcond, hermitian=True)
        out[~full] = np.einsum("ni,nij,nj->n", m[~full], inv, m[~full])
    return out


def channel_correlation(model, rows):
    """Per-position covariance of the ``z_i`` (ny, nx, q, q) carried by the whitened
    covariance *rows* (for the limits); on a symmetric grid for half the positions
    (NaN elsewhere: see `~kpifs.detect.limits.mirror_half_map`)."""
    shape = model.grid.shape
    q = len(model.wavelengths)
    idx, z = model.row_projections(rows)                              # (npos, nrow, q)
    corr = np.full((shape[0] * shape[1], q, q), np.nan)
    corr[idx] = np.matmul(z.transpose(0, 2, 1), z)
    return corr.reshape(shape + (q, q))


def correlated_energy_limit(model, rows, a, threshold, pd, te):
    """The energy detector's limit map with the channel correlations of the whitened
    covariance *rows*, from its correlated null *te* (`energy_null`) and *threshold*;
    on a symmetric grid for half the positions (NaN elsewhere)."""
    shape = model.grid.shape
    q = len(model.wavelengths)
    idx, z = model.row_projections(rows)                              # (npos, nrow, q)
    amp = a[None, :] * np.sqrt(model.norm2.reshape(q, -1)[:, idx].T)     # (npos, q)
    n = min(4096, len(te["energy"]))      # enough draws for P_D, far from the tail
    # each position's projections of the draws, made block of positions by block as the
    # limit reads them (not one (npos, N) array)
    rows_amp, coef = np.einsum("kri,ki->kr", z, amp), np.ascontiguousarray(te["coef"][:n].T)
    lim = np.full(shape[0] * shape[1], np.nan)
    lim[idx] = energy_crossing_limits(lambda a, b: rows_amp[a:b] @ coef,
                                      np.sum(amp ** 2, axis=1), te["energy"][:n], threshold, pd)
    return lim.reshape(shape)


def energy_null(rows, n_draws, seed):
    """Noise draws ``n = a R_w`` from whitened covariance rows: coefficients and energies.

    Returns a dict with ``coef`` (n_draws, nrow) and ``energy`` (n_draws,) =
    ``||a R_w||^2``, the energy detector's law with the channels' correlations.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import energy_null
    >>> rows = np.eye(50).reshape(50, 1, 50)        # white noise, 50 dimensions
    >>> e = energy_null(rows, 20000, 0)["energy"]
    >>> bool(abs(e.mean() - 50) < 0.5)
    True
    """
    rng = np.random.default_rng(seed)
    coef = rng.standard_normal((n_draws, len(rows)))
    flat = rows.reshape(len(rows), -1)
    energy = np.sum((coef @ (flat @ flat.T)) * coef, axis=1)
    return {"coef": coef, "energy": energy}


def scale_block_rows(blocks, rank):
    """Whitened block rows with the variance of the whitened data, channel by channel.

    Block means helped estimate the covariance that whitens them, so their
    whitened energy is biased low (in-sample, by about the Hartlap factor:
    25 instead of 37 for 60 + 60 frames of 37 kernel phases, where the
    calibrated mean, independent of the covariance, gives 38.8). The empirical
    null therefore takes its *scale* from the error model, each channel's
    rows scaled to a total energy equal to its whitened dimension *rank* (the
    overall level the data show beyond the model is the reduced chi-square
    that detection measures), and its *shape* from the data: how the variance
    spreads over modes and channels, the drifts, the tails. Returns the rows
    and the mean in-sample energy ratio before scaling.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.channels import scale_block_rows
    >>> b = np.random.default_rng(0).standard_normal((12, 2, 30)) * 0.1
    >>> s, ratio = scale_block_rows(b, [30, 20])
    >>> np.round(np.sum(s ** 2, axis=(0, 2)), 6).tolist()
    [30.0, 20.0]
    """
    blocks = np.asarray(blocks, float)
    rank = np.broadcast_to(np.asarray(rank, float), blocks.shape[1:2])
    energy = np.sum(blocks ** 2, axis=(0, 2))
    k = np.where(energy > 0, np.sqrt(rank / np.where(energy > 0, energy, 1.0)), 0.0)
    return blocks * k[None, :, None], float(np.mean(energy[rank > 0] / rank[rank > 0]))
