"""The ``kpifs`` command line: `main` (the ``kpifs`` script, ``python -m kpifs``).

The commands live in the private package ``kpifs._cli``, one module each.
Exit status: 0 success, 1 ``kpifs batch`` with failed entries, 2 bad input or
usage (one-line message naming the file and the problem), 3 an unexpected
internal error (rerun with ``--debug`` for the traceback), 130 interrupted.
"""
import sys

from ._cli import main as _main

__all__ = ["main"]


def main(argv=None):
    """Run the ``kpifs`` command line with *argv* (default ``sys.argv[1:]``); return the
    exit status.

    Examples
    --------
    >>> from kpifs.cli import main
    >>> main(["kernel", "--pupil", "hubble", "-o", "model.fits", "-q"])
    2
    """
    return _main(argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
