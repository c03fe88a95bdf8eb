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
law: `~kpifs.detect.null.NullCalibration` draws it under H0.
"""
import hashlib
import logging

import numpy as np
from astropy import units as u
from astropy.table import QTable

from .._utils import thread_map, to_quantity
from ..covariance import whitening_range
from ..data import DetectionGrid
from ..exceptions import KpifsError
from ..model.kernel import MAS
from ..model.window import ExtractionWindow
from ._signatures import _norm_chunks, _unit
from .channels import channel_shrinkage, whiten_weights
from .spectral import spectral_basis, spectrum_shape, subspace_sign, subspace_weights
from .statistics import DEFAULT_TEST, get_test


__all__ = ["DetectionModel"]

#: Largest store of unit signatures a `DetectionModel` keeps (bytes, single precision).
UNIT_CACHE_BYTES = 256 * 2 ** 20

log = logging.getLogger(__name__)


class DetectionModel:
    """Signatures, their norms and fast maps for one kernel model, covariance and grid.

    Parameters
    ----------
    kernel_model : `~kpifs.model.kernel.KernelModel`
    wavelengths : `~astropy.units.Quantity` (q,)
    whitening : ndarray, shape (q, p, p)
        Per-channel whitening operators (`~kpifs.covariance.whitening_matrix`).
    grid : `~kpifs.data.DetectionGrid`
    pixscale : `~astropy.units.Quantity`, optional
        With *window*, the pixel scale of the extraction.
    window : `~kpifs.model.window.ExtractionWindow`, optional
        The extraction window, whose attenuation enters the signatures.
    dof : sequence of int, optional
        Whitened dimension kept per channel (for the energy detector).
    basis : optional
        Spectral model of the subspace test ``'S'`` (`~kpifs.detect.spectral.spectral_basis`:
        None for the default smooth basis, a rank, ``'blackbody'``, a file of
        spectra or an array (q, r)).
    detpa : tuple, optional
        ``(angles, weights)``: detector position angles (deg) of the data's
        frames or PA bins (`kpifs.detect.sky.pa_bins`) and their weights. The
        grid is then on the sky (``grid.frame == 'sky'``) and each signature is
        the weighted mean of the per-angle ones: a companion fixed on the sky
        seen by a rotating sequence.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect import DetectionModel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(100 * u.mas, 10 * u.mas)
    >>> dm = DetectionModel(km, [1.6] * u.um, np.eye(km.n_kp)[None] * 1e3, grid)
    >>> dm.local_statistic(np.zeros((1, km.n_kp))).shape
    (21, 21)
    """

    def __init__(self, kernel_model, wavelengths, whitening, grid, *, pixscale=None,
                 window=None, dof=None, detpa=None, basis=None):
        self.kernel_model = kernel_model
        self.wavelengths = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
        self.basis = spectral_basis(basis, self.wavelengths)
        w = np.asarray(whitening, float)
        q, p = len(self.wavelengths), kernel_model.n_kp
        if w.shape != (q, p, p):
            raise KpifsError(f"whitening operators of shape {w.shape}, expected ({q}, {p}, {p}) "
                             f"(one per channel)")
        self.whitening = w
        self.grid = grid
        self.dof = np.full(q, p) if dof is None else np.asarray(dof, int)
        self.pixscale = None if pixscale is None else to_quantity(pixscale, u.mas).value
        if window is not None and not isinstance(window, ExtractionWindow):
            raise KpifsError(f"window must be an ExtractionWindow, got {window!r}")
        self.window = window if (window is not None and pixscale is not None) else None
        if not isinstance(grid, DetectionGrid):
            raise KpifsError(f"grid must be a DetectionGrid, got {type(grid).__name__}")
        if (detpa is not None) != (grid.frame == "sky"):
            raise KpifsError("a sky grid needs the detector angles (detpa), and angles a sky "
                             "grid")
        if detpa is None:
            self._poses = [(None, 1.0)]
        else:
            ang = np.atleast_1d(np.asarray(detpa[0], float))
            wts = np.ones(ang.size) if detpa[1] is None else np.asarray(detpa[1], float)
            if ang.size == 0 or not np.all(np.isfinite(ang)):
                raise KpifsError("sky grid: the detector angles must be known (finite)")
            self._poses = list(zip(ang, wts / wts.sum()))
        self.detpa = detpa
        self._check_grid()
        self._wfac = (np.ones_like(grid.sep) if self.window is None
                      else self.window.at(grid.sep, self.pixscale))
        kern = kernel_model.kernel
        # L_i = K^T W_i^T maps whitened data to uv space: g_i = L_i y_i
        self._lift = np.matmul(w, kern).transpose(0, 2, 1)          # (q, nuv, p)
        self._trig = [self._axis_trig(lam) for lam in self.wavelengths.to_value(u.m)]
        self.norm2 = self._signature_norms()                         # (q, ny, nx)

    # --- set-up -----------------------------------------------------------------
    def _check_grid(self):
        g = self.grid
        far = float(np.max(g.sep[g.valid]))
        lam_min = self._channel_wavelengths().to_value(u.m).min()
        # signatures are periodic with the uv grid: beyond lambda / (2 step) positions alias
        step = self.kernel_model.pupil.step
        if step is not None:
            alias = lam_min / (2 * step.to_value(u.m)) / MAS
            if far > alias:
                raise KpifsError(f"the grid reaches {far:.0f} mas, beyond the aliasing limit "
                                 f"lambda_min / (2 x grid step) = {alias:.0f} mas of the "
                                 f"pupil model: reduce the maximum separation")
        if self.window is not None:
            edge = self.window.radius * self.pixscale * 1.5
            if far > edge:
                raise KpifsError(f"the grid reaches {far:.0f} mas, beyond the extraction "
                                 f"window (radius {self.window.radius * self.pixscale:.0f} "
                                 f"mas): reduce the maximum separation to < {edge:.0f} mas")

    def _channel_wavelengths(self):
        """The wavelengths the signatures are made at (a model of channel combinations:
        the channels', not the combinations' nominal ones), which set the aliasing."""
        return self.wavelengths

    def _axis_trig(self, lam):
        """Per pose (detector angle): the separable factors of ``sin(theta)`` on the grid.

        On the sky, ``theta = 2 pi (x u + y v) / lam`` with ``(x, y)`` the
        detector offset of ``(dRA, dDec)`` (`kpifs.detect.sky.sky_to_detector`),
        which is ``2 pi (dRA u' + dDec v') / lam`` with ``u' = -u cos + v sin``,
        ``v' = u sin + v cos``: still separable on the grid, pose by pose.
        """
        uv = self.kernel_model.uv.value
        out = []
        for ang, wt in self._poses:
            if ang is None:
                uu, vv = uv[:, 0], uv[:, 1]
            else:
                c, s = np.cos(np.deg2rad(ang)), np.sin(np.deg2rad(ang))
                uu, vv = -c * uv[:, 0] + s * uv[:, 1], s * uv[:, 0] + c * uv[:, 1]
            tx = 2 * np.pi * np.outer(self.grid.x * MAS, uu) / lam    # (nx, nuv)
            ty = 2 * np.pi * np.outer(self.grid.y * MAS, vv) / lam    # (ny, nuv)
            # several poses (a rotating sequence on the sky) multiply this store: single
            # precision when there are several (1e-7 on a signature)
            dt = np.float64 if len(self._poses) == 1 else np.float32
            out.append(tuple(f(t).astype(dt) for t in (tx, ty) for f in (np.sin, np.cos))
                       + (wt,))
        return out

    def _sin_rows(self, i, rows):
        """``sin(theta_i)`` (weighted mean over poses) at flat grid positions *rows*."""
        return self._sin_from(self._trig[i], rows)

    def _sin_from(self, trig, rows):
        """``sin(theta)`` at flat grid positions *rows* from one axis's separable factors
        *trig* (``sin``/``cos`` along x and y and the pose weight, per pose):
        ``sin(a + b) = sin a cos b + cos a sin b``."""
        iy, ix = np.divmod(rows, self.grid.shape[1])
        # runs of consecutive positions of one grid row (the rows come sorted): its y
        # factors broadcast and its x factors sliced, not gathered
        cuts = np.flatnonzero((np.diff(iy) != 0) | (np.diff(ix) != 1)) + 1
        runs = list(zip(np.r_[0, cuts], np.r_[cuts, len(rows)])) \
            if len(cuts) < len(rows) // 8 else None
        out = None
        for sx, cx, sy, cy, wt in trig:
            if runs is None:
                part = sx[ix] * cy[iy]
                part += cx[ix] * sy[iy]
            else:
                part = np.empty((len(rows), sx.shape[1]), np.result_type(sx, cy))
                tmp = np.empty((max(b - a for a, b in runs), sx.shape[1]), part.dtype)
                for a, b in runs:
                    xs = slice(ix[a], ix[a] + b - a)
                    np.multiply(sx[xs], cy[iy[a]], out=part[a:b])
                    part[a:b] += np.multiply(cx[xs], sy[iy[a]], out=tmp[:b - a])
            if wt != 1.0:
                part = wt * part          # (a float64 weight: float64, as the sum is)
            out = part if out is None else out + part
        return out

    def _signature_norms(self):
        """``||s_i||^2`` everywhere; on the way, the unit signatures of `half_positions`
        are kept (single precision, within `UNIT_CACHE_BYTES`) for the nulls and limits."""
        q, p = len(self.wavelengths), self.kernel_model.n_kp
        n = self.grid.valid.size
        keep, mirrored, rows = self._norm_rows()
        cache = q * len(keep) * p * 4 <= UNIT_CACHE_BYTES
        at = np.searchsorted(rows, keep) if not mirrored else np.arange(len(keep))
        unit = np.empty((q, len(keep), p), np.float32) if cache else None
        wf = self._wfac.ravel()[keep]
        out = np.zeros((q, n))

        def channel(i):
            # ||W K sin||^2 through the (nuv, p) lift: fewer flops than the (nuv, nuv) Gram;
            # through its (nuv, r) restriction to the whitening's range when that is narrow
            lift, basis = self._range_lift(i)
            raw = _norm_chunks(rows, 2048, lambda c: self._sin_rows(i, c) @ lift,
                               at, wf, unit[i] if cache else None, basis)
            out[i, rows] = raw
            if mirrored:
                out[i, n - 1 - rows] = raw
        thread_map(channel, range(q))
        if cache:
            self._unit_cache = (keep, unit)
        return out.reshape((q,) + self.grid.shape) * self._wfac[None] ** 2

    def _range_lift(self, i):
        """Channel *i*'s lift and the basis of its coordinates: ``(L_i Q_i, Q_i)`` with
        ``Q_i`` (p, r) an orthonormal basis of the whitening's range
        (`~kpifs.covariance.whitening_range`, *r* its rank: a whitened signature lies
        there, ``s = (sin L_i Q_i) Q_i^T``), or ``(L_i, None)`` when the range is not
        narrow (few frames for many kernel phases make it so: 19 of 264 dimensions for
        20 frames)."""
        kept = self.__dict__.setdefault("_range_lifts", {})
        if i not in kept:
            ranks = np.broadcast_to(self.dof, (len(self._lift),))
            basis = whitening_range(self.whitening[i], ranks[i])
            kept[i] = (self._lift[i], None) if basis is None else (self._lift[i] @ basis, basis)
        return kept[i]

    def _symmetric_grid(self):
        g = self.grid
        return bool(np.allclose(g.x, -g.x[::-1]) and np.allclose(g.y, -g.y[::-1]))

    # --- maps -------------------------------------------------------------------
    def dot_maps(self, y):
        """``s_i^T y_i`` over the grid for whitened data *y* (..., q, p) -> (..., q, ny, nx).

        The maps of one data set (q, p) are kept for the next few calls: a search
        projects the same residual for its candidates, its noise measures and its
        maps."""
        y = np.asarray(y, float)
        if y.ndim != 2:
            return self._dot_maps(y)
        key = hashlib.sha1(np.ascontiguousarray(y).tobytes()).hexdigest() + repr(y.shape)
        kept = self.__dict__.setdefault("_dot_maps_kept", {})
        maps = kept.get(key)
        if maps is None:
            maps = kept[key] = self._dot_maps(y)
            while len(kept) > 4:
                try:                              # (another thread may evict it first)
                    kept.pop(next(iter(kept)), None)
                except (RuntimeError, StopIteration):
                    break
        return maps.copy()

    def _dot_maps(self, y):
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
        m = len(g)
        a = 0.0
        for sx, cx, sy, cy, wt in self._trig[i]:
            nx, nuv = sx.shape
            gw = wt * g
            a = a + (sx[None] * gw[:, None, :]).reshape(m * nx, nuv) @ cy.T     # (m*nx, ny)
            a = a + (cx[None] * gw[:, None, :]).reshape(m * nx, nuv) @ sy.T
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
        a = spectrum_shape(spectrum, len(self.wavelengths))
        amp = a[:, None, None] * np.sqrt(self.norm2)
        with np.errstate(invalid="ignore", divide="ignore"):
            return amp / np.sqrt(np.sum(amp ** 2, axis=0))

    @property
    def subspace(self):
        """Weights ``U`` (r, q, ny, nx) of the subspace statistic (`kpifs.detect.spectral`).

        With the channels' correlation (`correlate`), the weights of the GLR
        under that correlation (shrunk towards independence by the cross-
        validated ``channel_alpha``): the channels' common noise (one
        optical-path error seen at every wavelength) is cancelled, as joint
        whitening across channels would.
        """
        if "_subspace" not in self.__dict__:
            w = subspace_weights(self.norm2, self.basis)
            corr = self.__dict__.get("_channel_corr")
            if corr is not None:
                w = whiten_weights(w, corr, self.channel_alpha)
            self._subspace = w
            self._subspace_sign = subspace_sign(w, self.norm2, self.basis)
        return self._subspace

    @property
    def subspace_sign(self):
        """Sign vectors ``h`` (r, ny, nx) of the subspace test: the fitted spectrum has a
        positive mean where the dot product of ``h`` and ``U^T z`` is positive (the
        test counts only those: a spectrum of negative mean is the mirror position's)."""
        self.subspace
        return self._subspace_sign

    def correlate(self, noise_rows):
        """Take the channels' correlation at every position from whitened *noise_rows*.

        ``C(pos) = Z^T Z`` with ``Z`` the rows' projections on the unit
        signatures (`row_projections`); used by the subspace test's weights
        (`subspace`) and returned, shape (ny, nx, q, q) (NaN off the grid).
        """
        ny, nx = self.grid.shape
        q = len(self.wavelengths)
        idx, z = self.row_projections(noise_rows)
        corr = np.full((ny * nx, q, q), np.nan)
        corr[idx] = np.matmul(z.transpose(0, 2, 1), z)
        if self.half_positions()[1]:                 # z(-pos) = -z(pos): the same C
            corr[ny * nx - 1 - idx] = corr[idx]
        self._channel_corr = corr.reshape(ny, nx, q, q)
        self.channel_alpha = channel_shrinkage(z)
        log.info("channels' correlation shrunk towards independence by %.2f "
                 "(cross-validated)", self.channel_alpha)
        self.__dict__.pop("_subspace", None)
        self.__dict__.pop("_digest", None)
        self._corr_key = hashlib.sha1(np.ascontiguousarray(noise_rows).tobytes()).hexdigest() \
            + f"|{self.channel_alpha!r}"
        return self._channel_corr

    def local_statistic(self, y, form=DEFAULT_TEST, spectrum=None):
        """Detection statistic at each grid position (NaN outside the searched area).

        ``'B'``/``'B-paper'``: the binary test; ``'NP'``: the matched filter for a
        companion of the given spectrum shape and unknown amplitude,
        ``sum_i a_i s_i^T y_i / ||s_a||`` (N(0, 1) under H0); ``'S'``: the
        subspace (spectral-model) test ``||U^T z||^2`` (chi2_r at a known
        position, `kpifs.detect.spectral`).
        """
        return self._statistic(self.dot_maps(y), form, spectrum)

    def maps(self, y, form=DEFAULT_TEST, spectrum=None):
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
        t = get_test(form).map_statistic(self, z, spectrum)
        return np.where(self.grid.valid, t, np.nan)

    def local_pfa(self, t, form=DEFAULT_TEST):
        """False-alarm probability of a local statistic at a known position (the test's
        own law, `~kpifs.detect.statistics.DetectionTest.local_pfa`)."""
        return get_test(form).local_pfa(self, t)

    # --- what the Monte-Carlo null needs ------------------------------------------
    def key(self):
        """A digest of everything the projection depends on (for caches; computed once)."""
        if "_digest" in self.__dict__:
            return self._digest
        h = hashlib.sha1()
        for arr in (self.kernel_model.kernel, self.kernel_model.uv.value, self.whitening,
                    self.wavelengths.value, self._wfac, self.basis):
            h.update(np.ascontiguousarray(arr).tobytes())
        for part in self.grid.key():
            h.update(repr(part).encode())
        h.update(repr([(None if a is None else float(a), float(w))
                       for a, w in self._poses]).encode())
        h.update(self.__dict__.get("_corr_key", "").encode())
        self._digest = h.hexdigest()
        return self._digest

    def _unit_signatures(self, rows):
        """Unit-norm whitened signatures at flat grid positions *rows*: (q, npos, p), float32."""
        if "_unit_cache" in self.__dict__:            # kept by `_signature_norms`
            keep, unit = self._unit_cache
            at = np.minimum(np.searchsorted(keep, rows), len(keep) - 1)
            if np.array_equal(keep[at], rows):
                # a run of kept positions (as `row_projections` asks): a view, no copy
                run = len(at) > 0 and at[-1] - at[0] == len(at) - 1
                return unit[:, at[0]:at[-1] + 1] if run else unit[:, at]
        q, p = len(self.wavelengths), self.kernel_model.n_kp
        out = np.empty((q, len(rows), p), np.float32)
        wf = self._wfac.ravel()[rows]
        for i in range(q):
            lift, basis = self._range_lift(i)
            s = self._sin_rows(i, rows) @ lift                    # (npos, p) or (npos, r)
            norm2 = np.einsum("ij,ij->i", s, s)
            out[i] = _unit(s if basis is None else s @ basis.T, norm2, wf)
        return out

    def row_projections(self, noise_rows, *, chunk=512, also=()):
        """Whitened noise rows projected on the unit signatures (half the grid).

        A signature at ``-pos`` is minus that at ``pos``, so on a symmetric grid
        only the positions of `half_positions` are projected (every valid one
        otherwise). Returns ``(rows_idx, Z)``: the flat indices of those positions and
        ``Z`` of shape (npos, nrow, q) with ``Z[k, r, i] = u_i(pos_k) . R_w[r, i]``,
        so that ``Z[k]^T Z[k]`` is the covariance of ``(z_1 ... z_q)`` at position
        ``k`` (channel correlations included). The row sets in *also* (the
        empirical null's blocks) are projected in the same pass over the
        signatures; the last few results are kept (the nulls and the limits
        share them).
        """
        sets = [np.asarray(r, float) for r in (noise_rows, *also)]
        keys = [hashlib.sha1(np.ascontiguousarray(r).tobytes()).hexdigest() for r in sets]
        cache = self.__dict__.setdefault("_row_projections", {})
        todo = [j for j, k in enumerate(keys) if k not in cache]
        if todo:
            rows = self.half_positions()[0]
            q = len(self.wavelengths)
            # written channel-major (contiguous rows), turned to (npos, nrow, q) at the end
            outs = {j: np.empty((q, len(sets[j]), len(rows))) for j in todo}
            for a in range(0, len(rows), chunk):
                unit = self._unit_signatures(rows[a:a + chunk])                 # (q, n, p)
                for i in range(q):
                    ui = unit[i].astype(float)        # one channel at a time: in the cache
                    for j in todo:
                        np.matmul(sets[j][:, i, :], ui.T, out=outs[j][i, :, a:a + chunk])
            for j in todo:
                cache[keys[j]] = (rows, np.ascontiguousarray(outs[j].transpose(2, 1, 0)))
            while len(cache) > 3:
                cache.pop(next(iter(cache)))
        return cache[keys[0]]

    def _norm_rows(self):
        """Kept positions, mirrored?, and the rows whose norms are computed (`half_positions`)."""
        n = self.grid.valid.size
        keep, mirrored = self.half_positions()
        if not mirrored:
            return np.flatnonzero(self.grid.valid.ravel()), False, np.arange(n)
        pair = np.zeros(n, bool)
        pair[keep] = pair[n - 1 - keep] = True
        rest = np.flatnonzero(~pair)
        return keep, True, np.concatenate([keep, rest[rest <= n - 1 - rest]])

    def half_positions(self):
        """Valid positions, split into a half and its mirror image when the grid allows."""
        g = self.grid
        rows = np.flatnonzero(g.valid.ravel())
        symmetric = self._symmetric_grid() and np.array_equal(g.valid, g.valid[::-1, ::-1])
        if not symmetric:
            return rows, False
        x, y = g.X.ravel()[rows], g.Y.ravel()[rows]
        half = (y > 0) | ((y == 0) & (x > 0))
        return rows[half], True

    # --- candidates -------------------------------------------------------------
    def candidates(self, y, *, threshold, form=DEFAULT_TEST, null=None, min_distance=None,
                   spectrum=None):
        """Local maxima of the statistic above *threshold*, as a `~astropy.table.QTable`.

        Maxima closer than *min_distance* (mas; default ``lambda_min / D``) to a
        stronger one are dropped (side lobes). With *null* (a
        `~kpifs.detect.null.NullCalibration`) the table gives each maximum's
        global false-alarm probability.
        """
        t, c, err = self.maps(y, form, spectrum)
        step = max(abs(self.grid.step[0]), abs(self.grid.step[1]))
        if min_distance is None:
            diam = float(np.max(np.hypot(*self.kernel_model.uv.value.T)))
            min_distance = self.wavelengths.to_value(u.m).min() / diam / MAS
        size = max(3, 2 * int(np.ceil(min_distance / step)) + 1)
        tt = np.nan_to_num(t, nan=-np.inf)
        local_max = _window_max(tt, size)
        peaks = (tt == local_max) & (tt >= threshold) & self.grid.valid
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
        if null is not None:
            pfa, tail = null.pfa(tt[iy, ix], return_method=True)
        else:
            pfa, tail = np.full(len(iy), np.nan), np.zeros(len(iy), bool)
        tab["pfa_global"] = pfa
        # which P_FA come from the extrapolated tail of the null (beyond the draws)
        tab["pfa_global_tail"] = tail
        tab["contrast"] = c[:, iy, ix].T.reshape(len(iy), q)
        tab["contrast_err"] = err[:, iy, ix].T.reshape(len(iy), q)
        tab.meta["test"] = form
        tab.meta["threshold"] = float(threshold)
        tab.meta["position_angle"] = "degrees from +y (image rows) towards +x (columns)"
        return tab


def _window_max(t, size):
    """Maximum over the *size* x *size* window (odd) centred on each pixel, ``-inf``
    beyond the edges: ``scipy.ndimage.maximum_filter(t, size, mode='constant',
    cval=-inf)``, separably in numpy (importing scipy.ndimage costs a search 0.13 s)."""
    h = size // 2
    view = np.lib.stride_tricks.sliding_window_view
    t = np.pad(t, ((0, 0), (h, h)), constant_values=-np.inf)
    t = view(t, size, axis=1).max(axis=-1)
    t = np.pad(t, ((h, h), (0, 0)), constant_values=-np.inf)
    return view(t, size, axis=0).max(axis=-1)
