"""The sequential search: the strongest peak above the threshold, fitted and
subtracted, judged by the noise its residual shows, until none is left; then
the candidates judged together, each with the others in the model
(`kpifs.detect.detect`)."""
import logging
import warnings
from dataclasses import dataclass

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


@dataclass(frozen=True, slots=True)
class _Search:
    """What every step of one sequential search reads, and none changes.

    Attributes
    ----------
    model : `~kpifs.detect.DetectionModel`
        The projection searched (its grid, statistics and local laws).
    kpd : `~kpifs.data.KernelPhaseData`
        The data (kernel model, wavelengths, window and pixel scale of the models).
    null : `~kpifs.detect.NullCalibration`
        The null: its test (``form``), global P_FA and whitened noise rows.
    w : ndarray
        The whitening, one matrix per channel.
    fit : bool
        Whether candidates are fitted (else their grid models are subtracted).
    threshold : float
        The statistic a candidate must reach, at its noise scale.
    spectrum : ndarray or None
        The companion spectrum the statistics assume (None: free).
    scaler : callable
        ``scaler(residual, n_par) -> (reduced chi-square, noise scale)``.
    ring : callable
        ``ring(residual, peak) -> noise scale`` of the annulus around *peak* (mas).
    poses : tuple or None
        The frames' rotation for a model on the sky (`rotated_binary_kernel_phases`).
    characterise : object or None
        The characterisation's error model (its ``whitening``, ``whitened_rows`` and
        ``dof``): candidates refitted with it.
    stack : object or None
        A stack of channel combinations or time blocks that models and refits its
        candidates itself.
    """

    model: object
    kpd: object
    null: object
    w: np.ndarray
    fit: bool
    threshold: float
    spectrum: object
    scaler: object
    ring: object
    poses: tuple = None
    characterise: object = None
    stack: object = None

    @property
    def power(self):
        """The power of the noise scale the test's statistic is divided by."""
        return get_test(self.null.form).power


def _fit_row(row, residual, search, *, from_fit=False):
    """Fit one candidate (a 1-row table, updated in place) on *residual*; returns the
    model subtracted: the fitted one, window gain included (a bright companion's
    approximate model would leave side lobes to be found next)."""
    kpd, poses, characterise, stack = search.kpd, search.poses, search.characterise, \
        search.stack
    if search.fit and stack is not None:
        return stack.refine(row, residual, search.null.noise_rows)[0]
    if search.fit:
        model_kp = refine_candidates(row, residual, search.w, kpd, search.null.noise_rows,
                                     poses, from_fit=from_fit)[0]
        if characterise is not None:
            # from the search model's optimum (the robust start), the characterisation
            model_kp = refine_candidates(row, residual, characterise.whitening, kpd,
                                         characterise.whitened_rows, poses,
                                         dof=characterise.dof, from_fit=True)[0]
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


def _scale_errors(row, scale, search):
    """The search fit's errors scaled by the noise *scale* its candidate was judged with."""
    if search.fit and search.characterise is None:
        for col in ("fit_x_err", "fit_y_err", "fit_contrast_err", "fit_contrast_model_err"):
            if col in row.colnames:
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
    search = _Search(model, kpd, null, w, fit, threshold, spectrum, scaler, ring, poses,
                     characterise, stack)
    rows, models, scales = [], [], []
    residual = kp.copy()
    n_par = 2 + kp.shape[0]
    while len(rows) < max_candidates:
        found = _next_candidate(search, residual, n_par * (len(rows) + 1))
        if found is None:
            break
        row, model_kp, residual, scale = found
        rows.append(row)
        models.append(model_kp)
        scales.append(scale)
    if len(rows) == max_candidates:
        warnings.warn(f"{kpd.name}: the search stopped at max_candidates = {max_candidates}; "
                      f"more peaks may lie above the threshold", KpifsWarning, stacklevel=3)
    if len(rows) > 1:
        rows, residual = _joint_check(rows, models, scales, kp, search)
    kappa, scale = scaler(residual, n_par * len(rows))
    if not rows:
        return _no_candidates(search, kp), kappa, scale
    out = vstack(rows)
    out.meta = rows[0].meta
    out.meta["chi2_red"] = kappa
    return out, kappa, scale


def _next_candidate(search, residual, n_par):
    """The strongest peak of *residual* above the threshold, fitted and judged with
    *n_par* parameters fitted in all (see `_sequential_search`): its 1-row table
    (statistic, P_FA and errors at its noise scale), its model, the residual once
    that is subtracted and the noise scale; None when no peak passes."""
    model, null = search.model, search.null
    tab = model.candidates(whiten(residual, search.w), threshold=search.threshold,
                           form=null.form, null=null, spectrum=search.spectrum)
    if not len(tab):
        return None
    row = tab[:1]
    model_kp = _fit_row(row, residual, search)
    after = residual - model_kp
    kappa, scale = search.scaler(after, n_par)
    # judged against its annulus's noise too, once subtracted (a bright companion's
    # side lobes gone), away from the peak and its mirror (what its fit absorbed)
    peak = (float(row["x"][0].to_value(u.mas)), float(row["y"][0].to_value(u.mas)))
    around = search.ring(after, peak)
    log.debug("peak %.2f: noise scale %.2f after its subtraction, %.2f in its annulus",
              float(row["statistic"][0]), scale, around)
    scale = max(scale, around)
    stat = float(row["statistic"][0]) / scale ** search.power
    if stat < search.threshold:
        where = ("fit_x", "fit_y") if search.fit else ("x", "y")
        x, y = (row[0][col].to_value(u.mas) for col in where)
        log.info("peak at (%.1f, %.1f) mas: statistic %.2f / chi2_red %.2f is below the "
                 "threshold %.2f", x, y, float(row["statistic"][0]), kappa, search.threshold)
        return None
    pfa, tail = null.pfa(np.array([stat]), return_method=True)
    row["statistic"] = [stat]
    row["pfa_global"], row["pfa_global_tail"] = pfa, tail
    row["pfa_local"] = model.local_pfa(np.array([stat]), null.form)
    row["contrast_err"] = row["contrast_err"] * np.sqrt(scale)
    _scale_errors(row, scale, search)
    row["chi2_red"] = [kappa]
    return row, model_kp, after, scale


def _no_candidates(search, kp):
    """The empty candidate table of a search that found none (the columns of one that
    did)."""
    empty = search.model.candidates(whiten(kp, search.w), threshold=np.inf,
                                    form=search.null.form, null=search.null,
                                    spectrum=search.spectrum)
    if search.fit:
        for col in ("fit_x", "fit_y", "fit_x_err", "fit_y_err"):
            empty[col] = [] * u.mas
        empty["fit_contrast"] = np.zeros((0, kp.shape[0]))
        empty["fit_contrast_err"] = np.zeros((0, kp.shape[0]))
        empty["fit_chi2"] = np.zeros(0)
    empty["chi2_red"] = np.zeros(0)
    return empty


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
    by_index = dict(models) if isinstance(models, dict) else dict(enumerate(models))
    if refit is not None and len(idx) <= JOINT_REFIT:
        for j in idx:
            by_index[j] = refit(j, kp - sum((by_index[i] for i in idx if i != j),
                                            np.zeros_like(kp)))
    terms = list(idx) + ([] if judged is None else [judged])
    for i in range(kp.shape[0]):
        basis = np.stack([w[i] @ by_index[j][i] for j in terms], axis=1)      # (p, n)
        if not np.any(basis):
            continue
        coef = optimize.nnls(basis, w[i] @ kp[i])[0]          # a companion's flux is never negative
        out[i] = np.stack([by_index[j][i] for j in idx], axis=1) @ coef[:len(idx)]
    return out


def _refit(search, row, found, walk, data):
    """A candidate's model refitted on *data* (the data less the others' models), on a
    copy of its *row*: the row is kept as found. A refit that walks more than *walk* mas
    away has found another source (typically the one being judged, once it is left out
    of the model): the candidate keeps its model as *found*."""
    moved_row = row.copy()
    fitted = _fit_row(moved_row, data, search, from_fit=True)
    if not search.fit:
        return fitted
    r0, r1 = row[0], moved_row[0]
    moved = np.hypot(*((r1[c] - r0[c]).to_value(u.mas) for c in ("fit_x", "fit_y")))
    return fitted if moved <= walk else found


def _joint_check(rows, models, scales, kp, search):
    """Drop the candidates that the others explain, weakest first, and refit the rest.

    Candidate ``k`` is judged on the data less the other candidates' models
    (refitted without it, `_others`): its statistic there, at its grid
    peak and its fit (the largest within a grid step of either), scaled by the
    noise of the residual of all of them (and of its annulus), must still pass
    *threshold*. A peak that the search met before the companion that made it
    (a side lobe, or a fit that walked to the mirror of a real companion's
    signal) explains the data worse than the residual level once that
    companion is in the model, and goes. Returns the kept rows and the
    residual of their models (*search*: the search's `_Search`).
    """
    model, w = search.model, search.w
    n_par = 2 + kp.shape[0]
    radius = float(np.max(np.abs(model.grid.step))) * (1 + 1e-9)
    walk = max(radius, resolution_mas(search.kpd.kernel_model, search.kpd.wavelengths))

    def refit(j, data):
        return _refit(search, rows[j], models[j], walk, data)
    keep = list(range(len(rows)))
    dropped = []
    while len(keep) > 1:
        _, scale = search.scaler(kp - _others(kp, w, models, keep), n_par * len(keep))
        stats = {}
        for k in keep:
            r = rows[k][0]
            pts = [(r["x"].to_value(u.mas), r["y"].to_value(u.mas))]
            if search.fit:
                pts.append((r["fit_x"].to_value(u.mas), r["fit_y"].to_value(u.mas)))
            rest = kp - _others(kp, w, models, [j for j in keep if j != k], refit, judged=k)
            t = model.local_statistic(whiten(rest, w), search.null.form, search.spectrum)
            s = max(scale, search.ring(rest - models[k], pts[0]))
            stats[k] = np.nan_to_num(_near(model, t, pts, radius), nan=0.0) / s ** search.power
        worst = min(keep, key=lambda k: stats[k])
        if stats[worst] >= search.threshold:
            break
        r = rows[worst][0]
        log.info("candidate at (%.1f, %.1f) mas left out: with the other candidates in the "
                 "model its statistic is %.2f, below the threshold %.2f", r["x"].to_value(u.mas),
                 r["y"].to_value(u.mas), stats[worst], search.threshold)
        keep.remove(worst)
        dropped.append(worst)
    if dropped:
        # the rest refitted without the models of those left out
        for k in keep:
            others = sum((models[j] for j in keep if j != k), np.zeros_like(kp))
            models[k] = _fit_row(rows[k], kp - others, search, from_fit=True)
            _scale_errors(rows[k], scales[k], search)
    return [rows[k] for k in keep], kp - sum(models[j] for j in keep)
