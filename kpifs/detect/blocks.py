"""Searching a rotating sequence block by block (issue 29; DESIGN.md section 6).

The calibrated product of a pupil-tracking sequence keeps its time blocks
(`kpifs.rotation`). The search stacks, channel by channel, two whitened parts:

- the calibrated mean ``C_m d`` (``C_m``: the error model's whitening in its
  modes; calibrator and residual included), whose signature is the
  frame-weighted mean of the blocks' ``C_m K sin(theta_b)``;
- the block contrasts ``sqrt(n_b) C_f (d_b - d)`` (``C_f``: one frame's noise
  whitened in its leading modes, `~kpifs.rotation.noise_whitening`, from the
  frames' scatter within their blocks, which holds none of a companion's
  turning), free of the calibrator and of every aberration fixed on the
  detector, whose signature ``sqrt(n_b) C_f K (sin(theta_b) - mean)`` is what
  survives of a companion turning with the sky (its self-subtraction).

Tests, limits, fits and the null see one whitened vector per channel, of
dimension ``r_m + B r_f`` (``B`` blocks): the blocks' correlations add up
instead of a smeared mean's. The angular-differential mode searches what turns,
with no calibrator or static residual, and the calibrated mean (if any) scaled
by its own reduced chi-square; a map costs one projection per block. A block's
signature is the mean of two poses at its angle -/+ the spread of its frames'
angles: a companion far out moves within a block.
"""
import hashlib
import logging
from dataclasses import replace

import numpy as np
from astropy import units as u

from .._utils import thread_map, to_quantity
from ..calibration.adi import _check_rotation
from ..calibration.spectral_diff import retained_by_separation
from ..exceptions import KpifsError
from ..model.kernel import MAS
from ..rotation import noise_whitening
from ._blockfit import refine_stack
from ._blocktrig import block_trig
from .combinations import combination_contrasts, combination_table, distinct_contrasts, \
    nominal_wavelengths
from ._signatures import _norm_chunks, _unit
from .maps import UNIT_CACHE_BYTES, DetectionModel
from .sdk import SpectralStack
from .sky import sky_to_detector
from .spectral import spectral_basis


__all__ = ["BlockModel", "BlockStack", "block_stack", "MODES"]

log = logging.getLogger(__name__)

#: Block searches: the mean and the blocks' contrasts, the contrasts (and a calibrated mean
#: at its own scale), or the mean only (the blocks ignored: the model averaged over the
#: angles, as before issue 29).
MODES = ("rotation", "angular-differential", "mean")
#: Grid positions whose channel signatures are made at a time when a model mixes channels
#: (channels x blocks x positions x kernel phases in memory, single precision).
MIXED_CHUNK = 128


class BlockModel(DetectionModel):
    """`~kpifs.detect.DetectionModel` of stacked time blocks (see `kpifs.detect.blocks`).

    Parameters
    ----------
    kernel_model, wavelengths, grid, pixscale, window, dof, basis
        As `~kpifs.detect.DetectionModel` (the grid on the sky).
    comp_mean : ndarray (q, r_m, p) or None
        The mean's whitening in its modes (rows beyond a channel's rank zero);
        None: the angular-differential search (the blocks' departures only).
    comp_frame : ndarray (q, r_f, p)
        One frame's whitening in its modes (`~kpifs.rotation.noise_whitening`).
    angles, frames : ndarray (B,)
        The blocks' detector angles (deg; their frames' mean) and frames.
    spread : ndarray (B,), optional
        The r.m.s. of each block's frames' angles about its angle (deg): a block's
        signature is then the mean of two poses at ``angle -/+ spread`` (the
        frames' mean and second moment; exact for two frames), not one pose at
        its angle, which overstates a companion that moves within the block
        (the squared norm by 1/0.69 at 300 mas for 4 frames over 6 deg).
    mixing : ndarray (k, q), optional
        Channel combinations (spectral-differential blocks, ASDI,
        `kpifs.calibration.spectral_diff`): the model's ``k`` channels are
        combinations of the data's ``q`` (*wavelengths*), combination ``i``'s
        signature ``sum_c mixing[i, c] K sin(theta_c)``; *comp_mean* and
        *comp_frame* are then the combinations' (k, r, p).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.data import DetectionGrid
    >>> from kpifs.detect.blocks import BlockModel
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> grid = DetectionGrid.from_separation(80 * u.mas, 10 * u.mas, frame="sky")
    >>> c = np.eye(km.n_kp)[None, :5]
    >>> bm = BlockModel(km, [1.6] * u.um, grid, c, c, [0.0, 20.0, 40.0], [2, 2, 2])
    >>> bm.dim, bm.local_statistic(np.zeros((1, bm.dim))).shape
    (20, (17, 17))
    """

    def __init__(self, kernel_model, wavelengths, grid, comp_mean, comp_frame, angles, frames,
                 *, spread=None, pixscale=None, window=None, dof=None, basis=None, mixing=None):
        self.kernel_model = kernel_model
        real = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
        self._real = real
        self.mixing = None if mixing is None else np.asarray(mixing, float)
        if self.mixing is None:
            self.wavelengths = real
        else:
            self.wavelengths = nominal_wavelengths(self.mixing, real)      # labels only
        self.basis = spectral_basis(basis, self.wavelengths)
        self.grid = grid
        if grid.frame != "sky":
            raise KpifsError("a block search is on the sky: give a sky grid")
        self.with_mean = comp_mean is not None
        self.comp_mean = None if comp_mean is None else np.asarray(comp_mean, float)
        self.comp_frame = np.asarray(comp_frame, float)
        self.frames = np.asarray(frames, float)
        q = len(self.wavelengths)
        self.r_mean = 0 if comp_mean is None else self.comp_mean.shape[1]
        self.r_frame = self.comp_frame.shape[1]
        self.dim = self.r_mean + self.r_frame * len(self.frames)
        self.dof = np.full(q, self.dim) if dof is None else np.asarray(dof, int)
        self.pixscale = None if pixscale is None else to_quantity(pixscale, u.mas).value
        self.window = window if (window is not None and pixscale is not None) else None
        self._poses = [(float(a), 1.0) for a in angles]
        self.detpa = (np.asarray(angles, float), self.frames / self.frames.sum())
        spread = np.zeros(len(self.frames)) if spread is None else np.asarray(spread, float)
        # the poses whose signatures average to a block's: one per block when no block
        # spreads (no cost), else two, block by block along the trig factors' uv axis
        self.spread = spread
        self._sub = 2 if np.any(spread > 0) else 1
        pose = self.detpa[0][:, None] + (spread[:, None] * [-1.0, 1.0] if self._sub == 2
                                         else np.zeros((len(spread), 1)))
        self.whitening = None
        self._check_grid()
        self._wfac = (np.ones_like(grid.sep) if self.window is None
                      else self.window.at(grid.sep, self.pixscale))
        # L_i = K^T C_i^T: the modes' coordinates to uv space, (q, nuv, r)
        kern = kernel_model.kernel
        self._lift_f = np.matmul(self.comp_frame, kern).transpose(0, 2, 1)
        self._lift_m = None if comp_mean is None else \
            np.matmul(self.comp_mean, kern).transpose(0, 2, 1)
        # per channel, the poses' separable factors side by side (float32): a map is two
        # products over (poses x uv points)
        uv = kernel_model.uv.value
        self._trig = thread_map(lambda lam: block_trig(grid, uv, pose.ravel(), lam),
                                real.to_value(u.m))
        self.norm2 = self._signature_norms()

    def _channel_wavelengths(self):
        return self._real

    def _weights(self):
        """Per block: the mean's weight ``n_b / N`` and the departures' ``sqrt(n_b)``."""
        n = self.frames
        return n / n.sum(), np.sqrt(n)

    def _block_sines(self, c, rows):
        """Per block ``b``: ``sin(theta)`` of channel *c* at flat grid positions *rows*
        (npos, nuv), float32, summed over the block's poses (one buffer, rewritten for
        each block: use it before the next)."""
        nx = self.grid.shape[1]
        iy, ix = np.divmod(rows, nx)
        sx, cx, sy, cy = self._trig[c]
        nuv = self.kernel_model.uv.shape[0]
        # runs of consecutive positions along one grid line: slices of the x factors times
        # one line of the y factors (no gathered copies of either)
        cut = np.flatnonzero((np.diff(iy) != 0) | (np.diff(ix) != 1)) + 1
        runs = [(a, b, ix[a], iy[a]) for a, b in zip(np.r_[0, cut], np.r_[cut, len(rows)])]
        sin = np.empty((len(rows), nuv), np.float32)
        tmp = np.empty_like(sin)
        # block by block: the work arrays (npos x nuv) stay in the processor's cache
        ns = self._sub
        for b in range(len(self.frames)):
            for k in range(ns):
                uv = slice((b * ns + k) * nuv, (b * ns + k + 1) * nuv)
                for a, e, x0, y0 in runs:
                    xs = slice(x0, x0 + e - a)
                    if k == 0:
                        np.multiply(sx[xs, uv], cy[y0, uv], out=sin[a:e])
                    else:
                        np.multiply(sx[xs, uv], cy[y0, uv], out=tmp[a:e])
                        sin[a:e] += tmp[a:e]
                    np.multiply(cx[xs, uv], sy[y0, uv], out=tmp[a:e])
                    sin[a:e] += tmp[a:e]
            yield b, sin

    def _stacked(self, i, rows, free=None):
        """Stacked signatures ``[m, sqrt(n_b)(S_b - mean)]`` (npos, dim), unsigned; with
        *free* (npos,), the squared norm without the mean's removal is written there."""
        wm, _ = self._weights()
        nuv = self._lift_f.shape[1]
        lift = self._lift_f[i].astype(np.float32)
        per = np.empty((len(self.frames), len(rows), lift.shape[1]))
        sbar = np.zeros((len(rows), nuv), np.float32) if self.with_mean else None
        # a block's poses (two: its frames' spread) summed, their mean's 1/2 in the products
        ns = self._sub
        lift = lift / np.float32(ns)
        for b, sin in self._block_sines(i, rows):
            per[b] = sin @ lift
            if sbar is not None:
                sin *= np.float32(wm[b] / ns)
                sbar += sin
        mean = None if sbar is None else (sbar @ self._lift_m[i].astype(np.float32)).astype(float)
        return self._parts(per, mean, free)

    def _stacked_mixed(self, rows, free=None):
        """`_stacked` of every combination (k, npos, dim) when the model mixes channels:
        each channel's block signatures ``K sin(theta_c)`` once (one product per channel
        and block), mixed into the combinations, then whitened (*free* (k, npos))."""
        q, nb = len(self._real), len(self.frames)
        kt = (self.kernel_model.kernel.T / self._sub).astype(np.float32)         # (nuv, p)
        per_c = np.empty((q, nb, len(rows), kt.shape[1]), np.float32)

        def channel(c):
            for b, sin in self._block_sines(c, rows):
                per_c[c, b] = sin @ kt
        thread_map(channel, range(q))
        mixed = np.tensordot(self.mixing.astype(np.float32), per_c, axes=(1, 0))  # (k, B, ...)
        wm, _ = self._weights()
        out = []
        for i in range(len(mixed)):
            per = (mixed[i] @ self.comp_frame[i].T.astype(np.float32)).astype(float)
            mean = None
            if self.with_mean:
                mean = np.tensordot(wm, mixed[i].astype(float), axes=(0, 0)) @ self.comp_mean[i].T
            out.append(self._parts(per, mean, None if free is None else free[i]))
        return np.stack(out)

    def _parts(self, per, mean, free):
        """``[m, sqrt(n_b)(S_b - mean)]`` from the blocks' projected signatures *per*
        (B, npos, r_f) and the mean's *mean* (npos, r_m) or None; *free* as `_stacked`."""
        wm, wd = self._weights()
        md = np.tensordot(wm, per, axes=(0, 0))
        parts = list(wd[:, None, None] * (per - md))
        if free is not None:
            free[:] = np.einsum("b,bkr,bkr->k", wd ** 2, per, per)
        if mean is not None:
            parts.insert(0, mean)
            if free is not None:
                free += np.einsum("kr,kr->k", mean, mean)
        return np.concatenate(parts, axis=-1)

    def _signature_norms(self):
        if self.mixing is not None:
            return self._mixed_norms()
        q = len(self.wavelengths)
        n = self.grid.valid.size
        keep, mirrored, rows = self._norm_rows()
        cache = q * len(keep) * self.dim * 4 <= UNIT_CACHE_BYTES
        at = np.searchsorted(rows, keep) if not mirrored else np.arange(len(keep))
        unit = np.empty((q, len(keep), self.dim), np.float32) if cache else None
        wf = self._wfac.ravel()[keep]
        out = np.zeros((q, n))
        free = np.zeros((q, n))

        def channel(i):
            def stacked(chunk):         # and, on the way, the norms before self-subtraction
                fb = np.empty(len(chunk))
                s = self._stacked(i, chunk, free=fb)
                free[i, chunk] = fb
                return s
            raw = _norm_chunks(rows, 256, stacked, at, wf, unit[i] if cache else None)
            out[i, rows] = raw
            if mirrored:
                out[i, n - 1 - rows] = raw
                free[i, n - 1 - rows] = free[i, rows]
        thread_map(channel, range(q))
        if cache:
            self._unit_cache = (keep, unit)
            # dot_maps from the unit signatures: ||s|| (the window's factor in it)
            self._amp = np.sqrt(out[:, keep]) * wf
            self._mirrored = mirrored
        # the blocks' signatures without the removal of their mean: what an arc of
        # rotation lets survive is norm2 / norm2_free (the self-subtraction)
        self.norm2_free = free.reshape((q,) + self.grid.shape) * self._wfac[None] ** 2
        return out.reshape(self.norm2_free.shape) * self._wfac[None] ** 2

    def _mixed_norms(self):
        """`_signature_norms` of channel combinations: chunk by chunk, every combination
        from the channels' signatures made once (`_stacked_mixed`)."""
        k = len(self.wavelengths)
        n = self.grid.valid.size
        keep, mirrored, rows = self._norm_rows()
        cache = k * len(keep) * self.dim * 4 <= UNIT_CACHE_BYTES
        at = np.searchsorted(rows, keep) if not mirrored else np.arange(len(keep))
        unit = np.empty((k, len(keep), self.dim), np.float32) if cache else None
        wf = self._wfac.ravel()[keep]
        out, free = np.zeros((k, n)), np.zeros((k, n))
        for a in range(0, len(rows), MIXED_CHUNK):
            chunk = rows[a:a + MIXED_CHUNK]
            fb = np.empty((k, len(chunk)))
            s = self._stacked_mixed(chunk, free=fb)
            raw = np.einsum("kij,kij->ki", s, s)
            out[:, chunk], free[:, chunk] = raw, fb
            if cache:
                sel = (at >= a) & (at < a + len(chunk))
                for i in range(k):
                    unit[i, sel] = _unit(s[i, at[sel] - a], raw[i, at[sel] - a], wf[sel])
        if mirrored:
            out[:, n - 1 - rows] = out[:, rows]
            free[:, n - 1 - rows] = free[:, rows]
        if cache:
            self._unit_cache = (keep, unit)
            self._amp = np.sqrt(out[:, keep]) * wf
            self._mirrored = mirrored
        self.norm2_free = free.reshape((k,) + self.grid.shape) * self._wfac[None] ** 2
        return out.reshape(self.norm2_free.shape) * self._wfac[None] ** 2

    def retained(self):
        """Fraction of a companion's squared signal the search keeps (per channel and
        position): 1 minus the self-subtraction of the angular-differential part."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.norm2 / self.norm2_free

    def _unit_signatures(self, rows):
        if "_unit_cache" in self.__dict__:
            keep, unit = self._unit_cache
            at = np.minimum(np.searchsorted(keep, rows), len(keep) - 1)
            if np.array_equal(keep[at], rows):
                return unit[:, at]
        q = len(self.wavelengths)
        wf = self._wfac.ravel()[rows]
        if self.mixing is not None:
            s = self._stacked_mixed(rows)
            return np.stack([_unit(si, np.einsum("ij,ij->i", si, si), wf) for si in s]
                            ).astype(np.float32)
        out = np.empty((q, len(rows), self.dim), np.float32)
        for i in range(q):
            s = self._stacked(i, rows)
            out[i] = _unit(s, np.einsum("ij,ij->i", s, s), wf)
        return out

    def dot_maps(self, y):
        y = np.asarray(y, float)
        lead = y.shape[:-2]
        yb = y.reshape((-1,) + y.shape[-2:])
        m, q = len(yb), len(self.wavelengths)
        rm, rf, nb = self.r_mean, self.r_frame, len(self.frames)
        ny, nx = self.grid.shape
        v = np.sqrt(self.frames / self.frames.sum())
        wm, wd = self._weights()
        cached = self.__dict__.get("_unit_cache")
        out = np.zeros((m, q, ny, nx) if cached is None else (m, q, ny * nx))

        def channel(i):
            yd = yb[:, i, rm:].reshape(m, nb, rf)
            yd = yd - v[None, :, None] * np.einsum("mbr,b->mr", yd, v)[:, None, :]
            if cached is not None:
                # the cached unit signatures: (positions x dim) per map instead of two
                # products over (positions x blocks x uv points)
                keep, unit = cached
                yi = np.concatenate([yb[:, i, :rm], yd.reshape(m, -1)], axis=1)
                amp = self._amp[i]
                with np.errstate(invalid="ignore"):
                    d = (yi.astype(np.float32) @ unit[i].T).astype(float) * amp
                d = np.where(amp > 0, d, 0.0)
                out[:, i, keep] = d
                if self._mirrored:              # the signature at -pos is minus that at pos
                    out[:, i, ny * nx - 1 - keep] = -d
                return
            g = (wd[None, :, None] * yd) @ self._lift_f[i].T                   # (m, B, nuv)
            if self.with_mean:
                g = g + wm[None, :, None] * (yb[:, i, :rm] @ self._lift_m[i].T)[:, None, :]
            if self._sub == 2:                  # each block's two poses, half each
                g = np.repeat(0.5 * g, 2, axis=1)
            g = g.reshape(m, -1).astype(np.float32)
            k = g.shape[1]
            acc = 0.0
            # a combination of channels: its channels' projections, weighted
            for c, wt in (enumerate(self.mixing[i]) if self.mixing is not None
                          else [(i, 1.0)]):
                sx, cx, sy, cy = self._trig[c]
                gc = g * np.float32(wt)
                acc = acc + (sx[None] * gc[:, None, :]).reshape(m * nx, k) @ cy.T
                acc += (cx[None] * gc[:, None, :]).reshape(m * nx, k) @ sy.T
            out[:, i] = -acc.reshape(m, nx, ny).transpose(0, 2, 1) * self._wfac
        # channels side by side, one BLAS thread each (BLAS's threads on a busy machine
        # wait for each other: 0.2 s became 10 s at a load of 9 on 2 cores)
        thread_map(channel, range(q))
        return out.reshape(lead + (q, ny, nx))

    def key(self):
        if "_digest" in self.__dict__:
            return self._digest
        h = hashlib.sha1(b"blocks")
        for arr in (self.kernel_model.kernel, self.kernel_model.uv.value,
                    np.zeros(0) if self.comp_mean is None else self.comp_mean,
                    self.comp_frame, self.frames, self.detpa[0], self.spread,
                    self.wavelengths.value,
                    self._wfac, self.basis,
                    np.zeros(0) if self.mixing is None else self.mixing, self._real.value):
            h.update(np.ascontiguousarray(arr).tobytes())
        for part in self.grid.key():
            h.update(repr(part).encode())
        h.update(f"{self.with_mean}".encode())
        h.update(self.__dict__.get("_corr_key", "").encode())
        self._digest = h.hexdigest()
        return self._digest


def _compress(w, rank):
    """The whitening operators' kept modes: C (q, r, p) with ``C^T C = W^T W``."""
    q, p, _ = w.shape
    r = int(np.max(rank))
    out = np.zeros((q, r, p))
    for i in range(q):
        vals, vecs = np.linalg.eigh(w[i])
        order = np.argsort(-np.abs(vals))[:int(rank[i])]
        out[i, :len(order)] = (vecs[:, order] * vals[order]).T
    return out


def _complement(v):
    """Orthonormal rows (B-1, B) orthogonal to the unit vector *v*."""
    q, _ = np.linalg.qr(np.column_stack([v, np.eye(len(v))[:, :-1]]))
    return q[:, 1:].T


class BlockStack:
    """Whitened, stacked data of a block search, its noise rows, models and fits.

    Built by `block_stack`; ``kp`` (q, dim) is already whitened (its whitening
    is the identity), so that `~kpifs.detect.detect` handles it as any data.
    """

    def __init__(self, kpd, kp, w, rank, *, mode="rotation", cov=None, spectrum=None):
        if mode not in MODES:
            raise KpifsError(f"unknown block search {mode!r}: use one of {MODES}")
        rb = kpd.rotation
        self.kpd, self.mode = kpd, mode
        self.mixing, self.spectral = None, None
        cov_rows = kpd.covariance_rows
        if getattr(kpd, "spectral", None) is not None:
            # ASDI (issue 39): the blocks of the channel combinations free of the static
            # profiles (`kpifs.detect.sdk`), searched as a rotating sequence's channels
            rb, kp, w, rank, cov_rows = self._combine(rb, kp, w, rank, cov, spectrum)
        self.blocks = rb
        n = rb.frames.astype(int)
        frames = np.asarray(kpd.meta.get("detpa_frames") or [], float)
        if frames.size == n.sum() and np.all(np.isfinite(frames)):
            self._frame_angles = frames
            edges = np.concatenate([[0], np.cumsum(n)])
            self._block_frames = [np.arange(a, b) for a, b in zip(edges[:-1], edges[1:])]
        else:                                   # the blocks' mean angles only
            self._frame_angles = np.asarray(rb.angles, float)
            self._block_frames = [np.array([b]) for b in range(rb.n_blocks)]
        # the angular-differential search of calibrated data keeps the calibrated mean too,
        # weighted by its own excess (below): where the rotation moves a companion little
        # the calibrator still finds it, and a static residual shows in the mean alone
        # so does ASDI's: its combinations' mean is free of the static profiles
        self.with_mean = mode == "rotation" or bool(rb.calibrated) or self.mixing is not None
        rank = np.atleast_1d(rank)
        q = rb.data.shape[1]
        nb = rb.n_blocks
        self.comp_frame = cf = noise_whitening(rb)                              # (q, rf, p)
        rf = cf.shape[1]
        frank = np.count_nonzero(np.abs(cf).sum(axis=2), axis=1)
        # the frames' noise rows, per mode at unit variance (their in-sample variance
        # along their own leading modes is high), channels tied as the frames tie them
        noise = np.einsum("iap,fip->fia", cf, rb.noise)
        norm = np.sqrt(np.sum(noise ** 2, axis=0))
        noise = np.divide(noise, norm, out=np.zeros_like(noise), where=norm > 0)
        # as few rows as their rank (the same Gram matrix): the null's cost is in the rows
        _, sv, vt = np.linalg.svd(noise.reshape(len(noise), -1), full_matrices=False)
        keep = sv > 1e-10 * sv[0]
        noise = (sv[keep, None] * vt[keep]).reshape(-1, q, rf)
        hmat = _complement(np.sqrt(rb.frames / rb.frames.sum()))
        dev_rows = np.einsum("jb,fia->jfiba", hmat, noise).reshape(-1, q, nb * rf)
        dev = np.einsum("iap,bip->iba", cf, rb.contrasts()).reshape(q, nb * rf)
        self.comp_mean, self.mean_scale = None, None
        pieces, rows = [dev], [dev_rows]
        if self.with_mean:
            self.comp_mean = cm = _compress(w, rank)
            rm = cm.shape[1]
            ym = np.einsum("iap,ip->ia", cm, kp)
            if mode == "angular-differential":
                # the one-calibrator residual (target minus calibrator, fixed on the detector)
                # is in the mean only: its reduced chi-square scales the mean's part alone,
                # while the departures keep the frames' noise (a common scale would also
                # inflate their noise, and spare the mean)
                self.mean_scale = max(1.0, float(np.sum(ym ** 2) / max(np.sum(rank), 1)))
                self.comp_mean = cm = cm / np.sqrt(self.mean_scale)
                ym = ym / np.sqrt(self.mean_scale)
            pieces.insert(0, ym)
            rows = [_pad(_rows(cm, cov_rows), nb * rf, after=True)] \
                if cov_rows is not None else []
            rows.append(_pad(dev_rows, rm, after=False))
        self.kp = np.concatenate(pieces, axis=-1)
        self.dim = self.kp.shape[1]
        self.rows = np.concatenate(rows)
        # the empirical null's time blocks would miss the blocks' own part: Gaussian only
        self.block_rows = None
        self.whitening = np.broadcast_to(np.eye(self.dim), (q, self.dim, self.dim))
        self.rank = frank * (nb - 1) + (rank if self.with_mean else 0)
        log.info("%s: searched in %d time blocks over %.1f deg (%s), %d modes of one frame's "
                 "noise per channel", kpd.name, nb, rb.span, mode, rf)

    def _combine(self, rb, kp, w, rank, cov, spectrum):
        """The channel combinations free of the data's static profiles (``kpd.spectral``):
        the blocks, the mean and its covariance rows mixed by ``D`` (k, q), the mean
        whitened as the spectral-differential search's
        (`~kpifs.detect.sdk.SpectralStack`: the same combinations, channel weights,
        error model and static term)."""
        kpd = self.kpd
        if cov is None:
            raise KpifsError(f"{kpd.name}: a block search of spectral-differential data needs "
                             f"the data's covariance")
        sst = SpectralStack(kpd, kp, cov, spectrum=spectrum)
        mix = sst.data_mixing                                                  # (k, q)
        self.spectrum, self.data_mixing = sst.spectrum, mix
        self.mixing = sst.mixing
        self.n_comb = k = mix.shape[0]
        rb = replace(rb, data=np.einsum("kc,bcp->bkp", mix, rb.data),
                     noise=np.einsum("kc,ncp->nkp", mix, rb.noise))
        rows = None if kpd.covariance_rows is None else \
            np.einsum("kc,ncp->nkp", mix, kpd.covariance_rows)
        if rows is not None and sst.static_rows is not None:
            rows = np.concatenate([rows, sst.static_rows])
        self.spectral = {"basis": kpd.spectral.get("basis"), "profiles": sst.info["profiles"],
                         "combinations": int(k), "static_amplitude": sst.static_amplitude,
                         "static_amplitudes": sst.static_amplitudes}
        self._scale, self.combinations = sst.scale, sst.combinations
        return rb, mix @ kp, sst.combination_whitening, sst.rank, rows

    def detection_model(self, grid, *, basis=None):
        """The `BlockModel` on *grid*; in the angular-differential mode, what the rotation
        lets survive is measured (``self.info['retained']``, by separation) and too
        little of it is refused (nothing could be found) or warned about; of channel
        combinations (ASDI), what the spectral projection keeps too
        (``self.info['spectral']``)."""
        kpd = self.kpd
        model = BlockModel(kpd.kernel_model, kpd.wavelengths, grid, self.comp_mean,
                           self.comp_frame, self.blocks.angles, self.blocks.frames,
                           spread=self.spread(), pixscale=kpd.pixscale, window=kpd.window,
                           dof=self.rank, basis=basis, mixing=self.mixing)
        self.info = {"mode": self.mode, "n_blocks": int(self.blocks.n_blocks),
                     "frames": self.blocks.frames.tolist(),
                     "angles": np.round(self.blocks.angles, 4).tolist(),
                     "span": self.blocks.span, "frame_modes": int(self.comp_frame.shape[1]),
                     "mean_scale": self.mean_scale}
        if not self.with_mean:
            self.info["retained"] = _check_rotation(model, kpd, self.blocks)
        if self.mixing is not None:
            self.info["spectral"] = dict(self.spectral, **retained_by_separation(
                kpd.kernel_model, kpd.wavelengths, grid, self.combinations,
                spectrum=self.spectrum, scale=self._scale))
        return model

    def spread(self):
        """The r.m.s. of each block's frames' angles about the block's angle (deg; zeros
        when the frames' angles are not known)."""
        rb = self.blocks
        return np.array([np.sqrt(np.mean(((self._frame_angles[lab] - a + 180) % 360 - 180) ** 2))
                         for a, lab in zip(rb.angles, self._block_frames)])

    def _exponentials(self, sky):
        """``exp(-i theta)`` of a companion at *sky* (dRA, dDec; mas) per frame, channel and
        uv point (N, q, nuv): every frame at its own angle (a block's mean is the mean of
        its frames' models: a bright companion's model at the block's mean angle would
        leave side lobes)."""
        kpd = self.kpd
        x, y = sky_to_detector(float(sky[0]), float(sky[1]), self._frame_angles)   # (N,)
        lam = kpd.wavelengths.to_value(u.m)
        uv = kpd.kernel_model.uv.value
        theta = 2 * np.pi * MAS * (np.outer(x, uv[:, 0]) + np.outer(y, uv[:, 1]))
        return np.exp(-1j * theta[:, None, :] / lam[None, :, None])

    def model_kp(self, sky, contrast, *, derivative=False):
        """Whitened stacked model (q, dim) of a companion at *sky* (dRA, dDec; mas) of
        *contrast* (per channel, the window's attenuation included); with *derivative*,
        also its derivative with respect to each channel's contrast (q, dim)."""
        km = self.kpd.kernel_model
        lam = self.kpd.wavelengths.to_value(u.m)
        # K arg(1 + c exp(-i theta)) per block and channel, as KernelModel.binary_kernel_phases
        h = self._exponentials(sky)
        if self.mixing is not None:
            return self._mixed_model(h, contrast, derivative)
        c = np.broadcast_to(np.asarray(contrast, float), lam.shape)
        z = 1 + c[None, :, None] * h
        out = self._stack(self._by_block(np.angle(z)) @ km.kernel.T)
        if not derivative:
            return out
        return out, self._stack(self._by_block(np.imag(h / z)) @ km.kernel.T)   # d arg / dc

    def _mixed_model(self, h, contrast, derivative):
        """`model_kp` of channel combinations: combination ``i`` with its own contrast
        scale ``c_i`` times the spectrum shape in every channel, mixed by ``D``."""
        kern = self.kpd.kernel_model.kernel
        ca, at = distinct_contrasts(contrast, self.spectrum, self.n_comb)    # (u, q)
        z = 1 + ca[None, :, :, None] * h[:, None]                            # (N, u, q, nuv)

        def mixed(a):                   # per-frame (N, u, q, nuv) -> stacked (k, dim)
            per = (self._by_block(a) @ kern.T)[:, at]                         # (B, k, q, p)
            return self._stack(np.einsum("kc,bkcp->bkp", self.data_mixing, per))
        out = mixed(np.angle(z))
        if not derivative:
            return out
        return out, mixed(np.imag(self.spectrum[None, None, :, None] * h[:, None] / z))

    def spectrum_model(self, sky, contrasts):
        """`model_kp` of channel combinations (ASDI) with a contrast of its own in every
        channel (*contrasts* (q,), window included), and its derivatives with respect to
        each channel's contrast (q, k, dim): its spectrum measured through the
        combinations (`~kpifs.detect._blockfit.fit_spectrum`)."""
        kern = self.kpd.kernel_model.kernel
        h = self._exponentials(sky)
        z = 1 + np.asarray(contrasts, float)[None, :, None] * h                  # (N, q, nuv)
        per = self._by_block(np.angle(z)) @ kern.T                               # (B, q, p)
        dper = self._by_block(np.imag(h / z)) @ kern.T
        mix = self.data_mixing
        out = self._stack(np.einsum("kc,bcp->bkp", mix, per))
        return out, np.stack([self._stack(mix[None, :, c, None] * dper[:, None, c])
                              for c in range(mix.shape[1])])

    def channel_contrasts(self, c, cerr):
        """The combinations' contrast maps as the channels' (ASDI: their weighted mean times
        the spectrum shape, `~kpifs.detect.combinations.combination_contrasts`); as they are
        otherwise."""
        if self.mixing is None:
            return c, cerr
        return combination_contrasts(self.spectrum, c, cerr)

    def channel_table(self, cands):
        """The candidates' per-combination contrast columns as per-channel ones (in place;
        ASDI only)."""
        if self.mixing is not None:
            combination_table(self.spectrum, self.n_comb, cands)

    def _by_block(self, a):
        """Per-frame values (N, ...) averaged within each block (B, ...)."""
        return np.stack([a[lab].mean(axis=0) for lab in self._block_frames])

    def _stack(self, per):
        """Per-block kernel phases (B, q, p) -> the whitened stack (q, dim)."""
        rb = self.blocks
        mean = np.tensordot(rb.frames / rb.frames.sum(), per, axes=(0, 0))
        dev = np.sqrt(rb.frames)[:, None, None] * (per - mean)
        dev = np.einsum("iap,bip->iba", self.comp_frame, dev).reshape(per.shape[1], -1)
        if not self.with_mean:
            return dev
        return np.concatenate([np.einsum("iap,ip->ia", self.comp_mean, mean), dev], axis=-1)

    def _attenuation(self, x, y):
        kpd = self.kpd
        if kpd.window is None:
            return 1.0
        return float(kpd.window.at(np.hypot(x, y), kpd.pixscale))

    def refine(self, cands, residual, noise_rows=None, box=20.0):
        """Fit each candidate's sky offset and contrasts to the stacked data (in place, as
        `~kpifs.detect.fit.refine_candidates`); returns the fitted models."""
        return refine_stack(self, cands, residual, noise_rows, box)


def _rows(comp, rows):
    return np.einsum("iap,fip->fia", comp, rows)


def _pad(rows, n, *, after):
    z = np.zeros(rows.shape[:2] + (n,))
    return np.concatenate([rows, z] if after else [z, rows], axis=-1)


def block_stack(kpd, kp, w, rank, *, frame, mode="auto", cov=None, spectrum=None):
    """The `BlockStack` of a search, or None for the fast path (one mean, as before):
    blocks are searched on the sky when the data carry them (``kpd.rotation``); *mode*
    ``'auto'`` takes the data's own (``meta['block_search']``, else ``'rotation'``). Data
    with spectral-differential profiles (``kpd.spectral``) are searched by their channel
    combinations (ASDI), with the data's covariance *cov* (q, p, p) and the companion's
    *spectrum* shape."""
    if mode not in MODES + ("auto",):
        raise KpifsError(f"unknown block search {mode!r}: use one of {MODES} or 'auto'")
    if getattr(kpd, "rotation", None) is None or frame != "sky":
        if mode == "angular-differential":
            raise KpifsError(f"{kpd.name}: an angular-differential search needs the time "
                             f"blocks of a rotating sequence (kpifs extract "
                             f"--angular-differential on frames whose angles turn)")
        return None
    if mode == "auto":
        mode = kpd.rotation.search
    if mode == "mean":
        return None
    return BlockStack(kpd, kp, w, rank, mode=mode, cov=cov, spectrum=spectrum)
