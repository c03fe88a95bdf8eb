"""Searching spectral-differential kernel phases (issue 39; `kpifs.calibration.spectral_diff`).

Data carrying nuisance profiles along the channels (``kpd.spectral``) are
searched in the ``k = q - m`` channel combinations free of them: the kernel
phases of combination ``k`` are ``d_k = sum_c V[c, k] kp_c / s_c`` (``s_c``:
channel ``c``'s noise scale; `~kpifs.calibration.spectral_diff.kept_combinations`),
whitened combination by combination in that kept space (``k p`` degrees of
freedom). A companion of contrasts ``c a_c`` (``a``: its spectrum shape, flat by
default) has, in combination ``k``, the signature ``c sum_c V[c, k] a_c K
sin(theta_c) / s_c``: the projection acts on data, noise and signatures alike
(DESIGN.md section 8), and the search, its null, the limits and the fits all
see the same combinations, each with the companion's one contrast scale; a
candidate's fit then measures its contrast in every channel through the
combinations (`SpectralStack.spectrum_model`,
`~kpifs.detect._blockfit.fit_spectrum`). What the projection
leaves of a companion is measured (``info['retained']``, by separation) with the
separation from which half of it is left
(`~kpifs.calibration.spectral_diff.inner_separation`); the grid is not cut there:
the limits carry the self-subtraction.
"""
import hashlib
import logging

import numpy as np
from astropy import units as u

from ..calibration.spectral_diff import kept_combinations, retained_by_separation
from .._utils import thread_map
from ..covariance import whiten, whitening_matrix
from ..exceptions import KpifsError
from ..model.kernel import MAS
from ..simulation.aberrations import fit_static_amplitudes, leading_static_rows, \
    static_residual_rows
from ._blockfit import refine_stack
from ._signatures import _unit
from .combinations import combination_contrasts, combination_table, distinct_contrasts, \
    nominal_wavelengths
from .maps import UNIT_CACHE_BYTES, DetectionModel
from .sky import sky_to_detector
from .spectral import spectrum_shape

__all__ = ["SpectralModel", "SpectralStack", "static_term_rows", "static_term_groups",
           "compact_rows"]

log = logging.getLogger(__name__)

#: Position angles per separation at which the retained fraction is measured.
RETAINED_ANGLES = 16
#: Random screens of the static term (`SpectralStack`): not those of the profiles
#: (`kpifs.workflow` images seed 0), so that what the profiles leave of them is not
#: fitted on themselves.
STATIC_SEED = 1
#: The static term's groups, each with its own amplitude (`static_term_groups`): the
#: imaged residual of screens of these spatial spectra (the ``cutoff`` of
#: `~kpifs.simulation.simulate.phase_screens`, cycles/m: None, its AO-corrected default,
#: damped below the AO's frequencies; 1e-9, undamped: an uncorrected aberration, mostly
#: of low order), group ``g`` of seed ``STATIC_SEED + g``.
STATIC_SPECTRA = (None,)
#: Screens imaged per group of the static term.
STATIC_TERM_SCREENS = 200
#: The static term's rows kept: singular values above this fraction of the largest.
STATIC_FLOOR = 1e-4
#: Grid positions whose signatures are made at a time (channels x positions x kernel
#: phases in memory).
NORM_CHUNK = 256
#: Largest data (values) whose detection maps `SpectralModel.dot_maps` keeps for reuse.
DOT_MEMO_SIZE = 16 * 1024


class SpectralModel(DetectionModel):
    """`~kpifs.detect.DetectionModel` of channel combinations: combination ``k``'s
    signature is ``sum_c mixing[k, c] K sin(theta_c)`` whitened by ``whitening[k]``.

    Parameters
    ----------
    kernel_model, grid, pixscale, window, dof, detpa, basis
        As `~kpifs.detect.DetectionModel`.
    wavelengths : `~astropy.units.Quantity` (q,)
        The channels' wavelengths.
    whitening : ndarray (k, p, p)
        The combinations' whitening.
    mixing : ndarray (k, q)
        Each combination's weights on the channels' signatures.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect.sdk import SpectralModel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas)
    >>> mix = np.array([[1.0, -1.0]]) / np.sqrt(2)          # one combination of two channels
    >>> dm = SpectralModel(km, [1.6, 2.2] * u.um, np.eye(km.n_kp)[None], mix, grid)
    >>> dm.norm2.shape
    (1, 21, 21)
    """

    def __init__(self, kernel_model, wavelengths, whitening, mixing, grid, *, pixscale=None,
                 window=None, dof=None, detpa=None, basis=None):
        real = np.atleast_1d(u.Quantity(wavelengths, u.um))
        mix = np.asarray(mixing, float)
        self._real = real
        self._mix = mix
        nominal = nominal_wavelengths(mix, real)          # labels only
        self._init = True
        super().__init__(kernel_model, nominal, whitening, grid, pixscale=pixscale,
                         window=window, dof=dof, detpa=detpa,
                         basis=np.ones((len(mix), 1)) if basis is None else basis)

    def _channel_wavelengths(self):
        return self._real

    def _axis_trig(self, lam):
        # called once per combination by the parent: the channels' factors are made once
        if self.__dict__.pop("_init", False):
            self._channel_trig = [super(SpectralModel, self)._axis_trig(v)
                                  for v in self._real.to_value(u.m)]
        return None

    def _channel_sin(self, c, rows):
        return self._sin_from(self._channel_trig[c], rows)

    def _sin_rows(self, i, rows):
        out = 0.0
        for c, w in enumerate(self._mix[i]):
            if w != 0:
                out = out + w * self._channel_sin(c, rows)
        return out

    def _project(self, g, i):
        """``-sum_uv sin(theta) g`` of combination *i* (the channels' weighted sum)."""
        m = len(g)
        a = 0.0
        for c, w in enumerate(self._mix[i]):
            for sx, cx, sy, cy, wt in (self._channel_trig[c] if w != 0 else ()):
                nx, nuv = sx.shape
                gw = (w * wt) * g
                a = a + (sx[None] * gw[:, None, :]).reshape(m * nx, nuv) @ cy.T
                a = a + (cx[None] * gw[:, None, :]).reshape(m * nx, nuv) @ sy.T
        return -a.reshape(m, nx, -1).transpose(0, 2, 1)

    def _channel_sins(self, rows):
        """``sin(theta_c)`` of every channel at flat grid positions *rows*, (q, n, nuv): the
        parent's separable products (`_sin_from`, the same operations), written in place
        from slices of the x factors along each grid row (no gathered copies); with
        several poses, the parent's."""
        q = len(self._real)
        if any(len(t) != 1 or t[0][4] != 1.0 for t in self._channel_trig):
            return np.stack(thread_map(lambda c: self._channel_sin(c, rows), range(q)))
        iy, ix = np.divmod(rows, self.grid.shape[1])
        cuts = np.flatnonzero((np.diff(iy) != 0) | (np.diff(ix) != 1)) + 1
        runs = list(zip(np.r_[0, cuts], np.r_[cuts, len(rows)]))
        nuv = self._channel_trig[0][0][0].shape[1]
        out = np.empty((q, len(rows), nuv))

        def channel(c):
            sx, cx, sy, cy, _ = self._channel_trig[c][0]
            o = out[c]
            tmp = np.empty((max(b - a for a, b in runs), nuv))
            for a, b in runs:
                xs, y = slice(ix[a], ix[a] + b - a), iy[a]
                np.multiply(sx[xs], cy[y], out=o[a:b])
                o[a:b] += np.multiply(cx[xs], sy[y], out=tmp[:b - a])
        thread_map(channel, range(q))
        return out

    def _signature_norms(self):
        """As `~kpifs.detect.DetectionModel`'s, chunk by chunk: the channels' ``sin(theta_c)``
        once, mixed into the combinations in uv space (one matrix product), then each
        combination's through its lift ``K^T W_k^T`` (one product per combination, as
        many as without the projection, instead of one per channel and then the
        whitening). Only on the searched positions (``grid.valid``; NaN elsewhere, where
        every map and product of the search is NaN): a fifth fewer on the CHARIS grid."""
        k, p = len(self.wavelengths), self.kernel_model.n_kp
        q, n = len(self._real), self.grid.valid.size
        keep, mirrored, rows = self._norm_rows()
        rows = rows[self.grid.valid.ravel()[rows]]          # the searched positions: NaN off
        cache = k * len(keep) * p * 4 <= UNIT_CACHE_BYTES
        at = np.searchsorted(rows, keep) if not mirrored else np.arange(len(keep))
        unit = np.empty((k, len(keep), p), np.float32) if cache else None
        wf = self._wfac.ravel()[keep]
        out = np.full((k, n), np.nan)
        for a in range(0, len(rows), NORM_CHUNK):
            chunk = rows[a:a + NORM_CHUNK]
            sins = self._channel_sins(chunk)
            mixed = (self._mix @ sins.reshape(q, -1)).reshape(k, len(chunk), -1)
            sel = (at >= a) & (at < a + len(chunk))

            def combination(i):
                white = mixed[i] @ self._lift[i]                                # (n, p)
                raw = np.einsum("np,np->n", white, white)
                out[i, chunk] = raw
                if cache:
                    unit[i, sel] = _unit(white[at[sel] - a], raw[at[sel] - a], wf[sel])
            thread_map(combination, range(k))
        if mirrored:
            out[:, n - 1 - rows] = out[:, rows]
        if cache:
            self._unit_cache = (keep, unit)
            # dot_maps from the unit signatures: ||s|| at the positions kept
            self._amp = np.sqrt(out[:, keep]) * wf
            self._mirrored = mirrored
        return out.reshape((k,) + self.grid.shape) * self._wfac[None] ** 2

    def dot_maps(self, y):
        """As `~kpifs.detect.DetectionModel.dot_maps`; from the cached unit signatures
        (positions x kernel phases per combination) when they are kept, instead of one
        projection per channel and combination. The search, its noise maps and its
        products project the same data several times: the last few data sets' maps
        are kept (copies returned)."""
        cached = self.__dict__.get("_unit_cache")
        if cached is None or "_amp" not in self.__dict__:
            return super().dot_maps(y)
        y = np.asarray(y, float)
        if y.size > DOT_MEMO_SIZE:
            return self._dot_unit(y, *cached)
        memo = self.__dict__.setdefault("_dot_memo", {})
        key = (y.shape, hashlib.sha1(np.ascontiguousarray(y).tobytes()).hexdigest())
        if key not in memo:
            memo[key] = self._dot_unit(y, *cached)
            while len(memo) > 4:
                memo.pop(next(iter(memo)))
        return memo[key].copy()

    def _dot_unit(self, y, keep, unit):
        """The maps of whitened data *y* (..., k, p) from the unit signatures *unit* of the
        positions *keep* (and their mirror images)."""
        lead = y.shape[:-2]
        yb = y.reshape((-1,) + y.shape[-2:])
        m, q = len(yb), len(self.wavelengths)
        ny, nx = self.grid.shape
        out = np.zeros((m, q, ny * nx))
        for i in range(q):
            amp = self._amp[i]
            with np.errstate(invalid="ignore"):
                d = (yb[:, i].astype(np.float32) @ unit[i].T).astype(float) * amp
            d = np.where(amp > 0, d, 0.0)
            out[:, i, keep] = d
            if self._mirrored:                  # the signature at -pos is minus that at pos
                out[:, i, ny * nx - 1 - keep] = -d
        return out.reshape(lead + (q, ny, nx))

    def key(self):
        if "_digest" not in self.__dict__:
            base = super().key()
            h = hashlib.sha1(base.encode())
            h.update(np.ascontiguousarray(self._mix).tobytes())
            h.update(np.ascontiguousarray(self._real.value).tobytes())
            self._digest = h.hexdigest()
        return self._digest


_STATIC_CACHE = {}


def static_term_groups(kpd):
    """The static term's groups of channel rows, a list of (n_g, q, p), one amplitude
    each (`SpectralStack`): the product's own (``kpd.spectral['static_rows']``, imaged
    once when the product was made, split by ``kpd.spectral['static_groups']``, the
    groups' sizes; one group without), else
    `~kpifs.simulation.aberrations.static_residual_rows` of its pupil, channels, pixels
    and window for each of `STATIC_SPECTRA` (screens of seed ``STATIC_SEED + g``), the
    last ones kept (a sequence searched again: injections, a batch of the same
    instrument)."""
    sdk = getattr(kpd, "spectral", None) or {}
    own = sdk.get("static_rows")
    if own is not None:
        own = np.asarray(own, float)
        sizes = sdk.get("static_groups")
        if sizes is None:
            return [own]
        return np.split(own, np.cumsum(np.asarray(sizes, int))[:-1])
    h = hashlib.sha1(np.ascontiguousarray(kpd.kernel_model.kernel).tobytes())
    h.update(np.ascontiguousarray(kpd.wavelengths.to_value(u.m)).tobytes())
    h.update(repr((float(kpd.pixscale.to_value(u.mas)), kpd.meta.get("telescope"),
                   None if kpd.window is None else (kpd.window.size, repr(kpd.window)),
                   STATIC_SEED, STATIC_SPECTRA, STATIC_TERM_SCREENS)).encode())
    key = h.hexdigest()
    if key not in _STATIC_CACHE:
        _STATIC_CACHE.clear()
        _STATIC_CACHE[key] = [compact_rows(static_residual_rows(
            kpd.kernel_model, kpd.wavelengths, kpd.pixscale, window=kpd.window,
            telescope=kpd.meta.get("telescope"), seed=STATIC_SEED + g, cutoff=cut,
            n_screens=STATIC_TERM_SCREENS))
            for g, cut in enumerate(STATIC_SPECTRA)]
    return list(_STATIC_CACHE[key])


def static_term_rows(kpd):
    """The static term's channel rows (n, q, p) of *kpd*: `static_term_groups` one after
    the other, with the groups' sizes (a list) -- what a product keeps
    (``spectral['static_rows']`` and ``spectral['static_groups']``)."""
    groups = static_term_groups(kpd)
    return np.concatenate(groups), [len(r) for r in groups]


def compact_rows(rows, *, floor=STATIC_FLOOR):
    """Rows (n, q, p) as fewer rows with the same Gram matrix ``R^T R`` (their singular
    vectors times singular values), leaving out the directions below *floor* times the
    largest singular value (a variance below ``floor**2`` of the leading one): what the
    static term reads of them (its covariance and its leading modes) unchanged.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.sdk import compact_rows
    >>> r = np.random.default_rng(0).normal(size=(50, 2, 3))
    >>> c = compact_rows(r)
    >>> c.shape, bool(np.allclose(np.einsum("nqp,nrs->qprs", c, c),
    ...                           np.einsum("nqp,nrs->qprs", r, r)))
    ((6, 2, 3), True)
    """
    rows = np.asarray(rows, float)
    n = rows.shape[0]
    _, sv, vt = np.linalg.svd(rows.reshape(n, -1), full_matrices=False)
    keep = sv > floor * sv[0] if sv.size and sv[0] > 0 else np.zeros(sv.size, bool)
    return (sv[keep, None] * vt[keep]).reshape((-1,) + rows.shape[1:])


class SpectralStack:
    """Whitened channel combinations of a spectral-differential search, their noise rows,
    models and fits (the interface of `~kpifs.detect.blocks.BlockStack`: ``kp`` (k, p)
    is already whitened, its whitening the identity).

    Parameters
    ----------
    kpd : `~kpifs.KernelPhaseData`
        The data, with ``kpd.spectral`` (`~kpifs.calibration.spectral_diff`).
    kp : ndarray (q, p)
        Their kernel phases (one frame).
    cov : ndarray (q, p, p)
        Their covariance per channel.
    spectrum : array-like (q,), optional
        The companion's contrast shape (flat by default).
    poses : tuple, optional
        ``(angles, weights)`` of a sky search (`~kpifs.detect.sky.pa_bins`).
    static : {'auto', 'none'}, ndarray (n, q, p) or list of them, optional
        The static residual's term, its amplitudes fitted in the combinations (one per
        group, jointly): 'auto' for data with no calibrator, from the imaged static
        residual (`static_term_groups`); 'none' leaves it out; or the channel rows to
        fit (one group), or a list of groups of rows.
    normalise : {'auto', 'none'}, optional
        'auto': with no calibrator, each combination's covariance scaled to the
        variance its covariance rows hold.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.calibration.spectral_diff import nuisance_profiles
    >>> from kpifs.detect.sdk import SpectralStack
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> kp, cov = np.zeros((8, km.n_kp)), np.stack([np.eye(km.n_kp)] * 8)
    >>> kpd = KernelPhaseData(kp[None], np.linspace(1.2, 2.3, 8) * u.um, 16.2 * u.mas, km,
    ...                       covariance=cov)
    >>> kpd.spectral = {"profiles": nuisance_profiles(kpd, order=2)}
    >>> st = SpectralStack(kpd, kp, cov)
    >>> st.kp.shape, int(st.rank.sum()) == 5 * km.n_kp
    ((5, 37), True)
    """

    mode = "spectral-differential"

    def __init__(self, kpd, kp, cov, *, spectrum=None, poses=None, static="auto",
                 normalise="auto"):
        self.kpd, self.poses = kpd, poses
        self.static_amplitude = self.static_amplitudes = self.rows_variance = None
        q, p = kp.shape
        prof = np.asarray(kpd.spectral["profiles"], float)
        cov = np.asarray(cov, float)
        var = np.trace(cov, axis1=1, axis2=2) / p
        self.scale = np.sqrt(np.where(var > 0, var, np.max(var)))
        self.combinations = v = kept_combinations(prof, self.scale)         # (q, k)
        self.data_mixing = (v / self.scale[:, None]).T                       # (k, q)
        self.spectrum = spectrum_shape(spectrum, q)
        self.mixing = self.data_mixing * self.spectrum[None]
        k = v.shape[1]
        y = self.data_mixing @ kp
        static = self._whitening(cov, y, static, normalise)
        #: what the profiles leave of the static residual at its fitted amplitude (n, k, p),
        #: in the combinations, unwhitened (None: no static term)
        self.static_rows = static
        self.kp = whiten(y, self._w)
        self.rows = self._rows(kpd.covariance_rows)
        if static is not None and self.rows is not None:
            self.rows = np.concatenate([self.rows, whiten(static, self._w)])
        self.block_rows = self._rows(kpd.block_rows)
        self.whitening = np.broadcast_to(np.eye(p), (k, p, p))
        self.basis = np.ones((k, 1))
        self.n_comb = k
        self.inner = float("nan")
        self.info = {"mode": self.mode, "basis": kpd.spectral.get("basis"),
                     "profiles": int(prof.shape[1]), "combinations": int(k),
                     "dof": int(self.rank.sum()), "static_amplitude": self.static_amplitude,
                     "static_amplitudes": self.static_amplitudes,
                     "rows_variance": None if self.rows_variance is None else
                     round(float(np.median(self.rows_variance)), 4)}
        log.info("%s: spectral-differential search: %d profile(s) out of %d channels, %d "
                 "combinations", kpd.name, prof.shape[1], q, k)

    def _whitening(self, cov, y, static, normalise):
        """Each combination's whitening (``self._w``, ``self.rank``) from its channels'
        covariances *cov* summed; with no calibrator (*normalise* 'auto') scaled to the
        variance its covariance rows hold, and with the static term (`_static_term`,
        fitted to the combinations *y*), which is returned (None without)."""
        kpd = self.kpd
        # what the channels share (most of a static or drifting aberration cancels in a
        # combination, not all of it) reaches the null and the limits by the covariance
        # rows (`_rows`); measured on CHARIS simulations, whitening with the rows' own
        # (shrunk) covariance of each combination gives a less sensitive search
        ccov = np.tensordot(self.data_mixing ** 2, cov, axes=(1, 0))
        w, rank = whitening_matrix(ccov, return_rank=True,
                                   source="covariance of the channel combinations")
        rank = np.atleast_1d(rank)
        frames = not kpd.meta.get("calibrated", True) and kpd.covariance_rows is not None
        if normalise not in ("auto", "combination", "none"):
            raise KpifsError(f"normalise must be 'auto', 'combination' or 'none', got "
                             f"{normalise!r}")
        if normalise != "none" and frames:
            # the shrunk sum holds more variance than the frames' rows (20 frames for
            # hundreds of kernel phases): scaled to the rows', the data's reduced
            # chi-square reads the rows' scale, and the noise scale measured on the
            # data acts when they scatter more (a static residual, a drift)
            g = np.sum(self._rows(kpd.covariance_rows, w) ** 2, axis=(0, 2))
            f = np.where(g > 0, g / np.maximum(rank, 1), 1.0)
            if normalise == "auto":
                f = np.full_like(f, np.sum(g) / max(np.sum(rank), 1))
            ccov, w = ccov * f[:, None, None], w / np.sqrt(f)[:, None, None]
            self.rows_variance = f
        static = self._static_term(y, w, static, frames)
        if static is not None:
            # what the profiles leave of the static residual, at its fitted amplitude:
            # in each combination's whitening, and (across combinations) in the rows
            ccov = ccov + np.matmul(static.transpose(1, 2, 0), static.transpose(1, 0, 2))
            w, rank = whitening_matrix(ccov, return_rank=True,
                                       source="covariance of the channel combinations")
        self._w, self.rank = w, np.atleast_1d(rank)
        return static

    def _static_term(self, y, w, how, frames):
        """The static residual's rows in the combinations (n, k, p), each group's scaled by
        its maximum-likelihood amplitude, fitted jointly to the combinations *y* (k, p)
        whitened by *w* (`~kpifs.simulation.aberrations.fit_static_amplitudes`, on each
        group's leading modes): with *how* 'auto', for a product with no calibrator
        (the frames' scatter holds nothing static, and the profiles do not remove all
        of it), from `static_term_groups` (aberrations of several spatial spectra);
        with rows (n, q, p), from those (one group), or a list of them (groups); None
        with 'none' or all amplitudes 0."""
        kpd = self.kpd
        if isinstance(how, str):
            if how not in ("auto", "none"):
                raise KpifsError(f"static must be 'auto', 'none' or rows, got {how!r}")
            if how == "none" or not frames:
                return None
            how = static_term_groups(kpd)
        groups = [np.asarray(r, float) for r in
                  ([how] if isinstance(how, np.ndarray) and how.ndim == 3 else how)]
        shape = (len(self.scale), y.shape[1])
        if any(r.shape[1:] != shape for r in groups):
            # the imaged residual lost uv points the data keep (beyond Nyquist at the
            # short wavelengths): no term rather than a wrong one
            log.info("%s: static term left out: its rows have shape %s, the data (%d, %d)",
                     kpd.name, [r.shape[1:] for r in groups], *shape)
            return None
        rows = [np.einsum("kc,ncp->nkp", self.data_mixing, r) for r in groups]
        a = fit_static_amplitudes(y, w, [leading_static_rows(r, w) for r in rows])
        self.static_amplitudes = [float(v) for v in a]
        self.static_amplitude = float(a[0])
        log.info("%s: spectral-differential static term: amplitude(s) %s", kpd.name,
                 ", ".join(f"{v:.3g}" for v in a))
        keep = [r * np.sqrt(v) for r, v in zip(rows, a) if v > 0]
        return np.concatenate(keep) if keep else None

    @property
    def combination_whitening(self):
        """Each combination's whitening (k, p, p): its channels' covariances summed, with
        no calibrator scaled to its rows' variance and with the static term."""
        return self._w

    def _rows(self, rows, w=None):
        if rows is None:
            return None
        return whiten(np.einsum("kc,ncp->nkp", self.data_mixing, rows),
                      self._w if w is None else w)

    def detection_model(self, grid, *, basis=None):
        """The `SpectralModel` on *grid*; what the projection keeps of a companion is
        measured by separation (``info['retained']``) with the inner separation where
        half of it is left (``self.inner``, ``info['inner_separation']``)."""
        kpd = self.kpd
        model = SpectralModel(kpd.kernel_model, kpd.wavelengths, self._w, self.mixing, grid,
                              pixscale=kpd.pixscale, window=kpd.window, dof=self.rank,
                              detpa=self.poses, basis=self.basis)
        self._retained(grid)
        return model

    def _retained(self, grid):
        out = retained_by_separation(self.kpd.kernel_model, self.kpd.wavelengths, grid,
                                     self.combinations, spectrum=self.spectrum,
                                     scale=self.scale, angles=RETAINED_ANGLES)
        self.inner = out["inner_separation"]
        self.info.update(out)

    def _exponentials(self, pos):
        """``exp(-i theta)`` of a companion at *pos* (mas, the search's frame) per pose,
        channel and uv point (n, q, nuv), and the poses' weights (n,)."""
        kpd = self.kpd
        lam = kpd.wavelengths.to_value(u.m)
        if self.poses is None:
            xy, wts = np.array([[float(pos[0]), float(pos[1])]]), np.ones(1)
        else:
            ang, wts = np.asarray(self.poses[0], float), self.poses[1]
            wts = np.ones(ang.size) if wts is None else np.asarray(wts, float)
            xy = np.column_stack(sky_to_detector(float(pos[0]), float(pos[1]), ang))
        theta = 2 * np.pi * MAS * (xy @ kpd.kernel_model.uv.value.T)          # (n, nuv)
        return np.exp(-1j * theta[:, None, :] / lam[None, :, None]), wts / wts.sum()

    def model_kp(self, pos, contrast, *, derivative=False):
        """Whitened model (k, p) of a companion at *pos* (mas, the search's frame) with one
        contrast scale per combination (*contrast*, (k,), window included); with
        *derivative*, also its derivative with respect to each (k, p)."""
        km = self.kpd.kernel_model
        h, wts = self._exponentials(pos)
        ca, at = distinct_contrasts(contrast, self.spectrum, self.n_comb)    # (u, q)
        z = 1 + ca[None, :, :, None] * h[:, None]                            # (n, u, q, nuv)
        phase = (np.tensordot(wts, np.angle(z), axes=(0, 0)) @ km.kernel.T)[at]   # (k, q, p)
        out = whiten(np.einsum("kc,kcp->kp", self.data_mixing, phase), self._w)
        if not derivative:
            return out
        dz = np.imag(self.spectrum[None, :, None] * h[:, None] / z)
        dphase = (np.tensordot(wts, dz, axes=(0, 0)) @ km.kernel.T)[at]
        return out, whiten(np.einsum("kc,kcp->kp", self.data_mixing, dphase), self._w)

    def spectrum_model(self, pos, contrasts):
        """Whitened model (k, p) of a companion at *pos* with a contrast of its own in
        every channel (*contrasts* (q,), window included), and its derivatives with
        respect to each channel's contrast (q, k, p): its spectrum measured through the
        combinations (`~kpifs.detect._blockfit.fit_spectrum`)."""
        kern = self.kpd.kernel_model.kernel
        h, wts = self._exponentials(pos)
        z = 1 + np.asarray(contrasts, float)[None, :, None] * h                  # (n, q, nuv)
        phase = np.tensordot(wts, np.angle(z), axes=(0, 0)) @ kern.T             # (q, p)
        dphase = np.tensordot(wts, np.imag(h / z), axes=(0, 0)) @ kern.T
        out = whiten(self.data_mixing @ phase, self._w)
        return out, whiten(self.data_mixing.T[:, :, None] * dphase[:, None, :], self._w)

    def _attenuation(self, x, y):
        kpd = self.kpd
        if kpd.window is None:
            return 1.0
        return float(kpd.window.at(np.hypot(x, y), kpd.pixscale))

    def refine(self, cands, residual, noise_rows=None, box=20.0):
        """Fit each candidate's position and contrast scales to the combinations (in
        place, as `~kpifs.detect.fit.refine_candidates`); returns the fitted models."""
        return refine_stack(self, cands, residual, noise_rows, box)

    def channel_contrasts(self, c, cerr):
        """The combinations' contrast maps (k, ny, nx) and errors as the channels' (q, ...):
        their weighted mean (the companion's one scale) times the spectrum shape
        (`~kpifs.detect.combinations.combination_contrasts`)."""
        return combination_contrasts(self.spectrum, c, cerr)

    def channel_table(self, cands):
        """The candidates' per-combination contrast columns as per-channel ones (in place;
        `~kpifs.detect.combinations.combination_table`)."""
        combination_table(self.spectrum, self.n_comb, cands)
