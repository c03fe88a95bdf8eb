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

from ..covariance import empirical_covariance
from ..extraction.extract import extract_kernel_phases
from ..model.kernel import KernelModel
from ..model.pupil import make_pupil
from ..simulation.simulate import simulate_scene
from .known_position import monte_carlo_roc
from .statistics import REGISTRY, get_test
# where they were before the tests became objects (issue 38)
from .statistics.subspace import subspace_mean, theory_roc_subspace  # noqa: F401
from .stats import auc, roc_curve

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
    """Theoretical ``P_D(P_FA)`` of a test with a closed form at a known position
    (`DetectionTest.theory_pd <kpifs.detect.statistics.DetectionTest.theory_pd>`)
    for a signal of norm *norm_x* and *dof* noise dimensions.

    Examples
    --------
    >>> from kpifs.detect.roc import theory_roc
    >>> round(float(theory_roc("NP", 3.0, None, 0.01)), 4)
    0.7497
    """
    out = get_test(test).theory_pd(np.array([[float(norm_x)]]), dof, pfa)
    if out is None:
        raise ValueError(f"test {test!r} has no closed-form ROC")
    return out


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
        for test in REGISTRY.values():
            if test.name not in res:
                continue
            t0, t1 = res[test.name]
            pf, pdet = roc_curve(t0, t1)
            curves[name][test.name] = (pf, pdet)
            thr = np.quantile(t0, 1 - pfa_ref, method="higher")
            row = {"channels": name, "test": test.name, "norm_x": norm, "dof": dof,
                   "auc": auc(t0, t1), "pd": float(np.mean(t1 > thr)),
                   "auc_theory": np.nan, "pd_theory": np.nan}
            theory = test.theory_pd(xs, dof, pf)
            if theory is not None:
                row["auc_theory"] = test.theory_auc(xs, dof)
                row["pd_theory"] = float(test.theory_pd(xs, dof, pfa_ref))
                curves[name][f"{test.name} theory"] = (pf, theory)
            rows.append(row)
    table = QTable(rows=[[r[k] for k in rows[0]] for r in rows], names=list(rows[0]))
    table.meta.update({"preset": preset, "n_frames": n_frames, "n_draws": n_draws,
                       "seed": seed, "pfa_ref": pfa_ref, "n_kp": km.n_kp,
                       "separation_mas": float(np.hypot(*p.companion_offset.to_value(u.mas))),
                       "contrasts": [float(c) for c in p.contrasts],
                       "window_factor": wfac})
    return table, curves
