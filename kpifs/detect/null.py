"""The null hypothesis of a search: the law of the grid-maximised statistic under H0.

The statistic maximised over the grid has no closed-form law. A
`NullCalibration` draws it for one projection (`~kpifs.detect.maps.DetectionModel`):
under H0 the whitened data are noise, so ``z_i(pos)`` is the projection of a
noise draw on the unit signature at ``pos``. Without covariance rows the
draws are standard normal in every channel (independent channels); with
*noise_rows* (nrow, q, p), whitened rows whose Gram matrix is the covariance of
the whitened data across channels, they are random combinations of the rows,
which keeps the correlation between channels (achromatic aberrations,
spectral cross-talk). Draws are cached per (projection, test, draws, seed,
noise), most recently used last, so that a long-running process (a batch
worker) does not accumulate them.

The empirical null (``coefficients='sign'``) combines instead *block rows*,
the centred means of consecutive time blocks of each star's frames
(`~kpifs.calibration.calibrate.block_rows`), with random signs: a sign-flip
(randomisation) test whose draws are the differences the data themselves show
between parts of the sequence, with their own non-Gaussian shape, drifts
longer than a frame and correlations between channels. There are only
``2**(nblock - 1)`` distinct draws (a global sign changes nothing on a
symmetric grid); when *n_draws* reaches that number they are enumerated, an
exact randomisation law. `CombinedNull` gives the more conservative of two
nulls at every level, as `~kpifs.detect.detect` does by default.
"""
import hashlib
import logging

import numpy as np

from .._utils import as_rng, thread_map
from .._utils import progress as progress_bar
from ..exceptions import KpifsError
from .statistics import DEFAULT_TEST, NullSetup, get_test, subspace_test
from .stats import check_probability

__all__ = ["NullCalibration", "CombinedNull", "search_null",
           "check_draws", "MIN_DRAWS", "DEFAULT_DRAWS", "COEFFICIENTS", "NULL_METHODS",
           "EMPIRICAL_DRAWS"]

log = logging.getLogger(__name__)

_CACHE = {}
_MAX_CACHE = 32

#: Fewest draws that resolve the null: the tail fit needs ~100 draws above the 90 %
#: quantile.
MIN_DRAWS = 1000

#: Monte-Carlo draws of the Gaussian null by default. Read through the fitted tail
#: (`NullCalibration.threshold`), 5000 draws set the threshold at P_FA 1e-3 as
#: precisely as 30 000 read directly (a spread of 4.0 against 4.9 on the 20-frame
#: CHARIS simulation's threshold of 174; ``docs/figures/measure_null_draws.py``).
DEFAULT_DRAWS = 5000

#: Draws above a level below which the Monte-Carlo law is read directly; beyond, from
#: its fitted tail. An enumerated (exact) law is read directly down to 10 draws.
TAIL_EXCEEDANCES = {"monte-carlo": 100, "enumerated": 10}

#: Smallest global false-alarm probability reported (extrapolations go no further).
PFA_FLOOR = 1e-15

#: How noise rows are combined into draws: Gaussian (Monte Carlo) or random signs.
COEFFICIENTS = ("gaussian", "sign")

#: Fewest block rows of an empirical (sign-flip) null: 2**(n-1) distinct draws.
MIN_SIGN_ROWS = 6

#: Nulls of a search: ``'auto'`` is ``'both'`` when the data carry block rows.
NULL_METHODS = ("auto", "gaussian", "empirical", "both")

#: Most sign-flip draws of the empirical null (every pattern of up to 13 blocks).
EMPIRICAL_DRAWS = 2 ** 12

#: Draws whose projections in every channel are made in one product (a batch's share).
SUB_BATCH = 64


def check_draws(n_draws):
    """Refuse a number of Monte-Carlo draws that cannot resolve the null's tail.

    Examples
    --------
    >>> from kpifs.detect.null import check_draws
    >>> check_draws(10000)
    10000
    """
    try:
        n = int(n_draws)
    except (TypeError, ValueError):
        raise KpifsError(f"the number of Monte-Carlo draws must be an integer, got "
                         f"{n_draws!r}") from None
    if n < MIN_DRAWS:
        raise KpifsError(f"{n} Monte-Carlo draws cannot resolve a false-alarm probability: "
                         f"use at least {MIN_DRAWS} (--draws); below 10 / P_FA draws the "
                         f"null's tail is extrapolated")
    return n


def _via_rows(rows, n_kp):
    """Whether draws go through the rows' projections (fewer rows than kernel phases)."""
    return rows is not None and len(rows) < n_kp


class _Projections:
    """How a null's draws become projections on the unit signatures, channel by channel:
    through the rows' projections when there are fewer rows than kernel phases, else
    through the signatures themselves."""

    def __init__(self, null):
        model, rows = null.model, null.noise_rows
        self.null, self.rows = null, rows
        self.q, p = len(model.wavelengths), getattr(model, "dim", model.kernel_model.n_kp)
        self.p = p
        self.positions, self.mirrored = model.half_positions()
        self.npos = len(self.positions)
        # z = eps @ unit^T with eps = coef @ rows: project the rows once when they are few
        self.via_rows = _via_rows(rows, p)
        if self.via_rows:
            # the rows' projections on every valid position (the limits use them too)
            valid, z = model.row_projections(rows)                        # (nvalid, nrow, q)
            # (npos, nrow, q): the projections themselves when made on these positions
            self._z = z if np.array_equal(valid, self.positions) else \
                z[np.searchsorted(valid, self.positions)]
            # sum_i ||z_i||^2 is a quadratic form of coef: coef^T (sum_i Z_i Z_i^T) coef
            flat = self._z.transpose(1, 0, 2).reshape(len(rows), -1)
            self.gram = flat @ flat.T
            self.proj = self.sum_weights = None          # `channels` makes them if needed
        else:
            self.unit = model._unit_signatures(self.positions)            # (q, npos, p)
            self.flat_rows = None if rows is None else \
                rows.reshape(len(rows), -1).astype(np.float32)
            # ... or eps (all channels) @ the stacked signatures
            self.sum_weights = self.unit.transpose(0, 2, 1).reshape(self.q * p, -1) \
                if self.mirrored else None

    def channels(self):
        """Make the channels' projections (nrow, q, npos) and their sum, for the
        reductions that need every channel's ``z_i`` (and the channels' sum): every
        channel's draws are one product (`_Draw.all_channels`), or one each."""
        if self.via_rows and self.proj is None:
            proj = np.ascontiguousarray(self._z.transpose(1, 2, 0), np.float32)
            # the sum of z over channels is one product: coef @ sum_i proj_i
            self.sum_weights = proj.sum(axis=1)
            self.proj = proj
        return self

    def combine(self, weights):
        """Matrices (r, nrow, npos) that give the weighted channel sums
        ``sum_i weights[j, i] z_i`` of the draws as one product each (*weights*
        (r, q, npos)), or None when the draws do not go through the rows (there, the
        channels' projections are the cheaper route)."""
        if not self.via_rows:
            return None
        w = np.asarray(weights, float).transpose(2, 0, 1)                 # (npos, r, q)
        mats = np.matmul(w, self._z.transpose(0, 2, 1))                    # (npos, r, nrow)
        return np.ascontiguousarray(mats.transpose(1, 2, 0), np.float32)

    def draw(self, rng, a, b):
        """The draws ``a:b``: an object whose ``channel(i, out)`` projects channel ``i``
        and whose ``channel_sum()`` is the sum over channels (computed once)."""
        return _Draw(self, rng, a, b)


class _Draw:
    def __init__(self, proj, rng, a, b):
        self.p, n = proj, b - a
        self._sum = None
        if proj.via_rows:
            self.coef = proj.null._coefficients(rng, a, b)
        elif proj.rows is None:
            self.joint = rng.standard_normal((n, proj.q, proj.p), dtype=np.float32)
        else:
            self.joint = (proj.null._coefficients(rng, a, b) @ proj.flat_rows).reshape(
                n, proj.q, proj.p)

    def channel(self, i, out):
        if self.p.via_rows:
            return np.matmul(self.coef, self.p.proj[:, i], out=out)
        return np.matmul(self.joint[:, i], self.p.unit[i].T, out=out)

    def all_channels(self, at, out):
        """Every channel's projections of draws *at* (a slice of the batch), one product
        through the rows: *out* (m, q, npos)."""
        flat = self.p.proj.reshape(len(self.p.proj), -1)
        return np.matmul(self.coef[at], flat, out=out.reshape(len(out), -1)).reshape(out.shape)

    def channel_sum(self):
        if self._sum is None:
            self.p.channels()
            lhs = self.coef if self.p.via_rows else self.joint.reshape(len(self.joint), -1)
            self._sum = lhs @ self.p.sum_weights
        return self._sum

    def combined(self, mats):
        """The weighted channel sums of `_Projections.combine`'s *mats*: (r, n, npos)."""
        return np.matmul(self.coef, mats)

    def energy(self):
        """``sum_i ||z_i||^2`` of each draw, through the rows (None: not through them)."""
        if not self.p.via_rows:
            return None
        c = self.coef.astype(float)
        return np.einsum("nr,nr->n", c @ self.p.gram, c)


class NullCalibration:
    """Monte-Carlo law of the grid maximum of a map statistic under H0.

    Parameters
    ----------
    model : `~kpifs.detect.maps.DetectionModel`
        The projection (signatures and grid).
    form : str
        The test whose map statistic's maximum is drawn (a name of the registry
        `kpifs.detect.statistics`, with a map: 'B', 'B-paper', 'S', 'NP').
    n_draws, seed : int
        Monte-Carlo draws and their seed.
    spectrum : array-like, optional
        Spectrum shape of the ``'NP'`` matched filter.
    noise_rows : ndarray, shape (nrow, q, p), optional
        Whitened covariance rows (see above); None: independent channels.
    coefficients : {'gaussian', 'sign'}
        Draws ``a @ noise_rows`` with Gaussian ``a`` (the Monte-Carlo null of the
        covariance the rows carry), or with random signs (the empirical null of
        block rows: at most ``2**(nrow - 1)`` distinct draws, all of them when
        *n_draws* allows).
    progress : bool
        Progress bar while drawing (on a terminal).
    also : tuple of str
        Other tests whose maxima are drawn in the same pass (and cached): the
        limits' thresholds. Only what is asked for is reduced.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel, NullCalibration
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> null = NullCalibration(dm, n_draws=2000, seed=1)
    >>> 2.5 < null.threshold(0.01) ** 0.5 < 4.5        # a few sigma above one position's
    True
    """

    def __init__(self, model, *, form=DEFAULT_TEST, n_draws=DEFAULT_DRAWS, seed=0, spectrum=None,
                 noise_rows=None, coefficients="gaussian", progress=False, also=()):
        if get_test(form).map_name != form:
            raise KpifsError(f"test {form!r} has no map: its search uses "
                             f"{get_test(form).map_name!r}'s null")
        if coefficients not in COEFFICIENTS:
            raise KpifsError(f"unknown null coefficients {coefficients!r}: use one of "
                             f"{COEFFICIENTS}")
        n_draws = check_draws(n_draws)
        self.enumerated = False
        if coefficients == "sign":
            if noise_rows is None or len(noise_rows) < MIN_SIGN_ROWS:
                raise KpifsError(f"an empirical (sign-flip) null needs at least "
                                 f"{MIN_SIGN_ROWS} block rows, got "
                                 f"{0 if noise_rows is None else len(noise_rows)}")
            # on a symmetric grid the global sign gives the same maximum
            self._fixed_first = model.half_positions()[1]
            distinct = 2 ** min(len(noise_rows) - int(self._fixed_first), 40)
            self.enumerated = distinct <= n_draws
            n_draws = min(n_draws, distinct)
        self.coefficients, self.model, self.form = coefficients, model, form
        self.n_draws, self.seed, self.spectrum = n_draws, seed, spectrum
        self.noise_rows, self.progress = noise_rows, progress
        self.also = tuple(f for f in also if f != form)

    def _key(self, form=None):
        keys, form = self.__dict__.setdefault("_keys", {}), form or self.form
        return keys[form] if form in keys else keys.setdefault(form, self._digest(form))

    def _digest(self, form):
        if "_rows_key" not in self.__dict__:     # the rows hashed once, whatever the forms
            h = hashlib.sha1(self.model.key().encode())
            if self.noise_rows is not None:
                h.update(np.ascontiguousarray(self.noise_rows).tobytes())
            self._rows_key = h.hexdigest()
        return hashlib.sha1(f"{self._rows_key}|{form}|{self.n_draws}|{self.seed}|"
                            f"{self.spectrum!r}|{self.coefficients}".encode()).hexdigest()

    @property
    def draws(self):
        """Sorted draws of the grid maximum under H0 (computed once, cached)."""
        key = self._key()
        if key in _CACHE:
            _CACHE[key] = _CACHE.pop(key)        # most recently used
            return _CACHE[key]
        for form, maxima in self._draw().items():
            _CACHE[self._key(form)] = maxima
        while len(_CACHE) > _MAX_CACHE:
            _CACHE.pop(next(iter(_CACHE)))
        return _CACHE[key]

    def _draw(self, batch=256):
        """The draws of this null's test and of those drawn with it (*also*), by name,
        with the map's mean square (``'Z2'``) and what the tests' reductions add
        (`~kpifs.detect.statistics.DetectionTest.null_reducer`). A signature at
        ``-pos`` is minus that at ``pos``, so on a symmetric grid only half the
        positions are projected; with fewer noise rows than kernel phases the rows
        are projected once and the draws combine them. Draws go in batches whose
        work arrays stay in the processor's cache; each batch its own random stream
        (the same draws whatever the tests and the number of threads)."""
        proj = _Projections(self)
        names = tuple(dict.fromkeys((self.form,) + tuple(self.also)))
        setup = NullSetup(self.model, proj.positions, proj.mirrored, self.spectrum, names,
                          proj.combine)
        reducers = [r for r in (get_test(n).null_reducer(setup) for n in names) if r is not None]
        q = proj.q
        # the channels' projections one by one, only for reductions that need them
        per_channel = any(getattr(r, "per_channel", True) for r in reducers) \
            or not proj.via_rows
        if per_channel:
            proj.channels()

        def together(adders):
            # all channels at once where the draws go through the rows and every
            # reduction can take them so (`DetectionTest.null_reducer`'s add_channels)
            return proj.via_rows and adders and all(hasattr(p, "add_channels") for p in adders)

        def one(job):
            (a, b), rng = job
            draw = proj.draw(rng, a, b)
            parts = [r.batch(b - a) for r in reducers]
            adders = [p for r, p in zip(reducers, parts) if getattr(r, "per_channel", True)]
            z2 = draw.energy()
            if per_channel and together(adders):
                # every channel in one product, by sub-batches whose projections (m, q,
                # npos) stay small; the reductions take them all at once
                zs = np.empty((min(SUB_BATCH, b - a), q, proj.npos), np.float32)
                for s in range(0, b - a, SUB_BATCH):
                    at = slice(s, min(b - a, s + SUB_BATCH))
                    z = draw.all_channels(at, zs[:at.stop - at.start])
                    for part in adders:
                        part.add_channels(z, at, draw)
            elif per_channel:
                z = np.empty((b - a, proj.npos), np.float32)
                z2 = np.zeros(b - a) if z2 is None else z2
                for i in range(q):
                    draw.channel(i, out=z)
                    if not proj.via_rows:
                        z2 += np.einsum("nk,nk->n", z, z)
                    for part in adders:
                        part.add(i, z)
            # the map's mean square (mirrored positions have the same): `noise_draws`
            out = {"Z2": z2 / (q * proj.npos)}
            for part in parts:
                out.update(part.finish(draw))
            return out

        spans = [(a, min(self.n_draws, a + batch)) for a in range(0, self.n_draws, batch)]
        jobs = list(zip(spans, as_rng(self.seed).spawn(len(spans))))
        done = thread_map(one, jobs, wrap=lambda it: progress_bar(
            it, desc=f"calibrating sup-{self.form}", unit="batch", total=len(jobs),
            enabled=self.progress))
        maxima = {f: np.empty(self.n_draws) for f in done[0]}
        for (a, b), out in zip(spans, done):
            for f in maxima:
                maxima[f][a:b] = out[f]
        for f in maxima:
            maxima[f].sort()
        return maxima

    def noise_draws(self, kind="Z2"):
        """Sorted draws, under H0, of the map's mean square: ``mean z_i^2`` over the grid
        and channels (``'Z2'``, 1 on average: the law of
        `~kpifs.detect.channels.map_noise`), or ``mean ||U^T z||^2 / r`` of the subspace
        test's projections (``'G2'``, drawn with the binary forms)."""
        key = self._key(kind)
        if key not in _CACHE:
            sub = subspace_test()
            if kind == "G2" and sub is not None and sub.name not in (self.form,) + self.also:
                self.also += (sub.name,)        # the subspace projections make them
            _CACHE.pop(self._key(), None)
            self.draws
        return _CACHE[key]

    def _coefficients(self, rng, a, b):
        """Coefficients of draws ``a:b`` (float32, one row of weights per draw)."""
        nrow = len(self.noise_rows)
        if self.coefficients == "gaussian":
            return rng.standard_normal((b - a, nrow), dtype=np.float32)
        if self.enumerated:
            # every sign pattern once (the first row's sign fixed on a symmetric grid)
            free = nrow - int(self._fixed_first)
            k = (1 - 2 * (np.arange(a, b)[:, None] >> np.arange(free)[None, :] & 1))
            if self._fixed_first:
                k = np.concatenate([np.ones((b - a, 1), k.dtype), k], axis=1)
            return k.astype(np.float32)
        return (1 - 2 * rng.integers(0, 2, (b - a, nrow))).astype(np.float32)

    def _tail(self):
        """``(u, beta)``: the exponential tail ``P(T > t) = 0.1 exp(-(t - u) / beta)`` fitted
        to the draws' upper decile (``u`` the 90 % quantile, ``beta`` the mean excess), the
        tail of a maximum of chi-square-like variables."""
        draws = self.draws
        u0 = float(np.quantile(draws, 0.9))
        return u0, float(np.mean(draws[draws > u0] - u0))

    def threshold(self, pfa):
        """Threshold of the grid-maximised statistic at global false-alarm *pfa*.

        Read from the draws when at least `exceedances` of them lie above it;
        beyond, from the exponential tail fitted to the draws' upper decile. On
        Monte-Carlo draws the fitted tail is the more precise of the two: the
        order statistic near P_FA rests on ``P_FA x n_draws`` draws, the fit on
        a tenth of them all (measured in ``docs/figures/measure_null_draws.py``).
        """
        pfa = check_probability(pfa, "P_FA")
        draws = self.draws
        if pfa * len(draws) >= self.exceedances:
            return float(np.quantile(draws, 1 - pfa, method="higher"))
        u0, beta = self._tail()
        xi = u0 + beta * np.log(0.1 / pfa)
        log.debug("global P_FA %.1e: threshold %.3f from the exponential tail of %d draws",
                  pfa, xi, len(draws))
        return float(xi)

    @property
    def exceedances(self):
        """Fewest draws above a level for it to be read from the draws directly:
        100 for Monte-Carlo draws, 10 for an enumerated (exact) law."""
        return TAIL_EXCEEDANCES["enumerated" if self.enumerated else "monte-carlo"]

    def pfa(self, t, *, return_method=False):
        """Global false-alarm probability of local statistics *t*.

        The fraction of H0 maxima at or above *t* where at least `exceedances`
        draws are; beyond (never the ``1/draws`` floor), the exponential tail of
        `threshold`. With *return_method*, also a
        boolean array, True where the tail was used.
        """
        draws = self.draws
        t = np.asarray(t, float)
        tt = np.nan_to_num(t, nan=-np.inf)
        above = len(draws) - np.searchsorted(draws, tt, side="left")
        out = (above + 1) / (len(draws) + 1)
        tail = above < self.exceedances
        if np.any(tail):
            u0, beta = self._tail()
            with np.errstate(over="ignore", under="ignore"):
                # floored where double precision (and any model of the tail) ends
                out = np.where(tail, np.maximum(0.1 * np.exp(-(tt - u0) / beta), PFA_FLOOR),
                               out)
        out = np.where(np.isnan(t), np.nan, out)
        return (out, tail & np.isfinite(t)) if return_method else out


class CombinedNull:
    """The more conservative of several nulls of the same statistic, level by level.

    `threshold` is the largest of their thresholds and `pfa` the largest of
    their false-alarm probabilities, so that a false alarm is controlled when
    any one of them describes the data. *noise_rows* are the rows fits take
    their errors from (default: the first null's); the form is the first's.
    `search_null` builds it.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel, NullCalibration
    >>> from kpifs.detect.null import CombinedNull
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> a = NullCalibration(dm, n_draws=2000, seed=1)
    >>> b = NullCalibration(dm, n_draws=2000, seed=2)
    >>> both = CombinedNull([a, b])
    >>> both.threshold(0.05) == max(a.threshold(0.05), b.threshold(0.05))
    True
    """

    def __init__(self, nulls, *, noise_rows=None):
        self.nulls = list(nulls)
        if not self.nulls:
            raise KpifsError("no null to combine")
        first = self.nulls[0]
        self.form, self.model = first.form, first.model
        self.noise_rows = first.noise_rows if noise_rows is None else noise_rows

    def threshold(self, pfa):
        """Largest threshold of the nulls at global false-alarm *pfa*."""
        return max(n.threshold(pfa) for n in self.nulls)

    def noise_draws(self, kind="Z2"):
        """The first null's `NullCalibration.noise_draws`."""
        return self.nulls[0].noise_draws(kind)

    def pfa(self, t, *, return_method=False):
        """Largest global false-alarm probability of *t* (with *return_method*, True
        where that of the null giving it was extrapolated from its tail)."""
        out = [n.pfa(t, return_method=True) for n in self.nulls]
        p = np.stack([o[0] for o in out])
        k = np.argmax(np.nan_to_num(p, nan=-1.0), axis=0)
        best = np.take_along_axis(p, k[None], 0)[0]
        tail = np.take_along_axis(np.stack([o[1] for o in out]), k[None], 0)[0]
        return (best, tail) if return_method else best


def search_null(model, *, form, noise_rows, block_rows=None, method="auto",
                n_draws=DEFAULT_DRAWS, seed=0, spectrum=None, progress=False, source="data",
                also=()):
    """The null a search judges its maxima by, and how it was made.

    *method* ``'gaussian'``: the Monte-Carlo null of the error model
    (*noise_rows*); ``'empirical'``: the sign-flip null of *block_rows* (every
    sign pattern when there are at most `EMPIRICAL_DRAWS`, else that many random
    ones); ``'both'``: the more conservative of the two at every level
    (`CombinedNull`); ``'auto'``: 'both' when there are enough block rows, else
    'gaussian'. Fits take their errors from *noise_rows* whichever the method.
    Returns ``(null, parts)``, *parts* a dict of the nulls by name; *source*
    names the data in errors; *also* the other tests drawn in the same pass
    (`NullCalibration`).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> from kpifs.detect.null import search_null
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas, min_sep=20 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None], grid)
    >>> blocks = np.random.default_rng(0).standard_normal((12, 1, km.n_kp)) / 12 ** 0.5
    >>> null, parts = search_null(dm, form="B", noise_rows=None, block_rows=blocks,
    ...                           n_draws=2000)
    >>> sorted(parts), parts["empirical"].n_draws        # 2**11 sign patterns, all of them
    (['empirical', 'gaussian'], 2048)
    >>> null.threshold(0.01) == max(p.threshold(0.01) for p in parts.values())
    True
    """
    if method not in NULL_METHODS:
        raise KpifsError(f"unknown null {method!r}: use one of {NULL_METHODS}")
    usable = block_rows is not None and len(block_rows) >= MIN_SIGN_ROWS
    if method == "auto":
        method = "both" if usable else "gaussian"
    if method != "gaussian" and not usable:
        raise KpifsError(f"{source}: no time blocks of the stars' frames (KP-BLKROWS, written "
                         f"when kpifs calibrates frames; at least {MIN_SIGN_ROWS} in all): the "
                         f"{method!r} null cannot be drawn; use null='gaussian' (--null gaussian)")
    if method == "gaussian":
        null = NullCalibration(model, form=form, n_draws=n_draws, seed=seed, spectrum=spectrum,
                               noise_rows=noise_rows, progress=progress, also=also)
        return null, {"gaussian": null}
    parts = {}
    if method == "both":
        if _via_rows(noise_rows, getattr(model, "dim", model.kernel_model.n_kp)):
            model.row_projections(noise_rows, also=(block_rows,))     # one pass for both
        parts["gaussian"] = NullCalibration(model, form=form, n_draws=n_draws, seed=seed,
                                            spectrum=spectrum, noise_rows=noise_rows,
                                            progress=progress, also=also)
    parts["empirical"] = NullCalibration(model, form=form, n_draws=EMPIRICAL_DRAWS, seed=seed,
                                         spectrum=spectrum, noise_rows=block_rows,
                                         coefficients="sign", also=also)
    return CombinedNull(list(parts.values()), noise_rows=noise_rows), parts
