"""Exceptions and warnings raised by kpifs."""
from astropy.utils.exceptions import AstropyUserWarning

__all__ = ["KpifsError", "MissingInformation", "KpifsWarning"]


class KpifsError(ValueError):
    """Bad input to kpifs: the message names the problem (and the file, if any).

    It subclasses `ValueError` so that code catching ``ValueError`` keeps
    working; the command line turns it into a one-line message and exit
    status 2.

    Examples
    --------
    >>> from kpifs import KpifsError, make_pupil
    >>> try:
    ...     make_pupil("hubble")
    ... except KpifsError as err:
    ...     print(str(err).split(":")[0])
    unknown pupil 'hubble'
    """


class MissingInformation(KpifsError):
    """A file lacks something kpifs needs and cannot guess (wavelengths, pixel scale).

    The message says what to give; ``kpifs info`` still describes such a file.

    Examples
    --------
    >>> from kpifs.exceptions import KpifsError, MissingInformation
    >>> issubclass(MissingInformation, KpifsError)
    True
    """


class KpifsWarning(AstropyUserWarning):
    """A warning issued by kpifs (e.g. baselines dropped at the Nyquist limit).

    Examples
    --------
    >>> import warnings
    >>> from kpifs import KpifsWarning
    >>> from astropy.utils.exceptions import AstropyUserWarning
    >>> issubclass(KpifsWarning, AstropyUserWarning)
    True
    """
