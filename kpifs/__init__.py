"""kpifs: multi-wavelength kernel-phase analysis of integral-field-spectrograph data.

The pipeline runs pupil model -> kernel model -> extraction -> calibration
-> detection. Each stage is one module; this package re-exports the main
public objects.
"""
try:
    from ._version import version as __version__
except ImportError:  # pragma: no cover - only in a source tree never installed
    __version__ = "0.0.0"

from .exceptions import KpifsError, KpifsWarning  # noqa: F401
from .pupil import PupilModel, make_pupil  # noqa: F401
from .kernel import KernelModel  # noqa: F401
from .extract import KernelPhaseData, extract_kernel_phases  # noqa: F401

__all__ = [
    "__version__",
    "KpifsError",
    "KpifsWarning",
    "PupilModel",
    "make_pupil",
    "KernelModel",
    "KernelPhaseData",
    "extract_kernel_phases",
]
