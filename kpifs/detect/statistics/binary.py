"""The binary test ``B``: the generalised likelihood ratio of a companion of free
contrast in every channel, at each position.

With ``z_i = s_i^T y_i / ||s_i||`` (N(0, 1) under H0 at a known position),
``T_B = sum_i max(z_i, 0)^2``, whose law at a known position is the
chi-bar-squared ``P_FA = sum_k C(q, k) 2^-q chi2_k.sf``. Its limit solves
``P(T_B > threshold) = P_D`` for the contrast (`kpifs.detect.limits.limit_binary`).
The seed paper's form ``sum_i max(z_i, 0)`` (`kpifs.detect.statistics.binary_paper`)
shares this module's machinery: both forms come from the same projections of
the null's draws and the same draws of the limits.
"""
import numpy as np

from .._elementwise import binary_forms, binary_maxima
from ..limits import limit_binary, limit_binary_correlated_forms, mirror_half_map
from ..stats import binary_pfa, binary_statistic
from .base import DetectionTest

__all__ = ["BinaryTest"]


class _Reducer:
    """The binary forms among the tests reduced together, from one clipping of ``z``."""

    def __init__(self, setup, forms):
        self.forms, self.mirrored, self.npos = forms, setup.mirrored, len(setup.positions)

    def batch(self, n):
        return _Batch(self, n)


class _Batch:
    """One batch of draws: given every channel at once (`add_channels`), their grid
    maxima directly; given channel by channel (`add`), the forms' maps accumulated."""

    def __init__(self, reducer, n):
        self.r, self.n = reducer, n
        self.maxima = self.acc = None

    def add_channels(self, z, at, draw):
        """Every channel's projections *z* (m, q, npos) of the draws *at* (a slice): their
        grid maxima (`binary_maxima`), no map of the forms kept."""
        if self.maxima is None:
            self.maxima = np.empty((self.n, 4), np.float32)
        tot = draw.channel_sum()[at] if self.r.mirrored and "B-paper" in self.r.forms \
            else None
        self.maxima[at] = binary_maxima(z, tot)

    def add(self, i, z):
        """Channel *i*'s projections *z* (n, npos), added to the forms' maps."""
        if self.acc is None:
            shape = (self.n, self.r.npos)
            self.acc = {f: np.zeros(shape, np.float32) for f in self.r.forms}
            # mirrored positions: sum max(-z, 0)^2 = sum min(z, 0)^2 (B), and sum max(-z, 0)
            # = sum max(z, 0) - sum z (B-paper: one product for the channel sum)
            self.neg = np.zeros(shape, np.float32) if self.r.mirrored and "B" in self.acc \
                else None
        binary_forms(z, self.acc.get("B-paper"), self.acc.get("B"), self.neg)

    def finish(self, draw):
        if self.maxima is not None:
            return self._finish_maxima()
        out = {}
        for f, acc in self.acc.items():
            best = acc.max(axis=1)
            if f == "B" and self.r.mirrored:
                best = np.maximum(best, self.neg.max(axis=1))
            elif self.r.mirrored:
                best = np.maximum(best, (acc - draw.channel_sum()).max(axis=1))
            out[f] = best
        return out

    def _finish_maxima(self):
        # columns of `binary_maxima`: B's form, its mirror, B-paper's form, its mirror
        mx, out = self.maxima, {}
        for f in self.r.forms:
            own, mirror = (0, 1) if f == "B" else (2, 3)
            out[f] = np.maximum(mx[:, own], mx[:, mirror]) if self.r.mirrored else mx[:, own]
        return out


class BinaryTest(DetectionTest):
    """The GLR binary test, ``sum_i max(z_i, 0)^2``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.statistics import get_test
    >>> round(float(get_test("B").local_pfa(None, np.array(8.7464), n_channels=3)), 4)
    0.01
    """

    name = "B"
    label = r"B: GLR, $\Sigma_i \max(z_i, 0)^2$"
    description = "the binary GLR test (a free contrast in every channel)"
    power = 1.0
    #: The binary forms and the power of ``max(z_i, 0)`` in each.
    FORMS = {"B": 2, "B-paper": 1}

    def map_statistic(self, model, z, spectrum):
        return binary_statistic(np.moveaxis(z, -3, -1), self.name)

    def local_pfa(self, model, t, n_channels=None):
        q = len(model.wavelengths) if n_channels is None else n_channels
        return binary_pfa(np.nan_to_num(t, nan=0.0), q, self.name)

    def null_reducer(self, setup):
        forms = [f for f in setup.names if f in self.FORMS] or [self.name]
        # the first binary form reduces them all (one clipping of z serves both)
        return _Reducer(setup, tuple(f for f in self.FORMS if f in forms)) \
            if forms[0] == self.name else None

    def limit(self, inputs):
        a, norm2 = inputs.spectrum, inputs.norm2
        if inputs.corr is None:
            return limit_binary(norm2, inputs.thresholds(self.name), inputs.pd, form=self.name,
                                spectrum=a, seed=inputs.seed)
        # the correlated draws of each position serve every binary form
        forms = [f for f in self.FORMS if f in inputs.tests] or [self.name]
        lims = inputs.once("binary", lambda: limit_binary_correlated_forms(
            norm2, {f: inputs.thresholds(f) for f in forms}, inputs.pd, spectrum=a,
            seed=inputs.seed, correlation=inputs.corr))
        return mirror_half_map(lims[self.name]) if inputs.mirror else lims[self.name]

    def known_position(self, draws):
        return tuple(binary_statistic(z, self.name) for z in draws.z)
