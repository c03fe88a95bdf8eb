"""The seed paper's binary test ``B-paper``: ``sum_i max(z_i, 0)``.

Its law at a known position is ``sum_k C(q, k) 2^-q P(sum of k half-normals >
xi)`` (numerical for ``k >= 2``); it coincides with ``B`` for one channel. Its
map, null and limits are ``B``'s machinery with the power 1
(`kpifs.detect.statistics.binary`).
"""
from .binary import BinaryTest

__all__ = ["BinaryPaperTest"]


class BinaryPaperTest(BinaryTest):
    """The seed paper's printed binary test, ``sum_i max(z_i, 0)``.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.detect.statistics import get_test
    >>> round(float(get_test("B-paper").local_pfa(None, np.array(4.1544), n_channels=3)), 4)
    0.01
    """

    name = "B-paper"
    label = r"B-paper: the paper's $\Sigma_i \max(z_i, 0)$"
    description = "the seed paper's binary test (a free contrast in every channel)"
    power = 0.5
