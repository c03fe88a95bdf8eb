"""The sequential search: the strongest peak above the threshold, fitted and
subtracted, judged by the noise its residual shows, until none is left; then
the candidates judged together, each with the others in the model
(`kpifs.detect.detect`)."""
import logging
import warnings

import numpy as np
from astropy import units as u
from astropy.table import vstack

from .._lazy import lazy_module
from ..covariance import whiten
from ..exceptions import KpifsWarning
from .fit import refine_candidates
from .quality import resolution_mas
from .sky import rotated_binary_kernel_phases
from .statistics import get_test

__all__ = []

log = logging.getLogger(__name__)
optimize = lazy_module("scipy.optimize")


def _chi2_red(residual, w, dof, n_par):
    """Reduced chi-square of whitened kernel phases with *n_par* fitted parameters."""
    return float(np.sum(whiten(residual, w) ** 2) / max(dof - n_par, 1))


def _fit_row(row, residual, ctx, *, from_fit=False):
    """Fit one candidate (a 1-row table, updated in place) on *residual*; returns the
    model subtracted: the fitted one, window gain included (a bright companion's
    approximate model would leave side lobes to be found next)."""
    model, kpd, null, w, poses, characterise, stack = (
        ctx[k] for k in ("model", "kpd", "null", "w", "poses", "characterise", "stack"))
    if ctx["fit"] and stack is not None:
        return stack.refine(row, residual, null.noise_rows)[0]
    if ctx["fit"]:
        model_kp = refine_candidates(row, residual, w, kpd, null.noise_rows, poses,
                                     from_fit=from_fit)[0]
        if characterise is not None:
            # from the search model's optimum (the robust start), the characterisation
            model_kp = refine_candidates(row, residual, characterise[0], kpd,
                                         characterise[1], poses, dof=characterise[2],
                                         from_fit=True)[0]
        return model_kp
    r = row[0]
    x, y, c = r["x"].to_value(u.mas), r["y"].to_value(u.mas), np.asarray(r["contrast"])
    att = 1.0 if kpd.window is None else float(kpd.window.at(np.hypot(x, y), kpd.pixscale))
    if stack is not None:
        return stack.model_kp((x, y), c * att)
    if poses is None:
        return kpd.kernel_model.binary_kernel_phases([x, y] * u.mas, c * att, kpd.wavelengths)
    return rotated_binary_kernel_phases(kpd.kernel_model, [x, y] * u.mas, c * att,
                                        kpd.wavelengths, *poses)


def _scale_errors(row, scale, ctx):
    """The search fit's errors scaled by the noise *scale* its candidate was judged with."""
    if ctx["fit"] and ctx["characterise"] is None:
        for col in ("fit_x_err", "fit_y_err", "fit_contrast_err"):
            row[col] = row[col] * np.sqrt(scale)


def _sequential_search(model, kp, w, kpd, *, threshold, null, spectrum, fit, max_candidates,
                       scaler, ring, poses=None, characterise=None, stack=None):
    """Strongest peak above threshold, fitted and subtracted, until none is left.

    Each peak is judged on its statistic scaled by the reduced chi-square of
    the whitened residual once its model is subtracted (never scaled down), and
    its errors are scaled likewise: a calibration residual the error model
    missed inflates the chi-square instead of passing as companions. The
    candidates found are then judged together (`_joint_check`): one that the
    others explain is not a detection. Returns the candidates, the reduced
    chi-square of the final residual and the noise scale (*scaler*: residual,
    fitted parameters -> reduced chi-square, scale).
    """
    rows, models, scales = [], [], []
    residual = kp.copy()
    form = null.form
    q = kp.shape[0]
    n_par = 2 + q
    ctx = dict(model=model, kpd=kpd, null=null, w=w, poses=poses, characterise=characterise,
               stack=stack, fit=fit)
    while len(rows) < max_candidates:
        tab = model.candidates(whiten(residual, w), threshold=threshold, form=form, null=null,
                               spectrum=spectrum)
        if not len(tab):
            break
        row = tab[:1]
        model_kp = _fit_row(row, residual, ctx)
        r = row[0]
        x, y = (r["fit_x"], r["fit_y"]) if fit else (r["x"], r["y"])
        x, y = x.to_value(u.mas), y.to_value(u.mas)
        after = residual - model_kp
        kappa, scale = scaler(after, n_par * (len(rows) + 1))
        # judged against its annulus's noise too, once subtracted (a bright companion's
        # side lobes gone), away from the peak and its mirror (what its fit absorbed)
        peak = (float(row["x"][0].to_value(u.mas)), float(row["y"][0].to_value(u.mas)))
        around = ring(after, peak)
        log.debug("peak %.2f: noise scale %.2f after its subtraction, %.2f in its annulus",
                  float(row["statistic"][0]), scale, around)
        scale = max(scale, around)
        stat = float(row["statistic"][0]) / scale ** get_test(form).power
        if stat < threshold:
            log.info("peak at (%.1f, %.1f) mas: statistic %.2f / chi2_red %.2f is below the "
                     "threshold %.2f", x, y, float(row["statistic"][0]), kappa, threshold)
            break
        pfa, tail = null.pfa(np.array([stat]), return_method=True)
        row["statistic"] = [stat]
        row["pfa_global"], row["pfa_global_tail"] = pfa, tail
        row["pfa_local"] = model.local_pfa(np.array([stat]), form)
        row["contrast_err"] = row["contrast_err"] * np.sqrt(scale)
        _scale_errors(row, scale, ctx)
        row["chi2_red"] = [kappa]
        residual = after
        rows.append(row)
        models.append(model_kp)
        scales.append(scale)
    if len(rows) == max_candidates:
        warnings.warn(f"{kpd.name}: the search stopped at max_candidates = {max_candidates}; "
                      f"more peaks may lie above the threshold", KpifsWarning, stacklevel=3)
    if len(rows) > 1:
        rows, residual = _joint_check(rows, models, scales, kp, ctx, threshold=threshold,
                                      spectrum=spectrum, scaler=scaler, ring=ring)
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


def _near(model, stat, points, radius):
    """The largest of *stat* (a map) within *radius* mas of any of *points* (NaN: none)."""
    g = model.grid
    near = np.zeros(g.shape, bool)
    for px, py in points:
        near |= np.hypot(g.X - px, g.Y - py) <= radius
    vals = np.where(near & g.valid, stat, np.nan)
    return float(np.nanmax(vals)) if np.any(np.isfinite(vals)) else np.nan


#: Most other candidates refitted for each one judged (`_joint_check`); beyond, their
#: models are only scaled to the data together.
JOINT_REFIT = 4


def _others(kp, w, models, idx, refit=None, judged=None):
    """The models *idx* as the data have them together: each refitted (*refit*: index,
    data -> model) on the data less the others, when there are at most `JOINT_REFIT`,
    then scaled, channel by channel, to fit *kp* together with the *judged* candidate's
    model (non-negative least squares in the whitened space): without the share of the
    signal that an earlier fit took, nor the judged candidate's own signal."""
    out = np.zeros_like(kp)
    if not idx:
        return out
    models = dict(models) if isinstance(models, dict) else dict(enumerate(models))
    if refit is not None and len(idx) <= JOINT_REFIT:
        for j in idx:
            models[j] = refit(j, kp - sum((models[i] for i in idx if i != j),
                                          np.zeros_like(kp)))
    terms = list(idx) + ([] if judged is None else [judged])
    for i in range(kp.shape[0]):
        basis = np.stack([w[i] @ models[j][i] for j in terms], axis=1)      # (p, n)
        if not np.any(basis):
            continue
        coef = optimize.nnls(basis, w[i] @ kp[i])[0]          # a companion's flux is never negative
        out[i] = np.stack([models[j][i] for j in idx], axis=1) @ coef[:len(idx)]
    return out


def _joint_check(rows, models, scales, kp, ctx, *, threshold, spectrum, scaler, ring):
    """Drop the candidates that the others explain, weakest first, and refit the rest.

    Candidate ``k`` is judged on the data less the other candidates' models
    (refitted without it, `_others`): its statistic there, at its grid
    peak and its fit (the largest within a grid step of either), scaled by the
    noise of the residual of all of them (and of its annulus), must still pass
    *threshold*. A peak that the search met before the companion that made it
    (a side lobe, or a fit that walked to the mirror of a real companion's
    signal) explains the data worse than the residual level once that
    companion is in the model, and goes. Returns the kept rows and the
    residual of their models.
    """
    model, null, w = ctx["model"], ctx["null"], ctx["w"]
    form = null.form
    n_par = 2 + kp.shape[0]

    radius = float(np.max(np.abs(model.grid.step))) * (1 + 1e-9)
    walk = max(radius, resolution_mas(ctx["kpd"].kernel_model, ctx["kpd"].wavelengths))

    def refit(j, data):
        # on a copy: the candidate's own row is kept as found. A refit that walks more than
        # a resolution element (and a grid step) away has found another source (typically
        # the one being judged, once it is left out of the model): the candidate keeps its
        # model as found.
        row = rows[j].copy()
        fitted = _fit_row(row, data, ctx, from_fit=True)
        if not ctx["fit"]:
            return fitted
        r0, r1 = rows[j][0], row[0]
        moved = np.hypot(*((r1[c] - r0[c]).to_value(u.mas) for c in ("fit_x", "fit_y")))
        return fitted if moved <= walk else models[j]
    keep = list(range(len(rows)))
    dropped = []
    while len(keep) > 1:
        _, scale = scaler(kp - _others(kp, w, models, keep), n_par * len(keep))
        stats = {}
        for k in keep:
            r = rows[k][0]
            pts = [(r["x"].to_value(u.mas), r["y"].to_value(u.mas))]
            if ctx["fit"]:
                pts.append((r["fit_x"].to_value(u.mas), r["fit_y"].to_value(u.mas)))
            rest = kp - _others(kp, w, models, [j for j in keep if j != k], refit, judged=k)
            t = model.local_statistic(whiten(rest, w), form, spectrum)
            s = max(scale, ring(rest - models[k], pts[0]))
            stats[k] = np.nan_to_num(_near(model, t, pts, radius), nan=0.0) \
                / s ** get_test(form).power
        worst = min(keep, key=lambda k: stats[k])
        if stats[worst] >= threshold:
            break
        r = rows[worst][0]
        log.info("candidate at (%.1f, %.1f) mas left out: with the other candidates in the "
                 "model its statistic is %.2f, below the threshold %.2f", r["x"].to_value(u.mas),
                 r["y"].to_value(u.mas), stats[worst], threshold)
        keep.remove(worst)
        dropped.append(worst)
    if dropped:
        # the rest refitted without the models of those left out
        for k in keep:
            others = sum((models[j] for j in keep if j != k), np.zeros_like(kp))
            models[k] = _fit_row(rows[k], kp - others, ctx, from_fit=True)
            _scale_errors(rows[k], scales[k], ctx)
    return [rows[k] for k in keep], kp - sum(models[j] for j in keep)
