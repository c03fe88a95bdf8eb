"""Third-party modules loaded on first use.

``kpifs extract`` imports the workflow, which imports the detection modules;
those need `scipy.stats` and `scipy.optimize` (half a second of start-up)
only when a detection runs. ``stats = lazy_module("scipy.stats")`` at module
level gives a stand-in that imports the real module on its first attribute
access, so extraction never pays for it.
"""
import importlib
import types

__all__ = ["lazy_module"]


class _LazyModule(types.ModuleType):
    def __getattr__(self, attr):
        module = importlib.import_module(self.__name__)
        self.__dict__.update(module.__dict__)       # later look-ups are plain
        return getattr(module, attr)


def lazy_module(name):
    """A stand-in for module *name* that imports it on first attribute access.

    Examples
    --------
    >>> from kpifs._lazy import lazy_module
    >>> fractions = lazy_module("fractions")
    >>> str(fractions.Fraction(1, 3))
    '1/3'
    """
    return _LazyModule(name)
