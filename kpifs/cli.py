"""The ``kpifs`` command line.

Exit status: 0 success, 2 bad input or usage (one-line message naming the file
and the problem), 3 an unexpected internal error (rerun with ``--debug`` for
the traceback).
"""
import argparse
import logging
import sys
import warnings

from . import __version__
from .commands import (cmd_batch, cmd_demo, cmd_detect, cmd_extract, cmd_info,  # noqa: F401
                       cmd_kernel, cmd_roc, cmd_simulate, parse_wavelengths)
from .exceptions import KpifsError

__all__ = ["main"]

log = logging.getLogger("kpifs")

EPILOG_KERNEL = """examples:
  kpifs kernel --pupil subaru --step 0.38m -o subaru_model.fits
  kpifs kernel --pupil vlt --step 0.4m --offset 0.1m,0.05m --grey -o vlt_grey.fits
  kpifs kernel --pupil mypupil.fits --pupil-scale 0.02m -o model.fits
"""
EPILOG_EXTRACT = """examples:
  kpifs extract cube.fits --wavelengths 1.52um,1.60um,1.68um --pixscale 10.42mas \\
      --pupil subaru -o kp.fits
  kpifs extract sim/target.fits --pupil model.fits -o kp.fits --overwrite
  kpifs extract target/CRSA*_cube.fits --calibrator calib/CRSA*_cube.fits -o cal_kp.fits
  kpifs extract science_cube.fits --instrument sphere --wavelengths wavelength.fits \\
      --calibrator ref_cube.fits -o cal_kp.fits
"""
EPILOG_DETECT = """examples:
  kpifs detect cal_kp.fits -o detection.fits --plots figures
  kpifs detect target_kp.fits --calibrator calib_kp.fits --test B-paper --pfa 1e-3 \\
      --max-sep 200mas --step 5mas -o detection.fits
  kpifs detect cal_kp.fits --test NP --spectrum 1.3,1.0,0.7 -o detection.fits
"""
EPILOG_BATCH = """examples:
  kpifs batch archive.csv -o reprocessed
  kpifs batch --glob 'night1/*_cube.fits' --calibrator 'night1/cal/*_cube.fits' -o out
  kpifs batch archive.csv --scheduler tcp://10.0.0.5:8786 -o reprocessed
manifest (CSV):
  name,target,calibrator
  hd1234,hd1234/CRSA*_cube.fits,ref1/CRSA*_cube.fits|ref2/CRSA*_cube.fits
exit status 1 if any entry failed (see summary.ecsv); a rerun skips entries already done.
"""
EPILOG_INFO = """examples:
  kpifs info target/CRSA00000000_cube.fits
  kpifs info kp.fits
"""
EPILOG_SIMULATE = """examples:
  kpifs simulate --preset paper --frames 100 -o sim
  kpifs simulate --preset charis --layout charis --frames 5 -o charis_sim
  kpifs simulate --preset sphere --layout sphere -o sphere_sim
"""


def _add_pupil_options(p):
    g = p.add_argument_group("pupil model")
    g.add_argument("--pupil", default=None,
                   help="telescope name (subaru, vlt, pharo), pupil image FITS (PUPSCALE "
                        "keyword or --pupil-scale) or kernel-model FITS (default: the "
                        "instrument's telescope, subaru for plain cubes)")
    g.add_argument("--pupil-scale", help="pupil image pixel size, e.g. 0.02m")
    g.add_argument("--step", default="0.38m", help="grid step (default 0.38m)")
    g.add_argument("--offset", default="0.17m,0.11m",
                   help="grid offset x,y (default 0.17m,0.11m; 0,0 gives a "
                        "centro-symmetric model)")
    g.add_argument("--min-transmission", type=float, default=0.9,
                   help="keep cells at least this much inside the pupil (default 0.9)")
    g.add_argument("--grey", action="store_true", help="keep fractional transmissions")
    g.add_argument("--hexagonal", action="store_true", help="hexagonal grid")


def _add_cube_options(p):
    g = p.add_argument_group("input cubes")
    g.add_argument("--instrument", default="auto", choices=("auto", "charis", "sphere",
                                                            "generic"),
                   help="file format (default: recognised from the header)")
    g.add_argument("--wavelengths", help="list (1.52um,1.60um) or file (text/FITS, um or nm); "
                                         "default: from the file's header")
    g.add_argument("--pixscale", help="pixel scale, e.g. 10.42mas; default: from the header "
                                      "or the instrument (CHARIS 16.2mas, SPHERE 7.46mas)")


def build_parser():
    parser = argparse.ArgumentParser(
        prog="kpifs", description="Multi-wavelength kernel-phase analysis of IFS cubes.",
        epilog="Run 'kpifs COMMAND --help' for the options and examples of each command. "
               "Exit status: 0 ok, 2 bad input, 3 internal error.")
    parser.add_argument("--version", action="version", version=f"kpifs {__version__}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("-v", "--verbose", action="count", default=0, help="more messages")
    common.add_argument("-q", "--quiet", action="store_true", help="errors only")
    common.add_argument("--debug", action="store_true", help="show tracebacks")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("kernel", parents=[common], help="build a kernel model and save it",
                       epilog=EPILOG_KERNEL, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_pupil_options(p)
    p.add_argument("-o", "--output", required=True, help="output FITS file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_kernel)

    p = sub.add_parser("extract", parents=[common], help="kernel phases of IFS cubes",
                       epilog=EPILOG_EXTRACT, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cubes", nargs="+", metavar="CUBE",
                   help="FITS cube(s) of the target; several files are more frames")
    _add_cube_options(p)
    p.add_argument("--calibrator", action="append", nargs="+", metavar="CUBE",
                   help="cube(s) of a calibrator star; repeat the option for several "
                        "calibrators (their mean is subtracted)")
    g = p.add_argument_group("covariance")
    g.add_argument("--shrinkage", default="auto", choices=("auto", "ledoit-wolf", "none"),
                   help="covariance estimator (auto: Ledoit-Wolf when frames are too few)")
    g.add_argument("--joint-covariance", action="store_true",
                   help="also estimate the joint covariance across channels")
    g.add_argument("--covariance", action="store_true",
                   help="store the frames' covariance even without a calibrator")
    _add_pupil_options(p)
    g = p.add_argument_group("extraction")
    g.add_argument("--window", type=int, help="cut-out size in pixels (default: image size)")
    g.add_argument("--window-radius", type=float,
                   help="super-Gaussian radius in pixels (default 0.8 x half the cut-out)")
    g.add_argument("--centroid", default="com", choices=("com", "peak", "quadratic", "2dg"),
                   help="star-centre method (default com)")
    g.add_argument("--bad-pixels", default="fill", choices=("fill", "exclude"),
                   help="interpolate bad pixels (default) or leave them out")
    g.add_argument("--nyquist", default="drop", choices=("drop", "raise"),
                   help="uv points beyond the Nyquist limit: drop (warn) or refuse")
    p.add_argument("-o", "--output", required=True, help="output KPFITS file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_extract)

    p = sub.add_parser("info", parents=[common], help="describe a cube, KPFITS or model file",
                       epilog=EPILOG_INFO, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", metavar="FILE")
    _add_cube_options(p)
    _add_pupil_options(p)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("simulate", parents=[common], help="simulate a target and a calibrator",
                       epilog=EPILOG_SIMULATE,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="paper", choices=("paper", "charis", "sphere"))
    p.add_argument("--layout", default="plain", choices=("plain", "charis", "sphere"),
                   help="file layout (default plain 4-D cube)")
    p.add_argument("--frames", type=int, help="number of frames (preset default)")
    p.add_argument("--contrasts", help="per-channel contrasts, comma separated")
    p.add_argument("--separation", help="companion separation, e.g. 100mas")
    p.add_argument("--pa", help="companion angle from +x towards +y, e.g. 36.87deg")
    p.add_argument("--wavefront", help="rms wavefront error, e.g. 100nm")
    p.add_argument("--shape", type=int, help="image side in pixels (preset default)")
    p.add_argument("--exptime", help="exposure time per frame, e.g. 1s (default 0.1s)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("detect", parents=[common], help="search kernel phases for companions",
                       epilog=EPILOG_DETECT, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kp", metavar="KP.fits", help="kernel-phase data (KPFITS)")
    p.add_argument("--calibrator", nargs="+", metavar="CAL_KP.fits",
                   help="kernel phases of calibrator(s), if KP.fits is not calibrated")
    p.add_argument("--test", default="B", choices=("B", "B-paper", "NP", "E"),
                   help="B: GLR sum max(z,0)^2 (default); B-paper: sum max(z,0); NP: matched "
                        "filter for --spectrum; E: energy detector")
    p.add_argument("--pfa", type=float, default=1e-3, help="global false-alarm probability")
    p.add_argument("--pd", type=float, default=0.5, help="detection probability of the limits")
    p.add_argument("--max-sep", help="largest separation searched, e.g. 200mas")
    p.add_argument("--min-sep", help="smallest separation searched, e.g. 20mas")
    p.add_argument("--step", help="grid step, e.g. 5mas (default lambda/4D)")
    p.add_argument("--spectrum", help="companion spectrum shape: flat, comma list or file")
    p.add_argument("--draws", type=int, default=30000,
                   help="Monte-Carlo draws calibrating the grid search (default 30000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--plots", metavar="DIR", help="write PNG figures there")
    p.add_argument("-o", "--output", required=True, help="output FITS file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_detect)

    p = sub.add_parser("roc", parents=[common], help="the seed paper's ROC experiment",
                       epilog="example:\n  kpifs roc --preset paper --frames 300 -o roc",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="paper", choices=("paper", "charis", "sphere"))
    p.add_argument("--frames", type=int, default=1000, help="calibrator frames (default 1000)")
    p.add_argument("--draws", type=int, default=30000, help="Monte-Carlo draws (default 30000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=cmd_roc)

    p = sub.add_parser("batch", parents=[common], help="reprocess many observations on Dask",
                       epilog=EPILOG_BATCH, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("manifest", nargs="*", metavar="MANIFEST",
                   help="CSV/ECSV with columns name, target, calibrator (';' separates files, "
                        "'|' calibrator stars; globs allowed)")
    p.add_argument("--glob", help="one entry per matching target file")
    p.add_argument("--calibrator", help="with --glob: calibrator file pattern for every entry")
    p.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local "
                                       "cluster)")
    p.add_argument("--workers", type=int, default=2, help="local-cluster workers (default 2)")
    p.add_argument("--test", default="B", choices=("B", "B-paper", "NP", "E"))
    p.add_argument("--pfa", type=float, default=1e-3)
    p.add_argument("--pd", type=float, default=0.5)
    p.add_argument("--draws", type=int, default=20000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--pupil", help="pupil or kernel model (default: the instrument's telescope)")
    p.add_argument("--step", default="0.38m", help="pupil grid step (default 0.38m)")
    p.add_argument("--window", type=int, help="cut-out size in pixels")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true",
                   help="redo entries already done (default: skip them, resuming a run)")
    p.set_defaults(func=cmd_batch)

    p = sub.add_parser("demo", parents=[common], help="run the whole chain on simulated data",
                       epilog="example:\n  kpifs demo -o demo_output",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", default="kpifs_demo", help="output directory")
    p.add_argument("--frames", type=int, default=200, help="exposures per star (default 200)")
    p.add_argument("--draws", type=int, default=20000,
                   help="Monte-Carlo draws calibrating the search (default 20000)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=cmd_demo)
    return parser


def _setup_logging(args):
    """Send kpifs's log records to stderr at the level -v/-q ask for."""
    level = logging.WARNING - 10 * args.verbose
    if args.quiet:
        level = logging.ERROR
    for h in [h for h in log.handlers if getattr(h, "_kpifs_cli", False)]:
        log.removeHandler(h)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("kpifs: %(message)s"))
    handler._kpifs_cli = True
    log.addHandler(handler)
    log.setLevel(max(level, logging.DEBUG))


def main(argv=None):
    """Run the ``kpifs`` command line; return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    _setup_logging(args)
    old_show = warnings.showwarning
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            warnings.showwarning = _make_show(args)
            return args.func(args)
    except BrokenPipeError:  # output piped into `head` and closed: not an error
        sys.stderr.close()
        return 0
    except (KpifsError, OSError) as exc:
        if args.debug:
            raise
        print(f"kpifs {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # pragma: no cover - a bug, not bad input
        if args.debug:
            raise
        print(f"kpifs {args.command}: internal error: {type(exc).__name__}: {exc} "
              f"(rerun with --debug for the traceback)", file=sys.stderr)
        return 3
    finally:
        warnings.showwarning = old_show


def _make_show(args):
    def show(message, category, filename, lineno, file=None, line=None):
        if not args.quiet:
            print(f"kpifs {args.command}: warning: {message}", file=sys.stderr)
    return show


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
