"""The package version, importable without numpy or astropy (the command line's start)."""
try:
    from ._version import version as VERSION
except ImportError:  # pragma: no cover - only in a source tree never installed
    VERSION = "0.0.0"

__all__ = []
