"""The JWST and GPI simulator writers, now in their instruments' modules (kept here for
the imports that name this module): `kpifs.io.jwst.write_jwst_calints` and
`kpifs.io.gpi.write_gpi_exposures`."""
from .gpi import GPI_IFSROTAT, write_gpi_exposures
from .jwst import JWST_GEOMETRY, write_jwst_calints

__all__ = ["write_jwst_calints", "write_gpi_exposures", "JWST_GEOMETRY", "GPI_IFSROTAT"]
