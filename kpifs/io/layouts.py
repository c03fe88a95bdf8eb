"""Write cubes in the instruments' on-disk layouts (used for simulated data).

Each registered instrument (`kpifs.io.instruments.INSTRUMENTS`) writes its own
layout:

- ``plain`` (`kpifs.io.generic`): one FITS file, primary HDU a float32 cube
  ``(nframe, nwave, ny, nx)`` with the wavelengths in cards ``KPWL1 ... KPWLn``
  (um) and ``PIXSCALE`` (mas), and, for a scene with detector angles, a
  ``DETPA`` extension (deg, one per frame); what ``kpifs extract`` reads
  without further options.
- ``charis`` (`kpifs.io.charis`): one file per exposure, as the CHARIS
  data-reduction pipeline writes them: HDU 0 header only, HDU 1 the cube
  ``(nlam, ny, nx)``, HDU 2 its inverse variance; ``LAM_MIN``, ``LAM_MAX`` (nm),
  ``DLOGLAM``, ``NLAM``, ``CAL_BAND``, ``PARANG`` and a log-wavelength third WCS
  axis.
- ``sphere`` (`kpifs.io.sphere`): as the community SPHERE-IFS pipeline:
  ``science_cube.fits`` of shape ``(nwave, nframe, ny, nx)``,
  ``wavelength.fits`` (nm) and ``parallactic_angles.fits`` (deg).
- ``jwst``, ``gpi``, ``nirc2``: JWST ``*_calints.fits`` (one file per detector
  angle: a rotating sequence is several exposures), GPI ``*_spdc.fits`` and
  Keck/NIRC2 ``n0001.fits`` (one image per frame).
"""
from pathlib import Path

from ..exceptions import KpifsError
from .charis import write_charis_exposures
from .generic import write_plain_cube
from .instruments import INSTRUMENTS
from .sphere import write_sphere_cube

__all__ = ["write_plain_cube", "write_charis_exposures", "write_sphere_cube",
           "write_observation", "LAYOUTS"]

#: The simulator's layouts, one per registered instrument that writes files.
LAYOUTS = INSTRUMENTS.layouts()


def write_observation(obs, outdir, *, layout="plain", overwrite=False):
    """Write a `~kpifs.simulation.simulate.SimulatedObservation` (target and calibrator)
    to *outdir*.

    Returns a dict ``{"target": [paths], "calibrator": [paths]}``.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.io import write_observation
    >>> from kpifs.simulation.simulate import simulate_scene
    >>> tmp = tempfile.TemporaryDirectory()
    >>> files = write_observation(simulate_scene("paper", n_frames=1, npup=32), tmp.name)
    >>> [p.name for p in files["target"]]
    ['target.fits']
    >>> tmp.cleanup()
    """
    instrument = INSTRUMENTS.by_layout(layout)
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise KpifsError(f"{outdir}: exists and is not a directory")
    outdir.mkdir(parents=True, exist_ok=True)
    out = {}
    for role in ("target", "calibrator"):
        cards = (dict(obs.truth) if role == "target"
                 else {"KPSIMSEE": obs.truth["KPSIMSEE"]})
        cards["KPSIMROL"] = (role, "simulated target or calibrator")
        obj = "SIM-TARGET" if role == "target" else "SIM-CALIB"
        common = dict(cards=cards, overwrite=overwrite, exptime=obs.params.exptime, obj=obj)
        out[role] = instrument.write(obs, role, outdir, common)
    return out
