"""The fit of a block search's candidates (`kpifs.detect.blocks.BlockStack.refine`)."""
import numpy as np
from astropy import units as u

from .._lazy import lazy_module
from .._utils import one_blas_thread
from .fit import fit_errors

optimize = lazy_module("scipy.optimize")

__all__ = ["refine_stack", "fit_spectrum", "information_kept"]


#: The spectrum's least-squares steps leave out directions of the channels' contrasts
#: whose singular value is below this fraction of the largest (those the combinations
#: do not measure keep the start: the spectrum shape times the fitted scale).
SPECTRUM_RCOND = 1e-10
#: Channels keeping less than this fraction of their information have no error (NaN).
KEPT_FLOOR = 1e-9


def refine_stack(stack, cands, residual, noise_rows=None, box=20.0):
    """Fit each candidate's sky offset (within *box* mas) and contrasts to the stacked
    data of *stack* (a `~kpifs.detect.blocks.BlockStack`; *cands* in place, as
    `~kpifs.detect.fit.refine_candidates`); returns the fitted models (q, dim).

    A stack of channel combinations (``stack.mixing``: spectral-differential, ASDI)
    is fitted in two steps. The position, with one contrast scale shared by every
    combination (the companion's, times the spectrum shape): one free contrast, not
    one per combination, which would take 18 more parameters from the position's
    constraints on 19 combinations (``fit_contrast_model``, per channel). Then, at
    that position, the companion's own contrast in every channel (`fit_spectrum`:
    ``fit_contrast``, its errors with the position's uncertainty carried, and
    ``fit_contrast_kept``, how much of each channel's information the combinations
    keep once the rest is fitted). Its model is the one subtracted: a companion
    whose spectrum is not the shape searched for would otherwise leave a residual
    for the search to find next."""
    tied = getattr(stack, "mixing", None) is not None
    rows, models = [], []
    for row in cands:
        fit = _fit_position(stack, row, residual, noise_rows, box, tied)
        if not tied:
            model = stack.model_kp(fit["pos"], fit["model_contrasts"])
        else:
            # the spectrum's model is the one subtracted (the shape's is not made)
            spec = fit_spectrum(stack, fit["pos"], residual, fit["scale"] * stack.spectrum,
                                noise_rows=noise_rows)
            model = spec["model"]
            fit.update(fit_chi2=spec["chi2"], fit_contrast_model=fit["scale"] * stack.spectrum,
                       fit_contrast_model_err=fit["scale_err"] * stack.spectrum,
                       fit_contrast=spec["contrast"], fit_contrast_err=spec["error"],
                       fit_contrast_kept=spec["kept"])
        rows.append(fit)
        models.append(model)
    for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
        cands[k] = np.array([f[k] for f in rows]) * u.mas
    q = len(stack.spectrum) if tied else residual.shape[0]
    names = ("fit_contrast", "fit_contrast_err", "fit_contrast_kept", "fit_contrast_model",
             "fit_contrast_model_err") if tied else ("fit_contrast", "fit_contrast_err")
    for k in names:
        cands[k] = np.array([f[k] for f in rows]).reshape(len(cands), q)
    cands["fit_chi2"] = np.array([f["fit_chi2"] for f in rows])
    return models


def _fit_position(stack, row, residual, noise_rows, box, tied):
    """One candidate's least-squares fit (`refine_stack`): its columns' values, with
    ``pos``, the contrasts its model takes (``model_contrasts``, window included) and
    the shared ``scale`` and ``scale_err`` of a stack of combinations."""
    q = residual.shape[0]
    nc = 1 if tied else q
    x0, y0 = row["x"].to_value(u.mas), row["y"].to_value(u.mas)
    c0 = np.asarray(row["contrast"], float)
    if tied:                    # the combinations' contrast scales: one start
        c0 = np.atleast_1d(np.nanmedian(c0))
    scale_c = max(float(np.max(np.abs(c0))), 1e-6)

    def contrasts(par):
        return np.broadcast_to(par[2:], (q,)) * scale_c * stack._attenuation(par[0], par[1])

    def resid(par):
        return (residual - stack.model_kp(par[:2], contrasts(par))).ravel()

    def jac(par, step=1e-3):
        # contrasts: exact (channel by channel); position: central differences
        att = stack._attenuation(par[0], par[1])
        _, dc = stack.model_kp(par[:2], contrasts(par), derivative=True)
        out = np.zeros((q, dc.shape[1], len(par)))
        if tied:
            out[:, :, 2] = -dc * scale_c * att
        else:
            out[np.arange(q), :, 2 + np.arange(q)] = -dc * scale_c * att
        for j in range(2):
            d = np.zeros(len(par))
            d[j] = step
            out[:, :, j] = ((resid(par + d) - resid(par - d)) / (2 * step)).reshape(q, -1)
        return out.reshape(-1, len(par))

    start = np.concatenate([[x0, y0], c0 / scale_c])
    lo = np.concatenate([[x0 - box, y0 - box], np.full(nc, -np.inf)])
    hi = np.concatenate([[x0 + box, y0 + box], np.full(nc, np.inf)])
    with one_blas_thread():          # small products: BLAS's threads only wait
        res = optimize.least_squares(resid, start, bounds=(lo, hi), jac=jac)
    err = fit_errors(res.jac, noise_rows)
    fit = {"pos": res.x[:2], "fit_x": res.x[0], "fit_y": res.x[1], "fit_x_err": err[0],
           "fit_y_err": err[1], "fit_chi2": float(2 * res.cost),
           "fit_contrast": np.broadcast_to(res.x[2:] * scale_c, (q,)),
           "fit_contrast_err": np.broadcast_to(err[2:] * scale_c, (q,))}
    if tied:
        fit.update(scale=float(res.x[2] * scale_c), scale_err=float(err[2] * scale_c))
    fit["model_contrasts"] = contrasts(res.x)
    return fit


def fit_spectrum(stack, pos, data, start, *, noise_rows=None, step=1e-3, n_iter=10):
    """A companion's contrast in every channel at its fitted position *pos* (the fit with
    the spectrum shape searched for), from the whitened channel combinations *data*
    (k, dim) of *stack* (`stack.spectrum_model`).

    Gauss-Newton steps from *start* (q,), each the least-squares solution of least
    norm (`SPECTRUM_RCOND`): what the combinations do not measure keeps the start (the
    shape times the fitted scale). The position stays: fitted together with 22 free
    contrasts it moves further with the noise (measured on CHARIS simulations), and
    a spectrum far from the shape pulls it by a fraction of its error beyond the inner
    separation (more inside).

    Returns ``{'contrast', 'error', 'kept', 'chi2', 'model'}``: the contrasts (q,),
    their 1-sigma errors (`~kpifs.detect.fit.fit_errors` of the model with the
    position free too: its uncertainty is carried; with *noise_rows*, of the noise they
    describe; NaN where a channel is not measured at all), the fraction of each
    channel's information left once the position and the other channels are fitted
    (`information_kept`), the chi-square and the model at the fit (k, dim), window
    included.
    """
    pos = np.asarray(pos, float)
    c = np.array(start, float)
    q, att = len(c), stack._attenuation(*pos)

    def model(p, jacobian=False):
        out, dc = stack.spectrum_model(p, c * stack._attenuation(*p))
        return (out, dc * att) if jacobian else out

    for _ in range(n_iter):
        out, dc = model(pos, jacobian=True)
        d = np.linalg.lstsq(dc.reshape(q, -1).T, (data - out).ravel(), rcond=SPECTRUM_RCOND)[0]
        c += d
        if np.max(np.abs(d)) <= 1e-9 * max(np.max(np.abs(c)), 1e-300):
            break
    out, dc = model(pos, jacobian=True)
    # the position's columns by central differences, as the position fit's
    full = np.column_stack([(model(pos + d) - model(pos - d)).ravel() / (2 * step)
                            for d in np.eye(2) * step] + [dc.reshape(q, -1).T])
    kept = information_kept(full)[2:]
    err = fit_errors(full, noise_rows)[2:]
    return {"contrast": c, "error": np.where(kept > KEPT_FLOOR, err, np.nan), "kept": kept,
            "chi2": float(np.sum((data - out) ** 2)), "model": out}


def information_kept(jac):
    """Per column of a whitened Jacobian *jac* (n, q), the fraction of its information
    left once the other columns are fitted too: ``1 / (F_ii (F^-1)_ii)`` with ``F =
    J^T J`` (1 for a column orthogonal to the others, 0 for one they can stand for).

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect._blockfit import information_kept
    >>> information_kept(np.array([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])).tolist()
    [1.0, 1.0]
    >>> np.round(information_kept(np.array([[1.0, 1.0], [0.0, 1.0]])), 3).tolist()
    [0.5, 0.5]
    """
    f = jac.T @ jac
    vals, vecs = np.linalg.eigh(f)
    vals = np.maximum(vals, np.finfo(float).eps * max(vals.max(), 0.0))
    inv_diag = np.sum(vecs ** 2 / np.where(vals > 0, vals, np.inf), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        kept = 1 / (np.diag(f) * inv_diag)
    return np.clip(np.nan_to_num(kept, nan=0.0, posinf=0.0), 0.0, 1.0)
