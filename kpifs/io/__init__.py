"""Reading and writing files: instrument cubes, kernel-phase data (KPFITS), products."""
from .cube import IFSCube, read_generic, read_wavelength_file  # noqa: F401
from .charis import read_charis  # noqa: F401
from .sphere import read_sphere  # noqa: F401
from .readers import read_cube, detect_instrument  # noqa: F401
from .kpfits import read_kpfits, write_kpfits  # noqa: F401
from .layouts import write_observation  # noqa: F401

__all__ = ["IFSCube", "read_cube", "detect_instrument", "read_charis", "read_sphere",
           "read_generic", "read_wavelength_file", "read_kpfits", "write_kpfits",
           "write_observation"]
