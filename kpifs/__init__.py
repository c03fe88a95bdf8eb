"""kpifs: multi-wavelength kernel-phase analysis of integral-field-spectrograph data.

The pipeline runs pupil model -> kernel model -> extraction -> calibration
-> detection. Each stage is one module; this package re-exports the main
public objects. They are loaded on first use, so that ``import kpifs`` (and
the command line's start) stays fast.
"""
from ._meta import VERSION as __version__

__all__ = ["__version__", "KpifsError", "KpifsWarning", "PupilModel", "make_pupil",
           "KernelModel", "ExtractionWindow", "KernelPhaseData", "DetectionResult",
           "extract_kernel_phases"]


def _module_of(name):
    """The module that defines the public *name*, imported now (each import written out:
    the tools that draw the package's structure see them)."""
    if name in ("KpifsError", "KpifsWarning"):
        from . import exceptions as module
    elif name in ("PupilModel", "make_pupil"):
        from .model import pupil as module
    elif name == "KernelModel":
        from .model import kernel as module
    elif name == "ExtractionWindow":
        from .model import window as module
    elif name in ("KernelPhaseData", "DetectionResult"):
        from . import data as module
    elif name == "extract_kernel_phases":
        from .extraction import extract as module
    else:
        return None
    return module


def __getattr__(name):
    module = _module_of(name) if name in __all__ else None
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = globals()[name] = getattr(module, name)
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
