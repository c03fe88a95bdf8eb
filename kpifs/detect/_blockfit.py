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
    `~kpifs.detect.fit.refine_candidates`); returns the fitted models (q, dim).

    A stack of channel combinations (``stack.mixing``: spectral-differential, ASDI)
    has one contrast scale, the companion's, shared by every combination (each
    combination measures it through its own mixture of the channels): one free
    contrast, not one per combination, which would take 18 more parameters from
    the position's constraints on 19 combinations. Its ``fit_contrast`` columns, per
    combination as the search's, then all hold that scale, each with ``sqrt(k)`` times
    its error (the ``k`` columns' weighted mean, as the channels' contrasts are made,
    `~kpifs.detect.combinations.combination_table`, gives the scale and its error)."""
    q = residual.shape[0]
    tied = getattr(stack, "mixing", None) is not None
    nc = 1 if tied else q
    cols = {k: [] for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err", "fit_contrast",
                            "fit_contrast_err", "fit_chi2")}
    models = []
    for row in cands:
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
                out[:, :, j] = ((resid(par + d) - resid(par - d)) / (2 * step)).reshape(
                    q, -1)
            return out.reshape(-1, len(par))

        start = np.concatenate([[x0, y0], c0 / scale_c])
        lo = np.concatenate([[x0 - box, y0 - box], np.full(nc, -np.inf)])
        hi = np.concatenate([[x0 + box, y0 + box], np.full(nc, np.inf)])
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
        models.append(stack.model_kp(res.x[:2], contrasts(res.x)))
    for k in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
        cands[k] = np.array(cols[k]) * u.mas
    share = np.sqrt(q) if tied else 1.0
    cands["fit_contrast"] = np.broadcast_to(
        np.array(cols["fit_contrast"]).reshape(len(cands), nc), (len(cands), q)).copy()
    cands["fit_contrast_err"] = np.broadcast_to(
        np.array(cols["fit_contrast_err"]).reshape(len(cands), nc) * share,
        (len(cands), q)).copy()
    cands["fit_chi2"] = np.array(cols["fit_chi2"])
    return models
