"""Reading and writing files: kernel-phase data (KPFITS) and products."""
from .kpfits import read_kpfits, write_kpfits  # noqa: F401

__all__ = ["read_kpfits", "write_kpfits"]
