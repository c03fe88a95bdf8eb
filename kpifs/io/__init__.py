"""Reading and writing files: cubes, kernel-phase data (KPFITS) and products."""
from .cube import IFSCube, read_generic  # noqa: F401
from .kpfits import read_kpfits, write_kpfits  # noqa: F401
from .layouts import write_observation  # noqa: F401

__all__ = ["IFSCube", "read_generic", "read_kpfits", "write_kpfits", "write_observation"]
