"""Files: instrument cubes, wavelength arguments, KPFITS kernel-phase files, products.

Each instrument is one module holding an `~kpifs.io.instrument.Instrument`,
registered once in `kpifs.io.instruments`.
This layer knows file layouts, not the science: readers return an `IFSCube`
(or plain arrays and headers), writers take objects and only read the
attributes they write. The containers of `kpifs.data` and `kpifs.model.kernel`
connect the KPFITS and detection-product layouts to astropy's I/O registry.
"""
from .cube import IFSCube, read_generic  # noqa: F401
from .wavelengths import check_wavelengths, parse_wavelengths, read_wavelength_file  # noqa
from .angles import parse_angles  # noqa: F401
from .charis import read_charis  # noqa: F401
from .sphere import read_sphere  # noqa: F401
from .readers import read_cube, detect_instrument  # noqa: F401
from .kpfits import write_kpfits  # noqa: F401
from .layouts import write_observation  # noqa: F401

__all__ = ["IFSCube", "read_cube", "detect_instrument", "read_charis", "read_sphere",
           "read_generic", "parse_wavelengths", "check_wavelengths", "read_wavelength_file",
           "parse_angles", "write_kpfits", "write_observation"]
