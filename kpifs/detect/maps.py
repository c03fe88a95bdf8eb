"""Detection maps over a grid of companion positions.

For a companion at ``(alpha, beta)`` the first-order whitened signature in
channel ``i`` is ``s_i = w(alpha, beta) W_i K sin(-theta_i)`` with
``theta_i = 2 pi (alpha u + beta v) / lambda_i`` and ``w`` the extraction
window's value there (so that contrasts are the companion's true ones). For
data ``y_i``:

- ``s_i^T y_i = -w sin(theta_i)^T g_i`` with ``g_i = K^T W_i^T y_i``; over a
  rectangular grid ``sin(theta_x + theta_y) = sin theta_x cos theta_y + cos
  theta_x sin theta_y`` makes the whole map two matrix products;
- ``||s_i||^2 = w^2 sin(theta_i)^T (K^T W_i^T W_i K) sin(theta_i)`` depends only on
  the covariance: computed once per channel and reused for every data set and
  Monte-Carlo draw.

From these: ``z_i = s_i^T y_i / ||s_i||``, per-channel contrast estimates
``c_i = s_i^T y_i / ||s_i||^2`` with 1-sigma errors ``1 / ||s_i||``, and the local
binary statistic. The statistic maximised over the grid has no closed-form
law: `DetectionModel.calibrate` draws it under H0.
"""
import hashlib
import logging

import numpy as np
from astropy import units as u
from astropy.table import QTable

from .._utils import as_rng, to_quantity
from ..exceptions import KpifsError
from ..kernel import MAS
from ..prepare import window_at
from scipy import stats

from .stats import binary_pfa, binary_statistic, check_probability

__all__ = ["DetectionGrid", "DetectionModel"]

log = logging.getLogger(__name__)

# Monte-Carlo calibrations, most recent last; bounded so that a long-running
# process (a batch worker) does not accumulate them
_CALIBRATIONS = {}
_MAX_CALIBRATIONS = 32


class DetectionGrid:
    """A rectangular grid of companion offsets ``(alpha, beta)`` in mas.

    Parameters
    ----------
    x, y : `~astropy.units.Quantity`
        Grid coordinates along image x and y (1-D, uniformly spaced).
    min_sep, max_sep : `~astropy.units.Quantity`, optional
        Positions closer or farther than these are not searched.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.detect import DetectionGrid
    >>> g = DetectionGrid.from_separation(200 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    >>> g.shape, int(g.valid.sum())
    ((41, 41), 1232)
    """

    def __init__(self, x, y, *, min_sep=None, max_sep=None):
        self.x = np.atleast_1d(to_quantity(x, u.mas, name="grid x")).value.astype(float)
        self.y = np.atleast_1d(to_quantity(y, u.mas, name="grid y")).value.astype(float)
        if self.x.size < 2 or self.y.size < 2:
            raise KpifsError("a detection grid needs at least 2 points along each axis")
        self.min_sep = 0.0 if min_sep is None else to_quantity(min_sep, u.mas).value
        self.max_sep = np.inf if max_sep is None else to_quantity(max_sep, u.mas).value
        self.X, self.Y = np.meshgrid(self.x, self.y)
        self.sep = np.hypot(self.X, self.Y)
        self.valid = (self.sep >= self.min_sep) & (self.sep <= self.max_sep) & (self.sep > 0)
        if not self.valid.any():
            raise KpifsError("the detection grid has no valid position")

    @classmethod
    def from_separation(cls, max_sep, step, *, min_sep=None):
        """A square grid of half-width *max_sep* and spacing *step*, searched out to *max_sep*."""
        max_sep = to_quantity(max_sep, u.mas, name="maximum separation").value
        step = to_quantity(step, u.mas, name="grid step").value
        if not (step > 0 and max_sep > step):
            raise KpifsError(f"grid step ({step} mas) must be > 0 and smaller than the maximum "
                             f"separation ({max_sep} mas)")
        n = int(np.floor(max_sep / step))
        c = np.arange(-n, n + 1) * step
        return cls(c * u.mas, c * u.mas, min_sep=min_sep, max_sep=max_sep * u.mas)

    @property
    def shape(self):
        return self.X.shape

    @property
    def step(self):
        return float(self.x[1] - self.x[0]), float(self.y[1] - self.y[0])

    def wcs(self):
        """A linear WCS from map pixels to offsets (mas) along image x and y."""
        from astropy.wcs import WCS
        w = WCS(naxis=2)
        w.wcs.ctype = ["OFFSET-X", "OFFSET-Y"]
        w.wcs.cunit = ["mas", "mas"]
        w.wcs.crpix = [1, 1]
        w.wcs.crval = [self.x[0], self.y[0]]
        w.wcs.cdelt = [self.x[1] - self.x[0], self.y[1] - self.y[0]]
        return w

    def key(self):
        return (self.x.tobytes(), self.y.tobytes(), self.min_sep, self.max_sep)


class DetectionModel:
    """Signatures, their norms and fast maps for one kernel model, covariance and grid.

    Parameters
    ----------
    kernel_model : `~kpifs.kernel.KernelModel`
    wavelengths : `~astropy.units.Quantity` (q,)
    whitening : ndarray, shape (q, p, p)
        Per-channel whitening operators (`~kpifs.covariance.whitening_matrix`).
    grid : `DetectionGrid`
    pixscale : `~astropy.units.Quantity`, optional
        With *window*, the extraction window ``(radius in pixels, order)``
        whose attenuation enters the signatures.
    window : tuple, optional
    dof : sequence of int, optional
        Whitened dimension kept per channel (for the energy detector).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.detect import DetectionGrid, DetectionModel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None] * 1e3, grid)
    >>> dm.local_statistic(np.zeros((1, km.n_kp))).shape
    (21, 21)
    """

    def __init__(self, kernel_model, wavelengths, whitening, grid, *, pixscale=None,
                 window=None, dof=None):
        self.kernel_model = kernel_model
        self.wavelengths = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
        w = np.asarray(whitening, float)
        q, p = len(self.wavelengths), kernel_model.n_kp
        if w.shape != (q, p, p):
            raise KpifsError(f"whitening operators of shape {w.shape}, expected ({q}, {p}, {p}) "
                             f"(one per channel)")
        self.whitening = w
        self.grid = grid
        self.dof = np.full(q, p) if dof is None else np.asarray(dof, int)
        self.pixscale = None if pixscale is None else to_quantity(pixscale, u.mas).value
        self.window = window if (window is not None and pixscale is not None) else None
        self._check_grid()
        self._wfac = window_at(grid.sep, self.pixscale, self.window)
        kern = kernel_model.kernel
        # L_i = K^T W_i^T maps whitened data to uv space: g_i = L_i y_i
        self._lift = np.einsum("kj,wik->wji", kern, w)              # (q, nuv, p)
        self._trig = [self._axis_trig(lam) for lam in self.wavelengths.to_value(u.m)]
        self.norm2 = self._signature_norms()                         # (q, ny, nx)

    # --- set-up -----------------------------------------------------------------
    def _check_grid(self):
        g = self.grid
        far = float(np.max(g.sep[g.valid]))
        lam_min = self.wavelengths.to_value(u.m).min()
        # signatures are periodic with the uv grid: beyond lambda / (2 step) positions alias
        step = self.kernel_model.pupil.step
        if step is not None:
            alias = lam_min / (2 * step.to_value(u.m)) / MAS
            if far > alias:
                raise KpifsError(f"the grid reaches {far:.0f} mas, beyond the aliasing limit "
                                 f"lambda_min / (2 x grid step) = {alias:.0f} mas of the "
                                 f"pupil model: reduce the maximum separation")
        if self.window is not None:
            edge = self.window[0] * self.pixscale * 1.5
            if far > edge:
                raise KpifsError(f"the grid reaches {far:.0f} mas, beyond the extraction "
                                 f"window (radius {self.window[0] * self.pixscale:.0f} mas): "
                                 f"reduce the maximum separation to < {edge:.0f} mas")

    def _axis_trig(self, lam):
        uv = self.kernel_model.uv.value
        tx = 2 * np.pi * np.outer(self.grid.x * MAS, uv[:, 0]) / lam    # (nx, nuv)
        ty = 2 * np.pi * np.outer(self.grid.y * MAS, uv[:, 1]) / lam    # (ny, nuv)
        return np.sin(tx), np.cos(tx), np.sin(ty), np.cos(ty)

    def _sin_rows(self, i, rows):
        """``sin(theta_i)`` at flat grid positions *rows* (npos, nuv)."""
        sx, cx, sy, cy = self._trig[i]
        nx = self.grid.shape[1]
        iy, ix = np.divmod(rows, nx)
        return sx[ix] * cy[iy] + cx[ix] * sy[iy]

    def _signature_norms(self):
        q = len(self.wavelengths)
        ny, nx = self.grid.shape
        out = np.zeros((q, ny * nx))
        rows = np.arange(ny * nx)
        for i in range(q):
            b = self._lift[i] @ self._lift[i].T        # K^T W^T W K (nuv, nuv)
            for a in range(0, len(rows), 2048):
                s = self._sin_rows(i, rows[a:a + 2048])
                out[i, a:a + 2048] = np.einsum("ij,ij->i", s @ b, s)
        return out.reshape(q, ny, nx) * self._wfac[None] ** 2

    # --- maps -------------------------------------------------------------------
    def dot_maps(self, y):
        """``s_i^T y_i`` over the grid for whitened data *y* (..., q, p) -> (..., q, ny, nx)."""
        y = np.asarray(y, float)
        lead = y.shape[:-2]
        yb = y.reshape((-1,) + y.shape[-2:])
        m = len(yb)
        ny, nx = self.grid.shape
        out = np.empty((m, len(self.wavelengths), ny, nx))
        for i in range(len(self.wavelengths)):
            g = yb[:, i] @ self._lift[i].T                                 # (m, nuv)
            out[:, i] = self._project(g, i)
        return (out * self._wfac).reshape(lead + out.shape[1:])

    def _project(self, g, i):
        """``-sum_uv sin(theta) g`` on the grid for uv-space vectors g (m, nuv)."""
        sx, cx, sy, cy = self._trig[i]
        m = len(g)
        nx, nuv = sx.shape
        a = (sx[None] * g[:, None, :]).reshape(m * nx, nuv) @ cy.T         # (m*nx, ny)
        a += (cx[None] * g[:, None, :]).reshape(m * nx, nuv) @ sy.T
        return -a.reshape(m, nx, -1).transpose(0, 2, 1)

    def z_maps(self, y):
        """Normalised projections ``z_i = s_i^T y_i / ||s_i||`` (N(0, 1) under H0)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.dot_maps(y) / np.sqrt(self.norm2)

    def contrast_maps(self, y):
        """Per-channel contrast estimates ``s^T y / ||s||^2`` and their 1-sigma errors."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.dot_maps(y) / self.norm2, 1 / np.sqrt(self.norm2)

    def _mf_weights(self, spectrum):
        """Matched-filter weights ``a_i ||s_i|| / ||s_a||`` per channel and position."""
        from .limits import spectrum_shape
        a = spectrum_shape(spectrum, len(self.wavelengths))
        amp = a[:, None, None] * np.sqrt(self.norm2)
        with np.errstate(invalid="ignore", divide="ignore"):
            return amp / np.sqrt(np.sum(amp ** 2, axis=0))

    def local_statistic(self, y, form="B", spectrum=None):
        """Detection statistic at each grid position (NaN outside the searched area).

        ``'B'``/``'B-paper'``: the binary test; ``'NP'``: the matched filter for a
        companion of the given spectrum shape and unknown amplitude,
        ``sum_i a_i s_i^T y_i / ||s_a||`` (N(0, 1) under H0).
        """
        return self._statistic(self.dot_maps(y), form, spectrum)

    def maps(self, y, form="B", spectrum=None):
        """Statistic, per-channel contrasts and their errors from one projection.

        Returns ``(statistic, contrast, contrast_err)`` as `local_statistic` and
        `contrast_maps` would, computing ``s_i^T y_i`` once.
        """
        d = self.dot_maps(y)
        with np.errstate(invalid="ignore", divide="ignore"):
            return self._statistic(d, form, spectrum), d / self.norm2, 1 / np.sqrt(self.norm2)

    def _statistic(self, dot, form, spectrum):
        with np.errstate(invalid="ignore", divide="ignore"):
            z = dot / np.sqrt(self.norm2)
        if form == "NP":
            t = np.sum(self._mf_weights(spectrum) * z, axis=-3)
        else:
            t = binary_statistic(np.moveaxis(z, -3, -1), form)
        return np.where(self.grid.valid, t, np.nan)

    def local_pfa(self, t, form="B"):
        """False-alarm probability of a local statistic at a known position."""
        if form == "NP":
            return stats.norm.sf(np.nan_to_num(t, nan=-np.inf))
        return binary_pfa(np.nan_to_num(t, nan=0.0), len(self.wavelengths), form)

    # --- Monte-Carlo calibration of the grid search -----------------------------
    def _key(self, form, n_draws, seed, spectrum=None, noise_rows=None):
        h = hashlib.sha1()
        for arr in (self.kernel_model.kernel, self.kernel_model.uv.value, self.whitening,
                    self.wavelengths.value, self._wfac):
            h.update(np.ascontiguousarray(arr).tobytes())
        for part in self.grid.key():
            h.update(repr(part).encode())
        h.update(f"{form}|{n_draws}|{seed}|{spectrum!r}".encode())
        if noise_rows is not None:
            h.update(np.ascontiguousarray(noise_rows).tobytes())
        return h.hexdigest()

    def _unit_signatures(self, rows):
        """Unit-norm whitened signatures at flat grid positions *rows*: (q, npos, p), float32."""
        q, p = len(self.wavelengths), self.kernel_model.n_kp
        out = np.empty((q, len(rows), p), np.float32)
        wf = self._wfac.ravel()[rows]
        for i in range(q):
            sig = -self._sin_rows(i, rows) @ self._lift[i]          # (npos, p)
            norm = np.sqrt(self.norm2[i].ravel()[rows]) / np.where(wf > 0, wf, 1)
            out[i] = sig / norm[:, None]
        return out

    def row_projections(self, noise_rows, *, chunk=512):
        """Whitened noise rows projected on the unit signatures at every valid position.

        Returns ``(rows_idx, Z)``: the flat indices of the valid positions and
        ``Z`` of shape (npos, nrow, q) with ``Z[k, r, i] = u_i(pos_k) . R_w[r, i]``,
        so that ``Z[k]^T Z[k]`` is the covariance of ``(z_1 ... z_q)`` at position
        ``k`` (channel correlations included).
        """
        rows = np.flatnonzero(self.grid.valid.ravel())
        nr = len(noise_rows)
        q = len(self.wavelengths)
        out = np.empty((len(rows), nr, q))
        for a in range(0, len(rows), chunk):
            unit = self._unit_signatures(rows[a:a + chunk]).astype(float)    # (q, n, p)
            for i in range(q):
                out[a:a + chunk, :, i] = (noise_rows[:, i, :] @ unit[i].T).T
        return rows, out

    def _half_positions(self):
        """Valid positions, split into a half and its mirror image when the grid allows."""
        g = self.grid
        rows = np.flatnonzero(g.valid.ravel())
        symmetric = (np.allclose(g.x, -g.x[::-1]) and np.allclose(g.y, -g.y[::-1])
                     and np.array_equal(g.valid, g.valid[::-1, ::-1]))
        if not symmetric:
            return rows, False
        x, y = g.X.ravel()[rows], g.Y.ravel()[rows]
        half = (y > 0) | ((y == 0) & (x > 0))
        return rows[half], True

    def calibrate(self, *, form="B", n_draws=30000, seed=0, batch=1000, progress=False,
                  spectrum=None, noise_rows=None):
        """Draws of the grid-maximised binary statistic under H0 (sorted).

        Under H0 the whitened data are standard normal, so ``z_i(pos)`` is the
        projection of a standard normal vector on the unit signature. A
        signature at ``-pos`` is minus that at ``pos``, so on a symmetric grid
        only half the positions are projected. Cached per (kernel model,
        whitening, grid, form, draws, seed, noise).

        With *noise_rows* (nrow, q, p), whitened rows whose Gram matrix is the
        covariance of the whitened data across channels, the draws are random
        combinations of the rows instead of independent channels: the
        correlation between channels (from achromatic aberrations, spectral
        cross-talk) is kept, which matters for multi-channel sums.
        """
        if form not in ("B", "B-paper", "NP"):
            raise KpifsError(f"unknown map test {form!r}: 'B', 'B-paper' or 'NP'")
        key = self._key(form, n_draws, seed, spectrum, noise_rows)
        if key in _CALIBRATIONS:
            _CALIBRATIONS[key] = _CALIBRATIONS.pop(key)        # most recently used
            return _CALIBRATIONS[key]
        rng = as_rng(seed)
        q, p = len(self.wavelengths), self.kernel_model.n_kp
        rows, mirrored = self._half_positions()
        unit = self._unit_signatures(rows)                            # (q, npos, p)
        if form == "NP":
            mfw = self._mf_weights(spectrum).reshape(q, -1)[:, rows].astype(np.float32)
        maxima = np.empty(n_draws)
        starts = range(0, n_draws, batch)
        if progress:
            try:
                from tqdm.auto import tqdm
                starts = tqdm(starts, desc=f"calibrating sup-{form}", unit="batch")
            except ImportError:
                pass
        for a in starts:
            b = min(n_draws, a + batch)
            t_pos = np.zeros((b - a, len(rows)), np.float32)
            t_neg = np.zeros_like(t_pos) if mirrored else None
            if noise_rows is not None:
                coef = rng.standard_normal((b - a, len(noise_rows)), dtype=np.float32)
                joint = coef @ noise_rows.reshape(len(noise_rows), -1).astype(np.float32)
                joint = joint.reshape(b - a, q, p)
            for i in range(q):
                if noise_rows is None:
                    eps = rng.standard_normal((b - a, p), dtype=np.float32)
                else:
                    eps = joint[:, i]
                z = eps @ unit[i].T
                if form == "NP":
                    t_pos += mfw[i] * z
                    continue
                zp = np.maximum(z, 0)
                t_pos += zp * zp if form == "B" else zp
                if mirrored:
                    zn = np.maximum(-z, 0)
                    t_neg += zn * zn if form == "B" else zn
            if form == "NP" and mirrored:
                t_neg = -t_pos
            best = t_pos.max(axis=1)
            if mirrored:
                best = np.maximum(best, t_neg.max(axis=1))
            maxima[a:b] = best
        maxima.sort()
        _CALIBRATIONS[key] = maxima
        while len(_CALIBRATIONS) > _MAX_CALIBRATIONS:
            _CALIBRATIONS.pop(next(iter(_CALIBRATIONS)))
        return maxima

    def global_threshold(self, pfa, **kwargs):
        """Threshold of the grid-maximised statistic at global false-alarm *pfa*.

        Read from the Monte-Carlo draws when they reach *pfa* (at least 10 draws
        above it); below that, extrapolated from an exponential fit to the
        draws' upper decile, ``P(T > t) = 0.1 exp(-(t - u) / beta)`` with ``u``
        the 90 % quantile and ``beta`` the mean excess (the tail of a maximum of
        chi-square-like variables), and logged as such.
        """
        pfa = check_probability(pfa, "P_FA")
        draws = self.calibrate(**kwargs)
        if pfa * len(draws) >= 10:
            return float(np.quantile(draws, 1 - pfa, method="higher"))
        u0 = float(np.quantile(draws, 0.9))
        beta = float(np.mean(draws[draws > u0] - u0))
        xi = u0 + beta * np.log(0.1 / pfa)
        log.info("global P_FA %.1e is below what %d draws reach: threshold %.3f extrapolated "
                 "from the exponential tail of the draws", pfa, len(draws), xi)
        return float(xi)

    def global_pfa(self, t, **kwargs):
        """Global false-alarm probability of local statistics *t* (fraction of H0 maxima >= t)."""
        draws = self.calibrate(**kwargs)
        t = np.asarray(t, float)
        above = len(draws) - np.searchsorted(draws, np.nan_to_num(t, nan=-np.inf), side="left")
        return (above + 1) / (len(draws) + 1)

    # --- candidates -------------------------------------------------------------
    def candidates(self, y, *, threshold, form="B", n_draws=30000, seed=0, min_distance=None,
                   spectrum=None, noise_rows=None):
        """Local maxima of the statistic above *threshold*, as a `~astropy.table.QTable`.

        Maxima closer than *min_distance* (mas; default ``lambda_min / D``) to a
        stronger one are dropped (side lobes).
        """
        from scipy.ndimage import maximum_filter
        t, c, err = self.maps(y, form, spectrum)
        step = max(abs(self.grid.step[0]), abs(self.grid.step[1]))
        if min_distance is None:
            diam = float(np.max(np.hypot(*self.kernel_model.uv.value.T)))
            min_distance = self.wavelengths.to_value(u.m).min() / diam / MAS
        size = max(3, 2 * int(np.ceil(min_distance / step)) + 1)
        tt = np.nan_to_num(t, nan=-np.inf)
        peaks = (tt == maximum_filter(tt, size=size, mode="constant", cval=-np.inf)) & \
            (tt >= threshold) & self.grid.valid
        iy, ix = np.nonzero(peaks)
        order = np.argsort(-tt[iy, ix])
        iy, ix = iy[order], ix[order]
        q = len(self.wavelengths)
        gx, gy = self.grid.X[iy, ix], self.grid.Y[iy, ix]
        tab = QTable()
        tab["x"] = gx * u.mas
        tab["y"] = gy * u.mas
        tab["separation"] = np.hypot(gx, gy) * u.mas
        tab["position_angle"] = np.degrees(np.arctan2(gx, gy)) % 360 * u.deg
        tab["statistic"] = tt[iy, ix]
        tab["pfa_local"] = self.local_pfa(tt[iy, ix], form)
        tab["pfa_global"] = self.global_pfa(tt[iy, ix], form=form, n_draws=n_draws, seed=seed,
                                            spectrum=spectrum, noise_rows=noise_rows)
        tab["contrast"] = c[:, iy, ix].T.reshape(len(iy), q)
        tab["contrast_err"] = err[:, iy, ix].T.reshape(len(iy), q)
        tab.meta["test"] = form
        tab.meta["threshold"] = float(threshold)
        tab.meta["position_angle"] = "degrees from +y (image rows) towards +x (columns)"
        return tab
