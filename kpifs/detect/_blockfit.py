"""The fit of a block search's candidates (`kpifs.detect.blocks.BlockStack.refine`)."""
import numpy as np
from astropy import units as u

from .._lazy import lazy_module
from .._utils import one_blas_thread
from .fit import fit_errors

optimize = lazy_module("scipy.optimize")

__all__ = ["refine_stack"]


def refine_stack(stack, cands, residual, noise_rows=None, box=20.0):
    """Fit each candidate's sky offset (within *box* mas) and contrasts to the stacked
    data of *stack* (a `~kpifs.detect.blocks.BlockStack`; *cands* in place, as
    `~kpifs.detect.fit.refine_candidates`); returns the fitted models (q, dim)."""
    q = residual.shape[0]
    cols = {k: [] for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err", "fit_contrast",
                            "fit_contrast_err", "fit_chi2")}
    models = []
    for row in cands:
        x0, y0 = row["x"].to_value(u.mas), row["y"].to_value(u.mas)
        c0 = np.asarray(row["contrast"], float)
        scale_c = max(float(np.max(np.abs(c0))), 1e-6)

        def resid(par):
            c = par[2:] * scale_c * stack._attenuation(par[0], par[1])
            return (residual - stack.model_kp(par[:2], c)).ravel()

        def jac(par, step=1e-3):
            # contrasts: exact (channel by channel); position: central differences
            att = stack._attenuation(par[0], par[1])
            _, dc = stack.model_kp(par[:2], par[2:] * scale_c * att, derivative=True)
            out = np.zeros((q, dc.shape[1], len(par)))
            out[np.arange(q), :, 2 + np.arange(q)] = -dc * scale_c * att
            for j in range(2):
                d = np.zeros(len(par))
                d[j] = step
                out[:, :, j] = ((resid(par + d) - resid(par - d)) / (2 * step)).reshape(
                    q, -1)
            return out.reshape(-1, len(par))

        start = np.concatenate([[x0, y0], c0 / scale_c])
        lo = np.concatenate([[x0 - box, y0 - box], np.full(q, -np.inf)])
        hi = np.concatenate([[x0 + box, y0 + box], np.full(q, np.inf)])
        with one_blas_thread():          # small products: BLAS's threads only wait
            res = optimize.least_squares(resid, start, bounds=(lo, hi), jac=jac)
        err = fit_errors(res.jac, noise_rows)
        cols["fit_x"].append(res.x[0])
        cols["fit_y"].append(res.x[1])
        cols["fit_x_err"].append(err[0])
        cols["fit_y_err"].append(err[1])
        cols["fit_contrast"].append(res.x[2:] * scale_c)
        cols["fit_contrast_err"].append(err[2:] * scale_c)
        cols["fit_chi2"].append(float(2 * res.cost))
        att = stack._attenuation(res.x[0], res.x[1])
        models.append(stack.model_kp(res.x[:2], res.x[2:] * scale_c * att))
    for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
        cands[k] = np.array(cols[k]) * u.mas
    cands["fit_contrast"] = np.array(cols["fit_contrast"]).reshape(len(cands), q)
    cands["fit_contrast_err"] = np.array(cols["fit_contrast_err"]).reshape(len(cands), q)
    cands["fit_chi2"] = np.array(cols["fit_chi2"])
    return models
