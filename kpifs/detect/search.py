"""The sequential search: the strongest peak above the threshold, fitted and
subtracted, judged by the noise its residual shows, until none is left
(`kpifs.detect.detect`)."""
import logging
import warnings

import numpy as np
from astropy import units as u
from astropy.table import vstack

from ..covariance import whiten
from ..exceptions import KpifsWarning
from .fit import refine_candidates
from .sky import rotated_binary_kernel_phases

__all__ = []

log = logging.getLogger(__name__)

#: How each statistic scales with the noise variance (B: a sum of squares).
_POWER = {"B": 1.0, "B-paper": 0.5, "NP": 0.5, "S": 1.0}


def _chi2_red(residual, w, dof, n_par):
    """Reduced chi-square of whitened kernel phases with *n_par* fitted parameters."""
    return float(np.sum(whiten(residual, w) ** 2) / max(dof - n_par, 1))


def _sequential_search(model, kp, w, kpd, *, threshold, null, spectrum, fit, max_candidates,
                       scaler, ring, poses=None, characterise=None, stack=None):
    """Strongest peak above threshold, fitted and subtracted, until none is left.

    Each peak is judged on its statistic scaled by the reduced chi-square of
    the whitened residual once its model is subtracted (never scaled down), and
    its errors are scaled likewise: a calibration residual the error model
    missed inflates the chi-square instead of passing as companions. Returns
    the candidates, the reduced chi-square of the final residual and the noise
    scale (*scaler*: residual, fitted parameters -> reduced chi-square, scale).
    """
    rows = []
    residual = kp.copy()
    form = null.form
    q = kp.shape[0]
    n_par = 2 + q
    while len(rows) < max_candidates:
        tab = model.candidates(whiten(residual, w), threshold=threshold, form=form, null=null,
                               spectrum=spectrum)
        if not len(tab):
            break
        row = tab[:1]
        if fit and stack is not None:
            model_kp = stack.refine(row, residual, null.noise_rows)[0]
            r = row[0]
            x, y = r["fit_x"].to_value(u.mas), r["fit_y"].to_value(u.mas)
        elif fit:
            model_kp = refine_candidates(row, residual, w, kpd, null.noise_rows, poses)[0]
            if characterise is not None:
                # from the search model's optimum (the robust start), the characterisation
                model_kp = refine_candidates(row, residual, characterise[0], kpd,
                                             characterise[1], poses, dof=characterise[2],
                                             from_fit=True)[0]
            r = row[0]
            x, y = r["fit_x"].to_value(u.mas), r["fit_y"].to_value(u.mas)
        else:
            # the subtracted model is the fitted one, window gain included (a bright
            # companion's approximate model would leave side lobes to be found next)
            r = row[0]
            x, y, c = r["x"].to_value(u.mas), r["y"].to_value(u.mas), np.asarray(r["contrast"])
            att = 1.0 if kpd.window is None else \
                float(kpd.window.at(np.hypot(x, y), kpd.pixscale))
            if stack is not None:
                model_kp = stack.model_kp((x, y), c * att)
            elif poses is None:
                model_kp = kpd.kernel_model.binary_kernel_phases([x, y] * u.mas, c * att,
                                                                 kpd.wavelengths)
            else:
                model_kp = rotated_binary_kernel_phases(kpd.kernel_model, [x, y] * u.mas,
                                                        c * att, kpd.wavelengths, *poses)
        after = residual - model_kp
        kappa, scale = scaler(after, n_par * (len(rows) + 1))
        # judged against its annulus's noise too, once subtracted (a bright companion's
        # side lobes gone), away from the peak and its mirror (what its fit absorbed)
        peak = (float(row["x"][0].to_value(u.mas)), float(row["y"][0].to_value(u.mas)))
        around = ring(after, peak)
        log.debug("peak %.2f: noise scale %.2f after its subtraction, %.2f in its annulus",
                  float(row["statistic"][0]), scale, around)
        scale = max(scale, around)
        stat = float(row["statistic"][0]) / scale ** _POWER[form]
        if stat < threshold:
            log.info("peak at (%.1f, %.1f) mas: statistic %.2f / chi2_red %.2f is below the "
                     "threshold %.2f", x, y, float(row["statistic"][0]), kappa, threshold)
            break
        pfa, tail = null.pfa(np.array([stat]), return_method=True)
        row["statistic"] = [stat]
        row["pfa_global"], row["pfa_global_tail"] = pfa, tail
        row["pfa_local"] = model.local_pfa(np.array([stat]), form)
        row["contrast_err"] = row["contrast_err"] * np.sqrt(scale)
        if fit and characterise is None:
            for col in ("fit_x_err", "fit_y_err", "fit_contrast_err"):
                row[col] = row[col] * np.sqrt(scale)
        row["chi2_red"] = [kappa]
        residual = after
        rows.append(row)
    if len(rows) == max_candidates:
        warnings.warn(f"{kpd.name}: the search stopped at max_candidates = {max_candidates}; "
                      f"more peaks may lie above the threshold", KpifsWarning, stacklevel=3)
    kappa, scale = scaler(residual, n_par * len(rows))
    if not rows:
        empty = model.candidates(whiten(kp, w), threshold=np.inf, form=form, null=null,
                                 spectrum=spectrum)
        if fit:
            for col in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
                empty[col] = [] * u.mas
            empty["fit_contrast"] = np.zeros((0, q))
            empty["fit_contrast_err"] = np.zeros((0, q))
            empty["fit_chi2"] = np.zeros(0)
        empty["chi2_red"] = np.zeros(0)
        return empty, kappa, scale
    out = vstack(rows)
    out.meta = rows[0].meta
    out.meta["chi2_red"] = kappa
    return out, kappa, scale
