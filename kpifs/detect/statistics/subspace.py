"""The spectral-model (subspace) test ``S``: the GLR for a contrast spectrum in the
span of a low-rank basis (`kpifs.detect.spectral`).

``T_S = ||U^T z||^2`` counted where the fitted spectrum's mean is positive
(``h^T U^T z > 0``), half a ``chi2_r`` at a known position under H0. With the
channels' correlation its weights cancel the noise the channels share. It is
judged by its own map's noise too: a residual smooth across wavelength, as a
static aberration's is, concentrates in its projections.
"""
import numpy as np

from .._laws import chi2_sf
from ..channels import subspace_scale
from ..limits import mirror_half_map
from ..spectral import limit_subspace
from ..stats import known_position_subspace
from .base import DetectionTest

__all__ = ["SubspaceTest"]


class _Reducer:
    def __init__(self, setup):
        model, pos = setup.model, setup.positions
        sub = model.subspace
        self.sub = sub.reshape(sub.shape[:2] + (-1,))[:, :, pos].astype(np.float32)
        self.r = len(self.sub)
        self.sign = model.subspace_sign.reshape(self.r, -1)[:, pos].astype(np.float32)
        self.mirrored, self.npos = setup.mirrored, len(pos)

    def batch(self, n):
        return _Batch(self, n)


class _Batch:
    def __init__(self, reducer, n):
        self.red = reducer
        self.proj = np.zeros((reducer.r, n, reducer.npos), np.float32)

    def add(self, i, z):
        for j in range(self.red.r):
            self.proj[j] += self.red.sub[j, i] * z

    def finish(self, channel_sum):
        red, proj = self.red, self.proj
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
