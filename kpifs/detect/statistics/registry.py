"""The registry of detection tests: one line per test, in the order they are shown.

Adding a test is one new module of `kpifs.detect.statistics` (a `DetectionTest`
subclass) and one line here; `kpifs.detect.detect`, the command line, the
figures, the products and `kpifs roc` read this registry
(``docs/user/adding_a_test.rst``). `register_test` adds one at run time (a
plug-in, or a test's toy).
"""
from ...exceptions import KpifsError
from .base import DetectionTest
from .binary import BinaryTest
from .binary_paper import BinaryPaperTest
from .energy import EnergyTest
from .neyman_pearson import NeymanPearsonTest
from .subspace import SubspaceTest

__all__ = ["DEFAULT_TEST", "get_test", "register_test", "unregister_test", "registered_names",
           "auto_test", "reference_test", "subspace_test", "REGISTRY"]

#: Every test by name, in the order printouts, figures and products list them.
REGISTRY = {}

#: The map test of the projection's and the null's functions when none is named.
DEFAULT_TEST = "B"


def register_test(test):
    """Register a `DetectionTest` (an instance or a class) under its name; returns it.

    Examples
    --------
    >>> from kpifs.detect.statistics import register_test, unregister_test
    >>> from kpifs.detect.statistics.binary import BinaryTest
    >>> class Twice(BinaryTest):
    ...     name = "B2"
    >>> register_test(Twice).name
    'B2'
    >>> unregister_test("B2")
    """
    test = test() if isinstance(test, type) else test
    if not isinstance(test, DetectionTest) or not test.name:
        raise KpifsError(f"{test!r} is not a named DetectionTest")
    if test.name == "auto":
        raise KpifsError("'auto' is the choice of a test, not a test's name")
    REGISTRY[test.name] = test
    return test


def unregister_test(name):
    """Remove the test *name* from the registry (a toy's clean-up).

    Examples
    --------
    >>> from kpifs.detect.statistics import register_test, registered_names, unregister_test
    >>> from kpifs.detect.statistics.energy import EnergyTest
    >>> class Twice(EnergyTest):
    ...     name = "E2"
    >>> _ = register_test(Twice)
    >>> unregister_test("E2")
    >>> "E2" in registered_names()
    False
    """
    REGISTRY.pop(name, None)


def registered_names():
    """The names of the registered tests, in their order.

    Examples
    --------
    >>> from kpifs.detect.statistics import registered_names
    >>> registered_names()
    ('NP', 'E', 'B', 'B-paper', 'S')
    """
    return tuple(REGISTRY)


def get_test(name):
    """The registered test *name* (a `DetectionTest` given is returned as it is).

    Examples
    --------
    >>> from kpifs.detect.statistics import get_test
    >>> get_test("S").description[:26]
    'the spectral-model test (a'
    """
    if isinstance(name, DetectionTest):
        return name
    try:
        return REGISTRY[name]
    except (KeyError, TypeError):
        raise KpifsError(f"unknown test {name!r}: use one of {registered_names()} or 'auto'") \
            from None


def auto_test(n_basis, n_channels):
    """The test ``--test auto`` chooses (measured: ``docs/user/choosing_test.rst``).

    S only constrains the spectrum when its model has fewer dimensions than the
    channels; with as many, B's all-positive contrasts are the stronger constraint.

    Examples
    --------
    >>> from kpifs.detect.statistics import auto_test
    >>> auto_test(3, 22).name, auto_test(1, 1).name
    ('S', 'B')
    """
    return get_test("S" if n_basis < n_channels else "B")


def subspace_test():
    """The test whose map is the spectral model's projections (its null draws their mean
    square, ``'G2'``), or None.

    Examples
    --------
    >>> from kpifs.detect.statistics import subspace_test
    >>> subspace_test().name
    'S'
    """
    return next((t for t in REGISTRY.values() if t.subspace_map), None)


def reference_test():
    """The optimal reference, the matched filter (its theory is exact): the ROC
    figure compares channel sets with it.

    Examples
    --------
    >>> from kpifs.detect.statistics import reference_test
    >>> reference_test().name
    'NP'
    """
    return get_test("NP")


for _test in (NeymanPearsonTest, EnergyTest, BinaryTest, BinaryPaperTest, SubspaceTest):
    register_test(_test)
