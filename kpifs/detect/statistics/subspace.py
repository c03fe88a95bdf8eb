"""The spectral-model (subspace) test ``S``: the GLR for a contrast spectrum in the
span of a low-rank basis (`kpifs.detect.spectral`).

``T_S = ||U^T z||^2`` counted where the fitted spectrum's mean is positive
(``h^T U^T z > 0``), half a ``chi2_r`` at a known position under H0. With the
channels' correlation its weights cancel the noise the channels share. It is
judged by its own map's noise too: a residual smooth across wavelength, as a
static aberration's is, concentrates in its projections.
"""
import numpy as np

from ..._lazy import lazy_module
from .._laws import chi2_sf
from ..channels import subspace_scale
from ..limits import mirror_half_map
from ..spectral import limit_subspace
from ..stats import known_position_subspace
from .base import TILE, DetectionTest

__all__ = ["SubspaceTest", "subspace_mean", "theory_roc_subspace"]

stats = lazy_module("scipy.stats")


def subspace_mean(norms):
    """Mean ``(mu_h, lambda_perp, r)`` of the subspace statistic's projections at a known
    position: ``gamma = W z ~ N(mu, I_r)``, ``mu_h`` its part along the sign vector ``h``
    and ``lambda_perp`` the squared rest (as `~kpifs.detect.known_position.monte_carlo_roc`
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


class _Reducer:
    def __init__(self, setup):
        model, pos = setup.model, setup.positions
        sub = model.subspace
        self.sub = sub.reshape(sub.shape[:2] + (-1,))[:, :, pos].astype(np.float32)
        self.r = len(self.sub)
        self.sign = model.subspace_sign.reshape(self.r, -1)[:, pos].astype(np.float32)
        self.mirrored, self.npos = setup.mirrored, len(pos)
        # through the noise rows, each projection is one product of the draws:
        # sum_i U[j, i] z_i = coef @ sum_i U[j, i] Z_i (not q * r elementwise passes)
        self.mats = None if setup.combine is None else \
            setup.combine(sub.reshape(sub.shape[:2] + (-1,))[:, :, pos])
        self.per_channel = self.mats is None

    def batch(self, n):
        return _Batch(self, n)


class _Batch:
    def __init__(self, reducer, n):
        self.red = reducer
        if reducer.per_channel:
            self.proj = np.zeros((reducer.r, n, reducer.npos), np.float32)
            self.tmp = np.empty((TILE, reducer.npos), np.float32)

    def add(self, i, z):
        # by tiles of draws: z's tile and the product stay in the cache for every j
        # (the same operations, element by element, as over the whole batch)
        for a in range(0, len(z), TILE):
            zt = z[a:a + TILE]
            tmp = self.tmp[:len(zt)]
            for j in range(self.red.r):
                np.multiply(self.red.sub[j, i], zt, out=tmp)
                self.proj[j, a:a + TILE] += tmp

    def finish(self, draw):
        red = self.red
        proj = self.proj if red.per_channel else draw.combined(red.mats)
        t_s = np.einsum("jnk,jnk->nk", proj, proj)
        # the subspace map's mean square (per coefficient): `noise_draws('G2')`
        out = {"G2": t_s.mean(axis=1) / red.r}
        if not red.mirrored:    # the mirror carries the other sign: max over both is t_s
            t_s *= np.einsum("jk,jnk->nk", red.sign, proj) > 0
        out["S"] = t_s.max(axis=1)
        return out


class SubspaceTest(DetectionTest):
    """The spectral-model test: a contrast spectrum in a low-rank model.

    Examples
    --------
    >>> from kpifs.detect.statistics import get_test
    >>> get_test("S").subspace_map, get_test("S").n_params(22, 3)
    (True, 5)
    """

    name = "S"
    label = r"S: spectral model, GLR over a low-rank spectrum"
    description = ("the spectral-model test (a contrast spectrum in a low-rank model, the "
                   "channels' shared noise weighed)")
    power = 1.0
    subspace_map = True

    def n_params(self, n_channels, n_basis):
        return 2 + int(n_basis)

    def map_statistic(self, model, z, spectrum):
        zz = np.nan_to_num(z)
        g = np.sum(model.subspace * zz[..., None, :, :, :], axis=-3)        # (..., r, ny, nx)
        return np.sum(g ** 2, axis=-3) * (np.sum(model.subspace_sign * g, axis=-3) > 0)

    def local_pfa(self, model, t):
        # one sign of the spectrum's mean: half the two-sided law
        return np.where(np.nan_to_num(t) > 0,
                        0.5 * chi2_sf(np.nan_to_num(t, nan=0.0), model.basis.shape[1]), 1.0)

    def null_reducer(self, setup):
        return _Reducer(setup)

    def scale(self, common, subspace_noise, g2_draws):
        return subspace_scale(common, subspace_noise, g2_draws())

    def limit(self, inputs):
        lim = limit_subspace(inputs.model.subspace, inputs.norm2, inputs.thresholds(self.name),
                             inputs.pd, spectrum=inputs.spectrum, correlation=inputs.corr,
                             seed=inputs.seed)
        return mirror_half_map(lim) if inputs.mirror else lim

    def known_position(self, draws):
        w, h = known_position_subspace(draws.norms)
        return tuple(np.sum((z @ w.T) ** 2, axis=1) * ((z @ w.T) @ h > 0) for z in draws.z)

    def theory_pd(self, x, dof, pfa):
        """`theory_roc_subspace` of the signal's `subspace_mean`."""
        return theory_roc_subspace(*subspace_mean(np.linalg.norm(x, axis=1)), pfa)

    def theory_auc(self, x, dof):
        return _theory_auc_subspace(*subspace_mean(np.linalg.norm(x, axis=1)))
