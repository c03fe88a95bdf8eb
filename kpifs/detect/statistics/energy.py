"""The energy detector ``E``: ``T_E = ||y||^2``, anything beyond the noise.

One statistic for the whole data set, ``chi2_dof`` under H0 (or its law drawn
from the covariance rows when the channels are correlated); it has no map, so
the search's candidates come from B's map. Its limit is the contrast whose
non-centrality ``||x||^2`` reaches ``lambda`` with ``ncx2.sf(chi2.isf(P_FA,
dof), dof, lambda) = P_D``.
"""
import numpy as np

from ..._lazy import lazy_module
from ..channels import correlated_energy_limit
from ..limits import limit_energy, mirror_half_map
from .base import DetectionTest

__all__ = ["EnergyTest"]

stats = lazy_module("scipy.stats")


class EnergyTest(DetectionTest):
    """The energy detector (candidates from the binary test's map).

    Examples
    --------
    >>> from kpifs.detect.statistics import get_test
    >>> get_test("E").map_name, get_test("E").power
    ('B', 1.0)
    """

    name = "E"
    label = r"E: energy, $\|y\|^2$"
    description = "the energy test (anything beyond the noise; candidates from B's map)"
    power = 1.0
    map_test = "B"

    def n_params(self, n_channels, n_basis):
        return 3

    def limit(self, inputs):
        if inputs.corr is None:
            return limit_energy(inputs.norm2, inputs.pfa, inputs.pd, inputs.dof,
                                inputs.spectrum)
        lim = correlated_energy_limit(inputs.model, inputs.rows, inputs.spectrum,
                                      inputs.energy_threshold, inputs.pd, inputs.energy_null)
        return mirror_half_map(lim) if inputs.mirror else lim

    def known_position(self, draws):
        return draws.ee

    def theory_pd(self, x, dof, pfa):
        """``ncx2.sf(chi2.isf(P_FA, dof), dof, ||x||^2)``."""
        norm = float(np.linalg.norm(x))
        return stats.ncx2.sf(stats.chi2.isf(np.asarray(pfa, float), dof), dof, norm ** 2)
