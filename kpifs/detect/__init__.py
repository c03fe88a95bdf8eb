"""Detection: maps, the null of a grid search, limits, fits and the search itself."""
from .known_position import monte_carlo_roc  # noqa: F401
from .maps import DetectionModel  # noqa: F401
from .null import NullCalibration  # noqa: F401
from .options import SearchOptions  # noqa: F401
from .pipeline import default_grid, detect  # noqa: F401
from ..report import DetectionReport  # noqa: F401
from .statistics import DetectionTest, get_test, register_test, registered_names  # noqa: F401
from .stats import (auc, binary_pfa, binary_threshold, energy_pd, energy_threshold,  # noqa
                    np_pd, np_threshold, roc_curve)

#: The names of the tests registered when kpifs was imported (`registered_names` for now).
TESTS = registered_names()

__all__ = ["TESTS", "auc", "binary_pfa", "binary_threshold", "energy_pd", "energy_threshold",
           "monte_carlo_roc", "np_pd", "np_threshold", "roc_curve", "DetectionModel",
           "NullCalibration", "SearchOptions", "DetectionReport", "DetectionTest", "get_test",
           "register_test", "registered_names", "default_grid", "detect"]
