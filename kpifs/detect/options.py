"""`SearchOptions`: every option of `kpifs.detect.detect`, in one dataclass.

``detect(kpd, options)`` takes one; ``detect(kpd, test=..., pfa=...)`` builds one
from its keywords (the same names and defaults).
"""
from dataclasses import dataclass, fields

from ..exceptions import KpifsError
from .null import DEFAULT_DRAWS

__all__ = ["SearchOptions"]


@dataclass(frozen=True)
class SearchOptions:
    """The options of a search (`kpifs.detect.detect` documents each).

    Examples
    --------
    >>> from kpifs.detect.options import SearchOptions
    >>> opts = SearchOptions.from_keywords(pfa=1e-4)
    >>> opts.pfa, opts.test, opts.n_draws
    (0.0001, 'auto', 5000)
    """

    test: str = "auto"
    pfa: float = 1e-3
    pd: float = 0.5
    grid: object = None
    spectrum: object = None
    basis: object = None
    n_draws: int = DEFAULT_DRAWS
    seed: object = 0
    shrinkage: object = "auto"
    fit: bool = True
    max_candidates: int = 20
    allow_uncalibrated: bool = False
    frame: str = "auto"
    limits: bool = True
    null: str = "auto"
    progress: bool = False
    blocks: str = "auto"
    aliased: str = "keep"
    static: str = "auto"

    @classmethod
    def from_keywords(cls, **keywords):
        """The options from `detect`'s keywords; an unknown one is refused by name."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(keywords) - known)
        if unknown:
            raise KpifsError(f"unknown option(s) of detect: {', '.join(unknown)}")
        return cls(**keywords)
