"""Detection and characterisation: statistical tests, maps, the null, candidates and limits."""
from .stats import (TESTS, auc, binary_pfa, binary_threshold, energy_pd, energy_threshold,  # noqa
                    monte_carlo_roc, np_pd, np_threshold, roc_curve)
from .maps import DetectionModel  # noqa: F401
from .null import NullCalibration  # noqa: F401
from .pipeline import default_grid, detect  # noqa: F401

__all__ = ["TESTS", "auc", "binary_pfa", "binary_threshold", "energy_pd", "energy_threshold",
           "monte_carlo_roc", "np_pd", "np_threshold", "roc_curve", "DetectionModel",
           "NullCalibration", "default_grid", "detect"]
