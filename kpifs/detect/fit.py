"""Non-linear fit of a binary model to calibrated kernel phases.

The model in channel ``i`` is ``K arg(1 + c_i g(u) exp(-2 pi i (alpha u +
beta v) / lambda_i))`` (``g`` the extraction window's gain at the companion,
`kpifs.detect.gain`) and the residuals are whitened with the per-channel
``W_i``; the parameters are the offset ``(alpha, beta)`` in mas and one contrast
per channel (the companion's low-resolution spectrum). Uncertainties come from
the Jacobian at the optimum.
"""
import numpy as np
from astropy import units as u

from .._lazy import lazy_module
from ..exceptions import KpifsError
from ..model.kernel import MAS
from .gain import window_gain
from .sky import sky_to_detector

optimize = lazy_module("scipy.optimize")

__all__ = ["fit_binary", "fit_errors", "refine_candidates"]


class _BinaryModel:
    """The binary model of `fit_binary`, its whitened residuals and their Jacobian."""

    def __init__(self, kp, whitening, kernel_model, wavelengths, pixscale, window, detpa,
                 detpa_weights):
        self.kp, self.whitening, self.km, self.window = kp, whitening, kernel_model, window
        self.lam = np.atleast_1d(u.Quantity(wavelengths, u.um)).to_value(u.m)
        self.uv, self.kern = kernel_model.uv.value, kernel_model.kernel
        self.ps = None if pixscale is None else u.Quantity(pixscale, u.mas).value
        if detpa is None:
            self.rot = None
        else:
            ang = np.atleast_1d(np.asarray(u.Quantity(detpa, u.deg).value, float))
            rw = np.ones(ang.size) if detpa_weights is None else np.asarray(detpa_weights, float)
            self.rot = (ang, rw / rw.sum())
        self.corr = None

    def wfac(self, a, b):
        if self.ps is None or self.window is None:
            return 1.0
        return float(self.window.at(np.hypot(a, b), self.ps))

    def poses(self, a, b):
        if self.rot is None:
            return np.array([a]), np.array([b]), np.ones(1)
        xs, ys = sky_to_detector(a, b, self.rot[0])
        return np.atleast_1d(xs), np.atleast_1d(ys), self.rot[1]

    def set_correction(self, a, b, window_correction):
        """Per-pose complex correction g(u) / w(r0) of the window's gain
        (`kpifs.detect.gain`), computed at a reference position and held fixed while
        the optimiser moves: it varies on the window's scale, not the fringes'."""
        xs, ys, _ = self.poses(a, b)
        if self.ps is None or self.window is None or not window_correction:
            self.corr = [1.0] * len(xs)
            return
        self.corr = [window_gain(self.km, self.window, self.ps * u.mas, self.lam * u.m,
                                 (xf, yf)) / max(self.wfac(xf, yf), 1e-12)
                     for xf, yf in zip(xs, ys)]

    def model(self, params):
        a, b = params[:2]
        c = params[2:]
        xs, ys, ws = self.poses(a, b)
        cw = (c * self.wfac(a, b))[:, None]
        uv, lam = self.uv, self.lam
        out = 0.0
        for xf, yf, wf, cr in zip(xs, ys, ws, self.corr):
            theta = 2 * np.pi * (xf * MAS * uv[:, 0] + yf * MAS * uv[:, 1])[None, :] / lam[:, None]
            out = out + wf * np.angle(1 + cw * cr * np.exp(-1j * theta))
        return out @ self.kern.T

    def resid(self, params):
        r = self.kp - self.model(params)
        return np.einsum("wij,wj->wi", self.whitening, r).ravel()

    def _window_slope(self, a, b):
        if self.ps is None or self.window is None:
            return (0.0, 0.0)
        h = 1e-4
        return ((self.wfac(a + h, b) - self.wfac(a - h, b)) / (2 * h),
                (self.wfac(a, b + h) - self.wfac(a, b - h)) / (2 * h))

    def jac(self, params):
        # phi = arg(1 + c w h), h = corr e^{-i theta}, z = 1 + c w h:
        # d phi / d(c w) = Im(h / z), d phi / d theta = -Re(c w h / z)
        a, b = params[:2]
        c = params[2:]
        q, uv, lam, rot, whitening = len(c), self.uv, self.lam, self.rot, self.whitening
        wf = self.wfac(a, b)
        dw = self._window_slope(a, b)
        xs, ys, ws = self.poses(a, b)
        if rot is None:
            cs, sn = np.array([-1.0]), np.array([0.0])
        else:
            cs, sn = -np.cos(np.deg2rad(rot[0])), np.sin(np.deg2rad(rot[0]))
        # d(x, y)/d(a, b) = [[cs, sn], [sn, -cs]] (detector frame: identity)
        g = (c * wf)[:, None]
        k = 2 * np.pi * MAS / lam[:, None]
        dphi = np.zeros((q + 2, q, uv.shape[0]))
        for xf, yf, wt, cf, sf, cr in zip(xs, ys, ws, cs, sn, self.corr):
            theta = k * (xf * uv[:, 0] + yf * uv[:, 1])[None, :]
            hh = cr * np.exp(-1j * theta)
            ratio = hh / (1 + g * hh)
            dg = ratio.imag
            dth = -(g * ratio).real
            if rot is None:
                dxa, dya, dxb, dyb = 1.0, 0.0, 0.0, 1.0
            else:
                dxa, dya, dxb, dyb = cf, sf, sf, -cf
            dphi[0] += wt * (dth * k * (dxa * uv[:, 0] + dya * uv[:, 1]) + dg * c[:, None] * dw[0])
            dphi[1] += wt * (dth * k * (dxb * uv[:, 0] + dyb * uv[:, 1]) + dg * c[:, None] * dw[1])
            dphi[2 + np.arange(q), np.arange(q)] += wt * dg * wf
        p = self.kp.shape[1]
        out = np.zeros((q, p, q + 2))
        # position: every channel; contrast j: channel j only
        out[:, :, :2] = np.einsum("wij,nwj->win", whitening, dphi[:2] @ self.kern.T)
        dc = dphi[2 + np.arange(q), np.arange(q)] @ self.kern.T            # (q, p)
        out[np.arange(q), :, 2 + np.arange(q)] = np.einsum("wij,wj->wi", whitening, dc)
        return -out.reshape(q * p, q + 2)


def fit_binary(kp, whitening, kernel_model, wavelengths, start, contrast0, *, pixscale=None,
               window=None, bounds_mas=None, noise_rows=None, detpa=None,
               detpa_weights=None, jacobian="analytic", window_correction=True):
    """Fit position and per-channel contrasts of a companion.

    Parameters
    ----------
    kp : ndarray, shape (q, p)
        Calibrated kernel phases.
    whitening : ndarray, shape (q, p, p)
    kernel_model : `~kpifs.model.kernel.KernelModel`
    wavelengths : `~astropy.units.Quantity` (q,)
    start : tuple
        Starting ``(alpha, beta)`` in mas.
    contrast0 : array-like (q,)
        Starting contrasts.
    pixscale, window
        The pixel scale and the extraction window
        (`~kpifs.model.window.ExtractionWindow`), so
        that contrasts are true ones.
    bounds_mas : float, optional
        Half-width of the box (mas) around *start* the position may move in.
    noise_rows : ndarray, shape (nrow, q, p), optional
        Whitened covariance rows (``R_w^T R_w`` = covariance of the whitened
        data across channels). With them the uncertainties are the sandwich
        estimate ``(J^T J)^-1 (R_w J)^T (R_w J) (J^T J)^-1``, which accounts for
        correlations between channels; without, ``(J^T J)^-1``.
    detpa : array-like, optional
        Detector position angles (deg) of the frames (or PA bins,
        `kpifs.detect.sky.pa_bins`) averaged in *kp*. With them the position
        (*start* and the results) is the sky offset ``(dRA, dDec)`` and the
        model is the weighted mean of the per-angle models
        (`kpifs.detect.sky`); without, detector offsets.
    detpa_weights : array-like, optional
        Weights of *detpa* (default equal).
    jacobian : {'analytic', '2-point', '3-point'}
        The Jacobian of the model: exact derivatives (default) or
        scipy's finite differences.
    window_correction : bool
        Model the window's effect baseline by baseline
        (`kpifs.detect.gain.window_gain`, default) instead of a single factor
        ``w(r0)``: unbiased contrasts out to the window's edge.

    Returns
    -------
    dict
        ``x``, ``y`` (mas; ``dRA``, ``dDec`` with *detpa*), ``x_err``, ``y_err``,
        ``contrast`` (q,), ``contrast_err`` (q,), ``chi2``, ``dof``, ``success``,
        ``frame`` (``'sky'`` or ``'detector'``) and ``model``, the fitted kernel
        phases (q, p), window gain included (what a search subtracts).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.detect.fit import fit_binary
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    >>> wl = [1.6] * u.um
    >>> kp = km.binary_kernel_phases([60, -30] * u.mas, [5e-3], wl)
    >>> w = np.eye(km.n_kp)[None] * 1e4
    >>> r = fit_binary(kp, w, km, wl, (55.0, -25.0), [3e-3])
    >>> round(float(r["x"]), 1), round(float(r["y"]), 1), round(float(r["contrast"][0]), 4)
    (60.0, -30.0, 0.005)
    """
    kp = np.asarray(kp, float)
    q, p = kp.shape
    bm = _BinaryModel(kp, whitening, kernel_model, wavelengths, pixscale, window, detpa,
                      detpa_weights)
    x0 = np.concatenate([np.asarray(start, float), np.asarray(contrast0, float)])
    if x0.size != q + 2:
        raise KpifsError(f"need {q} starting contrasts, got {np.size(contrast0)}")
    half = bounds_mas if bounds_mas is not None else 20.0
    lo = np.concatenate([x0[:2] - half, np.full(q, -0.5)])
    hi = np.concatenate([x0[:2] + half, np.full(q, 0.5)])
    x0 = np.clip(x0, lo + 1e-12, hi - 1e-12)
    scale = np.concatenate([[1.0, 1.0], np.maximum(np.abs(x0[2:]), 1e-5)])
    if jacobian not in ("analytic", "2-point", "3-point"):
        raise KpifsError(f"jacobian must be 'analytic', '2-point' or '3-point', got {jacobian!r}")
    kw = dict(jac=bm.jac if jacobian == "analytic" else jacobian, bounds=(lo, hi),
              x_scale=scale, method="trf")
    bm.set_correction(*x0[:2], window_correction)
    res = optimize.least_squares(bm.resid, x0, **kw)
    if window_correction and bm.ps is not None and window is not None:
        # once more with the correction at the fitted position
        bm.set_correction(*res.x[:2], window_correction)
        res = optimize.least_squares(bm.resid, np.clip(res.x, lo + 1e-12, hi - 1e-12), **kw)
    jac = res.jac
    err = fit_errors(jac, noise_rows)
    dof = int(np.count_nonzero(np.abs(whitening).sum(axis=2))) - (q + 2)
    return {"x": res.x[0], "y": res.x[1], "x_err": err[0], "y_err": err[1],
            "contrast": res.x[2:], "contrast_err": err[2:], "chi2": float(2 * res.cost),
            "dof": dof, "success": bool(res.success),
            "frame": "detector" if bm.rot is None else "sky", "model": bm.model(res.x)}


def fit_errors(jac, noise_rows=None):
    """1-sigma errors of a least-squares fit from its whitened Jacobian: ``(J^T J)^+``,
    or, with *noise_rows* (the whitened noise's rows), the sandwich ``(J^T J)^+ J^T
    R^T R J (J^T J)^+`` of the noise they describe.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.fit import fit_errors
    >>> fit_errors(np.eye(3) * 2.0).tolist()
    [0.5, 0.5, 0.5]
    """
    cov = np.linalg.pinv(jac.T @ jac)
    if noise_rows is not None:
        rj = np.asarray(noise_rows, float).reshape(len(noise_rows), -1) @ jac
        cov = cov @ (rj.T @ rj) @ cov
    return np.sqrt(np.clip(np.diag(cov), 0, None))


def _walk(kp, w, kpd, start, c0, step, noise_rows, kw):
    """`fit_binary` from *start* in a box of +-*step* mas, walking on (at most 4 boxes)
    while the box stops it (a grid peak off the optimum, as a spectral-model test's
    can be near the grid's edge)."""
    for _ in range(4):
        r = fit_binary(kp, w, kpd.kernel_model, kpd.wavelengths, start, c0,
                       pixscale=kpd.pixscale, window=kpd.window, bounds_mas=step,
                       noise_rows=noise_rows, **kw)
        if max(abs(r["x"] - start[0]), abs(r["y"] - start[1])) < 0.95 * step:
            break
        start, c0 = (r["x"], r["y"]), np.asarray(r["contrast"])
    return r


def refine_candidates(cands, kp, w, kpd, noise_rows=None, poses=None, dof=None,
                      from_fit=False):
    """Fit each candidate (from its grid peak, or *from_fit* its earlier fit); with
    *dof* (the whitened dimension of *w*, a characterisation model) the errors are
    scaled by the fit's own reduced chi-square (never down) and ``fit_chi2_red`` is
    added. Returns the fitted models' kernel phases, one (q, p) array per candidate
    (what `~kpifs.detect.detect` subtracts before it searches again).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.detect.fit import refine_candidates
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
    >>> wl = [1.6] * u.um
    >>> kp = km.binary_kernel_phases([60, -30] * u.mas, [5e-3], wl)
    >>> kpd = KernelPhaseData(kp[None], wl, 10 * u.mas, km)
    >>> t = QTable({"x": [55.0] * u.mas, "y": [-25.0] * u.mas, "contrast": [[3e-3]]})
    >>> models = refine_candidates(t, kp, np.eye(km.n_kp)[None] * 1e4, kpd)
    >>> round(float(t["fit_x"][0].value), 1), models[0].shape == kp.shape
    (60.0, True)
    """
    q = kp.shape[0]
    cols = {k: [] for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err", "fit_contrast",
                            "fit_contrast_err", "fit_chi2")}
    models = []
    step = 20.0
    for row in cands:
        kw = {} if poses is None else dict(detpa=poses[0], detpa_weights=poses[1])
        pre = "fit_" if from_fit else ""
        start = (row[pre + "x"].to_value(u.mas), row[pre + "y"].to_value(u.mas))
        c0 = np.asarray(row[pre + "contrast"])
        r = _walk(kp, w, kpd, start, c0, step, noise_rows, kw)
        if np.mean(r["contrast"]) < 0:
            # kernel phases are odd: (x, c) and (-x, -c) are one model to first order, and
            # a companion's contrast is positive (a grid peak of channels correlated by a
            # common error can sit at the mirror): the fit from the mirror decides
            flip = _walk(kp, w, kpd, (-r["x"], -r["y"]), -np.asarray(r["contrast"]), step,
                         noise_rows, kw)
            if flip["chi2"] <= r["chi2"] * (1 + 1e-6) or np.mean(flip["contrast"]) > 0:
                r = flip
        k = 1.0
        if dof is not None:
            chi2_red = r["chi2"] / max(dof - (q + 2), 1)
            cols.setdefault("fit_chi2_red", []).append(chi2_red)
            k = np.sqrt(max(1.0, chi2_red))
        cols["fit_x"].append(r["x"])
        cols["fit_y"].append(r["y"])
        cols["fit_x_err"].append(r["x_err"] * k)
        cols["fit_y_err"].append(r["y_err"] * k)
        cols["fit_contrast"].append(r["contrast"])
        cols["fit_contrast_err"].append(np.asarray(r["contrast_err"]) * k)
        cols["fit_chi2"].append(r["chi2"])
        models.append(r["model"])
    for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
        cands[k] = np.array(cols[k]) * u.mas
    cands["fit_contrast"] = np.array(cols["fit_contrast"]).reshape(len(cands), q)
    cands["fit_contrast_err"] = np.array(cols["fit_contrast_err"]).reshape(len(cands), q)
    cands["fit_chi2"] = np.array(cols["fit_chi2"])
    if "fit_chi2_red" in cols:
        cands["fit_chi2_red"] = np.array(cols["fit_chi2_red"])
    return models
