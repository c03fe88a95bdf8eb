"""The Neyman-Pearson test ``NP``: the matched filter for a known spectrum shape.

``T_NP = sum_i a_i s_i^T y_i / ||s_a||`` at each position, N(0, 1) under H0
at a known position; its limit is ``(Q^-1(P_FA) - Q^-1(P_D)) / ||s_a||``, or with
the channels' correlation ``m^T C^+ m`` in place of ``||s_a||^2``. The optimal
reference: it needs the companion's spectrum.
"""
import numpy as np

from ..._lazy import lazy_module
from .._laws import norm_isf, norm_sf
from ..channels import np_correlated
from ..limits import limit_np
from .base import DetectionTest

__all__ = ["NeymanPearsonTest"]

stats = lazy_module("scipy.stats")


class _Reducer:
    def __init__(self, setup):
        q = setup.n_channels
        mfw = setup.model._mf_weights(setup.spectrum).reshape(q, -1)
        self.weights = mfw[:, setup.positions].astype(np.float32)
        self.mirrored = setup.mirrored
        # through the noise rows, the filter's sum is one product of the draws
        self.mats = None if setup.combine is None else setup.combine(mfw[None, :, setup.positions])
        self.per_channel = self.mats is None

    def batch(self, n):
        return _Batch(self, n)


class _Batch:
    def __init__(self, reducer, n):
        self.r = reducer
        self.acc = np.zeros((n, reducer.weights.shape[1]), np.float32) \
            if reducer.per_channel else None

    def add(self, i, z):
        self.acc += self.r.weights[i] * z

    def finish(self, draw):
        if self.r.mats is not None:
            self.acc = draw.combined(self.r.mats)[0]
        best = self.acc.max(axis=1)
        if self.r.mirrored:
            best = np.maximum(best, -self.acc.min(axis=1))
        return {"NP": best}


class NeymanPearsonTest(DetectionTest):
    """The matched filter (Neyman-Pearson) for the given spectrum shape.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.statistics import get_test
    >>> round(float(get_test("NP").local_pfa(None, np.array(3.0902))), 4)
    0.001
    """

    name = "NP"
    label = r"NP: matched filter, known spectrum (reference)"
    description = "the matched filter (the given spectrum shape)"
    power = 0.5
    spectral_null = True

    def n_params(self, n_channels, n_basis):
        return 3

    def map_statistic(self, model, z, spectrum):
        return np.sum(model._mf_weights(spectrum) * z, axis=-3)

    def local_pfa(self, model, t):
        return norm_sf(np.nan_to_num(t, nan=-np.inf))

    def null_reducer(self, setup):
        return _Reducer(setup)

    def limit(self, inputs):
        a, norm2 = inputs.spectrum, inputs.norm2
        if inputs.search == self.name:
            # the search's own (global) threshold, not the local one
            with np.errstate(divide="ignore"):      # no signal at the star
                return (inputs.search_threshold - norm_isf(inputs.pd)) / np.sqrt(
                    np.tensordot(a ** 2, norm2, axes=(0, 0)))
        if inputs.corr is not None:     # the known-spectrum reference with the correlation
            return np_correlated(norm2, inputs.corr, a, inputs.pfa, inputs.pd)
        return limit_np(norm2, inputs.pfa, inputs.pd, a)

    def known_position(self, draws):
        return draws.ex

    def theory_pd(self, x, dof, pfa):
        """``Q(Q^-1(P_FA) - ||x||)``."""
        return stats.norm.sf(stats.norm.isf(np.asarray(pfa, float)) - float(np.linalg.norm(x)))

    def theory_auc(self, x, dof):
        """``Phi(||x|| / sqrt 2)``."""
        return float(stats.norm.cdf(float(np.linalg.norm(x)) / np.sqrt(2)))
