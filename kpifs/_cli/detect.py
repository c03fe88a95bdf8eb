"""``kpifs detect``: search kernel phases for companions and write the products."""
import math
import sys
import warnings

from astropy import units as u

from .._checks import check_inputs, preflight_detect
from .._utils import check_output_dir, check_output_path
from ..data import KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning
from ..io.cube import open_fits
from ..model.field import field_sentence
from ..detect.sky import detector_to_sky, mean_angle
from ..plotting import save_detection_plots
from ..workflow import detect_observation
from ._options import detect_options
from ._summary import print_summary, products_line


def _grid_step(args):
    """``--step`` was the search grid's step here (the pupil grid's everywhere else): still
    read, with a warning, for one release."""
    if args.deprecated_step is None:
        return
    if args.grid_step is not None:
        raise KpifsError("give the search grid's step once, with --grid-step")
    warnings.warn("--step in kpifs detect is deprecated: the search grid's step is "
                  "--grid-step (--step is the pupil grid's step in every other command)",
                  KpifsWarning)
    args.grid_step = args.deprecated_step


def _check_kernel_phases(path, *, several=False):
    """Refuse, with the command that makes them, a file that holds no kernel phases (and,
    among several files, one that is not OIFITS: KPFITS products are one per search)."""
    with open_fits(path) as hdul:
        if "OI_T3" in hdul:                            # closure phases
            return
        if "KP-DATA" in hdul:                          # kernel phases
            if several:
                raise KpifsError(f"{path}: KPFITS kernel phases: only OIFITS files combine "
                                 f"in one search; give the frames of one star to kpifs "
                                 f"extract together instead")
            return
        what = ("detection products" if hdul[0].header.get("CONTENT") == "KPIFS-DETECTION"
                else "no KP-DATA extension (no kernel phases)")
    raise KpifsError(f"{path}: {what}; kpifs detect searches kernel phases: make them from "
                     f"the cubes first, e.g. 'kpifs extract {path} --calibrator CAL.fits -o "
                     f"kp.fits', then 'kpifs detect kp.fits'")


def run(args):
    _grid_step(args)
    options = detect_options(args).validate()
    check_output_path(args.output, overwrite=args.overwrite)
    paths = list(args.kp)
    check_inputs(paths, outputs=[args.output])
    preflight_detect(paths[0], args.calibrator, args.output, options)
    if args.plots:
        check_output_dir(args.plots)
    for path in paths + list(args.calibrator or []):
        _check_kernel_phases(path, several=len(paths) > 1)
    kpd = KernelPhaseData.read(paths if len(paths) > 1 else paths[0])
    cals = [KernelPhaseData.read(c) for c in (args.calibrator or [])]
    res = detect_observation(kpd, options, calibrators=cals,
                             progress=not args.quiet)
    res.write(args.output, inputs=paths + list(args.calibrator or []),
              overwrite=args.overwrite)
    print_summary(res, kpd, chosen=args.test)
    _aliased_line(res)
    if res.meta.get("field"):
        print("  " + field_sentence(res.meta["field"]))
    _spectral_line(res)
    st = res.meta.get("static")
    if st:
        print(f"static aberrations (no calibrator): a kernel-phase residual imaged through the "
              f"{st['pupil']} pupil, fitted at {st['share']:.2f} x the frames' variance, is in "
              f"the covariance of every test")
    if args.plots:
        truth = None
        if "KPSIMX" in kpd.header and "KPSIMY" in kpd.header:
            truth = (kpd.header["KPSIMX"], kpd.header["KPSIMY"])
            if res.meta.get("frame") == "sky":     # the simulator's truth is on the detector
                truth = detector_to_sky(*truth, mean_angle(res.meta["pa_bins"][0]))
        try:
            save_detection_plots(res, args.plots, truth=truth)
        except (OSError, ValueError, RuntimeError) as exc:   # the products are written
            print(f"kpifs detect: warning: {args.output} is written, but the figures "
                  f"could not be ({type(exc).__name__}: {exc})", file=sys.stderr)
            args.plots = None
    products_line(args.output, args.plots)
    return 0


def _spectral_line(res):
    """What a spectral-differential search projected out, and where it starts (issue 39)."""
    sdk = res.meta.get("blocks") or {}
    rotation = bool(sdk.get("spectral"))                  # ASDI: combinations' time blocks
    sdk = sdk.get("spectral") or sdk
    if sdk.get("profiles") is None:
        return
    inner = sdk.get("inner_separation")
    where = (f"half a companion's signal is kept from {inner:.0f} mas"
             if inner is not None and math.isfinite(inner) and inner > 0
             else "less than half a companion's signal is kept anywhere on the grid")
    print(f"spectral-differential: {sdk['profiles']} profile(s) along the channels "
          f"({sdk.get('basis')}) projected out of every kernel phase, "
          f"{sdk['combinations']} channel combinations searched"
          + (" by their mean and time blocks (ASDI)" if rotation else "") + f"; {where}")


def _aliased_line(res):
    """Which channels alias uv points, and what was done with them."""
    gone = res.meta.get("excluded_channels") or []
    numbers = res.meta.get("channels") or []
    hit = [(n, w) for n, w, f in zip(numbers, res.wavelengths.to_value(u.um),
                                     res.meta.get("aliased") or []) if f > 0]
    if gone:
        print(f"channel(s) {', '.join(map(str, gone))} left out (pixels too coarse: aliased "
              f"uv points)")
    if hit:
        print(f"channel(s) {', '.join(f'{n} ({w:.3f} um)' for n, w in hit)}: pixels too "
              f"coarse for some uv points; their contrasts are biased (flagged), "
              f"--aliased exclude leaves them out")
