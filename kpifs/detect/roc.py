"""The seed paper's ROC experiment: the tests compared on a simulated IFS scene.

Steps: simulate the scene (`~kpifs.simulation.simulate.simulate_scene`); extract the
companion-free calibrator frames and estimate, per channel, the covariance of
one frame's kernel phases; whiten; form the whitened companion signal
``x_i = W_i K arg(1 + c_i w exp(-2 pi i (alpha u + beta v)/lambda_i))``; draw M
realisations of ``y = e`` (H0) and ``y = x + e`` (H1) with ``e`` standard normal
in each channel's whitened subspace; compute every test on the whole set of
channels and on each channel alone; compare with the theory for NP and E, and
for the subspace test S at the companion's known position
(`theory_roc_subspace`).
"""
import logging

import numpy as np
from astropy import units as u
from astropy.table import QTable

from .._lazy import lazy_module
from ..covariance import empirical_covariance
from ..extraction.extract import extract_kernel_phases
from ..model.kernel import KernelModel
from ..model.pupil import make_pupil
from ..simulation.simulate import simulate_scene
from .stats import TESTS, auc, known_position_subspace, monte_carlo_roc, roc_curve

stats = lazy_module("scipy.stats")

__all__ = ["paper_experiment", "theory_roc", "theory_roc_subspace", "subspace_mean",
           "whitened_signal"]

log = logging.getLogger(__name__)


def _bases(cov, rtol=1e-6):
    """Whitening operators and orthonormal bases of the kept eigen-subspaces."""
    ws, bases = [], []
    for c in cov:
        vals, vecs = np.linalg.eigh(0.5 * (c + c.T))
        keep = vals > rtol * vals.max()
        v = vecs[:, keep]
        ws.append((v / np.sqrt(vals[keep])) @ v.T)
        bases.append(v)
    return np.array(ws), bases


def whitened_signal(kernel_model, whitening, wavelengths, offset, contrasts, *, window_factor=1.0):
    """``W_i K arg(1 + c_i w exp(...))`` per channel: (q, p).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, make_pupil
    >>> from kpifs.detect.roc import whitened_signal
    >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
    >>> x = whitened_signal(km, np.eye(km.n_kp)[None], [1.6] * u.um, [80, 60] * u.mas, [1e-3])
    >>> x.shape
    (1, 37)
    """
    kp = kernel_model.binary_kernel_phases(offset, np.asarray(contrasts) * window_factor,
                                           wavelengths)
    return np.einsum("wij,wj->wi", whitening, kp)


def theory_roc(test, norm_x, dof, pfa):
    """Theoretical ``P_D(P_FA)`` for ``'NP'`` and ``'E'``.

    Examples
    --------
    >>> from kpifs.detect.roc import theory_roc
    >>> round(float(theory_roc("NP", 3.0, None, 0.01)), 4)
    0.7497
    """
    pfa = np.asarray(pfa, float)
    if test == "NP":
        return stats.norm.sf(stats.norm.isf(pfa) - norm_x)
    if test == "E":
        return stats.ncx2.sf(stats.chi2.isf(pfa, dof), dof, norm_x ** 2)
    raise ValueError(test)


def subspace_mean(norms):
    """Mean ``(mu_h, lambda_perp, r)`` of the subspace statistic's projections at a known
    position: ``gamma = W z ~ N(mu, I_r)``, ``mu_h`` its part along the sign vector ``h``
    and ``lambda_perp`` the squared rest (as `~kpifs.detect.stats.monte_carlo_roc`
    builds ``W`` and ``h`` from the channels' signal norms *norms*).

    Examples
    --------
    >>> from kpifs.detect.roc import subspace_mean
    >>> mu_h, lam, r = subspace_mean([2.0, 2.0, 2.0, 2.0])   # flat: all along h
    >>> round(mu_h, 4), round(lam, 6), r
    (4.0, 0.0, 3)
    """
    norms = np.asarray(norms, float)
    w, h = known_position_subspace(norms)
    mu = w @ norms
    mu_h = float(mu @ h / np.linalg.norm(h))
    return mu_h, float(max(mu @ mu - mu_h ** 2, 0.0)), len(w)


def theory_roc_subspace(mu_h, lam_perp, r, pfa):
    """Theoretical ``P_D(P_FA)`` of the subspace test at a known position.

    ``S = |gamma|^2`` when ``h . gamma > 0`` (else 0), ``gamma ~ N(mu, I_r)``: with
    ``g`` the part along ``h``, ``P(S > t) = int_0^inf phi(g - mu_h)
    P(chi2'_{r-1}(lambda_perp) > t - g^2) dg``; under H0 that is half the chi2 law
    with r degrees of freedom, so the threshold at *pfa* (< 0.5) is
    ``chi2.isf(2 pfa, r)``.

    Examples
    --------
    >>> from kpifs.detect.roc import theory_roc_subspace
    >>> round(float(theory_roc_subspace(0.0, 0.0, 3, 0.01)), 4)     # H1 = H0
    0.01
    """
    pfa = np.atleast_1d(np.asarray(pfa, float))
    out = np.empty(pfa.shape)
    g = np.linspace(0.0, mu_h + 12.0, 4001)[1:] if mu_h > 0 else np.linspace(0, 12, 4001)[1:]
    dens = stats.norm.pdf(g - mu_h)
    for k, pf in enumerate(pfa):
        if pf >= 0.5:
            out[k] = np.nan
            continue
        t = stats.chi2.isf(2 * pf, r)
        rest = t - g ** 2
        if r == 1:
            tail = (rest <= 0).astype(float)
        elif lam_perp > 0:
            tail = np.where(rest <= 0, 1.0, stats.ncx2.sf(np.maximum(rest, 0), r - 1, lam_perp))
        else:
            tail = np.where(rest <= 0, 1.0, stats.chi2.sf(np.maximum(rest, 0), r - 1))
        out[k] = np.trapezoid(dens * tail, g)
    return out if out.size > 1 else out[0]


def _theory_auc_subspace(mu_h, lam_perp, r):
    # continuous part (P_FA < 0.5), then the atom at 0: H0 half the time, H1 when
    # h . gamma <= 0 (probability Phi(-mu_h)); ties count half, as in `auc`
    grid = np.concatenate([np.logspace(-10, -3, 200), np.linspace(1e-3, 0.5, 800)[1:-1]])
    cont = np.trapezoid(theory_roc_subspace(mu_h, lam_perp, r, grid), grid)
    q1 = stats.norm.cdf(-mu_h)
    return float(cont + 0.5 * ((1 - q1) + 0.5 * q1))


def _theory_auc(test, norm_x, dof):
    if test == "NP":
        return float(stats.norm.cdf(norm_x / np.sqrt(2)))
    grid = np.concatenate([np.logspace(-12, -3, 400), np.linspace(1e-3, 1, 4000)[1:]])
    return float(np.trapezoid(theory_roc(test, norm_x, dof, grid), grid))


def paper_experiment(*, preset="paper", n_frames=1000, n_draws=30000, seed=0, pfa_ref=0.01,
                     progress=False, **scene):
    """Run the ROC experiment; returns ``(table, curves)``.

    Parameters
    ----------
    preset : str
        Scene preset (`~kpifs.simulation.simulate.PRESETS`); *scene* overrides its fields.
    n_frames : int
        Calibrator frames used to estimate the covariance.
    n_draws : int
        Monte-Carlo draws under each hypothesis.
    seed : int
        Seeds the simulation and the draws.
    pfa_ref : float
        False-alarm probability at which ``P_D`` is tabulated.

    Returns
    -------
    table : `~astropy.table.QTable`
        One row per (test, channel set): ``auc``, ``pd`` at *pfa_ref*, and
        ``auc_theory``, ``pd_theory`` for NP and E; ``norm_x`` and ``dof``.
    curves : dict
        ``{channel set: {test: (pfa, pd)}}`` plus ``'theory'`` entries.

    Examples
    --------
    >>> import warnings
    >>> from kpifs.detect.roc import paper_experiment
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")       # 20 frames: shrinkage warning
    ...     table, curves = paper_experiment(n_frames=20, n_draws=2000, seed=1, npup=32,
    ...                                      shape=(24, 24))
    >>> sorted(set(str(t) for t in table["test"]))
    ['B', 'B-paper', 'E', 'NP', 'S']
    """
    obs = simulate_scene(preset, n_frames=n_frames, seed=seed, progress=progress, **scene)
    p = obs.params
    km = KernelModel.from_pupil(make_pupil(p.telescope))
    kpd = extract_kernel_phases(obs.calibrator, km, wavelengths=p.wavelengths,
                                pixscale=p.pixscale, source="simulated calibrator",
                                keep_phases=False)
    km = kpd.kernel_model
    cov = empirical_covariance(kpd.kp, source="simulated calibrator")
    w, bases = _bases(cov)
    wfac = float(kpd.window.at(np.hypot(*p.companion_offset.to_value(u.mas)), p.pixscale))
    x = whitened_signal(km, w, p.wavelengths, p.companion_offset, p.contrasts,
                        window_factor=wfac)
    q = len(p.wavelengths)
    sets = {"all": list(range(q))}
    sets.update({f"{p.wavelengths[i].to_value(u.um):.2f}um": [i] for i in range(q)})
    rng = np.random.default_rng(seed)
    rows, curves = [], {}
    for name, chans in sets.items():
        xs = x[chans]
        dof = int(sum(bases[i].shape[1] for i in chans))
        norm = float(np.linalg.norm(xs))
        res = monte_carlo_roc(xs, n_draws=n_draws, seed=rng, basis=[bases[i] for i in chans])
        curves[name] = {}
        for test in TESTS:
            t0, t1 = res[test]
            pf, pdet = roc_curve(t0, t1)
            curves[name][test] = (pf, pdet)
            thr = np.quantile(t0, 1 - pfa_ref, method="higher")
            row = {"channels": name, "test": test, "norm_x": norm, "dof": dof,
                   "auc": auc(t0, t1), "pd": float(np.mean(t1 > thr)),
                   "auc_theory": np.nan, "pd_theory": np.nan}
            if test in ("NP", "E"):
                row["auc_theory"] = _theory_auc(test, norm, dof)
                row["pd_theory"] = float(theory_roc(test, norm, dof, pfa_ref))
                curves[name][f"{test} theory"] = (pf, theory_roc(test, norm, dof, pf))
            elif test == "S":
                sm = subspace_mean(np.linalg.norm(xs, axis=1))
                row["auc_theory"] = _theory_auc_subspace(*sm)
                row["pd_theory"] = float(theory_roc_subspace(*sm, pfa_ref))
            rows.append(row)
    table = QTable(rows=[[r[k] for k in rows[0]] for r in rows], names=list(rows[0]))
    table.meta.update({"preset": preset, "n_frames": n_frames, "n_draws": n_draws,
                       "seed": seed, "pfa_ref": pfa_ref, "n_kp": km.n_kp,
                       "separation_mas": float(np.hypot(*p.companion_offset.to_value(u.mas))),
                       "contrasts": [float(c) for c in p.contrasts],
                       "window_factor": wfac})
    return table, curves
