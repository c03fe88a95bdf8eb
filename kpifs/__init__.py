"""kpifs: multi-wavelength kernel-phase analysis of integral-field-spectrograph data.

The pipeline runs pupil model -> kernel model -> extraction -> calibration
-> detection. Each stage is one module; this package re-exports the main
public objects. They are loaded on first use, so that ``import kpifs`` (and
the command line's start) stays fast.
"""
import importlib

from ._meta import VERSION as __version__

#: public name -> module that defines it
_PUBLIC = {
    "KpifsError": "exceptions",
    "KpifsWarning": "exceptions",
    "PupilModel": "model.pupil",
    "make_pupil": "model.pupil",
    "KernelModel": "model.kernel",
    "ExtractionWindow": "model.window",
    "KernelPhaseData": "data",
    "DetectionResult": "data",
    "extract_kernel_phases": "extraction.extract",
}

__all__ = ["__version__", *_PUBLIC]


def __getattr__(name):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(f".{_PUBLIC[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_PUBLIC))
