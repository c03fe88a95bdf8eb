"""Detection tests as objects: one module per test, one registry (`DESIGN.md` §7).

`base` defines `DetectionTest`; each test is a module (`neyman_pearson`,
`energy`, `binary`, `binary_paper`, `subspace`); `registry` imports each and
registers it. Adding a test touches its module and one registry line.
"""
from .base import DetectionTest, KnownPositionDraws, LimitInputs, NullSetup  # noqa: F401
from .registry import (DEFAULT_TEST, REGISTRY, auto_test, get_test, reference_test,  # noqa
                       register_test, registered_names, subspace_test, unregister_test)

__all__ = ["DEFAULT_TEST", "subspace_test", "DetectionTest", "NullSetup", "LimitInputs",
           "KnownPositionDraws", "REGISTRY", "auto_test", "get_test", "reference_test",
           "register_test", "unregister_test", "registered_names"]
