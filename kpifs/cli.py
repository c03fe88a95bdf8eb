"""The ``kpifs`` command line.

Exit status: 0 success, 2 bad input or usage (one-line message naming the file
and the problem), 3 an unexpected internal error (rerun with ``--debug`` for
the traceback).
"""
import argparse
import logging
import sys
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u

from . import __version__
from ._utils import check_output_path, to_quantity
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
"""
EPILOG_SIMULATE = """examples:
  kpifs simulate --preset paper --frames 100 -o sim
  kpifs simulate --preset charis --layout charis --frames 5 -o charis_sim
  kpifs simulate --preset sphere --layout sphere -o sphere_sim
"""


def _add_pupil_options(p):
    g = p.add_argument_group("pupil model")
    g.add_argument("--pupil", default="subaru",
                   help="telescope name (subaru, vlt, pharo), pupil image FITS (PUPSCALE "
                        "keyword or --pupil-scale) or kernel-model FITS (default: subaru)")
    g.add_argument("--pupil-scale", help="pupil image pixel size, e.g. 0.02m")
    g.add_argument("--step", default="0.38m", help="grid step (default 0.38m)")
    g.add_argument("--offset", default="0.17m,0.11m",
                   help="grid offset x,y (default 0.17m,0.11m; 0,0 gives a "
                        "centro-symmetric model)")
    g.add_argument("--min-transmission", type=float, default=0.9,
                   help="keep cells at least this much inside the pupil (default 0.9)")
    g.add_argument("--grey", action="store_true", help="keep fractional transmissions")
    g.add_argument("--hexagonal", action="store_true", help="hexagonal grid")


def _kernel_model(args):
    from .kernel import load_kernel_model
    offset = to_quantity(args.offset, u.m, name="--offset")
    if offset.size != 2:
        raise KpifsError(f"--offset needs two values x,y, got {args.offset!r}")
    return load_kernel_model(args.pupil, pupil_scale=args.pupil_scale,
                             step=to_quantity(args.step, u.m, name="--step"), offset=offset,
                             min_transmission=args.min_transmission, grey=args.grey,
                             hexagonal=args.hexagonal)


def cmd_kernel(args):
    check_output_path(args.output, overwrite=args.overwrite)
    km = _kernel_model(args)
    km.write(args.output, overwrite=args.overwrite)
    print(f"{km.pupil.n_sub} sub-apertures, {km.n_uv} uv points, rank {km.rank}, "
          f"{km.n_kp} kernel phases -> {args.output}")
    return 0


def parse_wavelengths(text):
    """Wavelengths from a list ('1.52um,1.6um') or a file (text or FITS, um or nm)."""
    from .io.cube import read_wavelength_file
    if text is None:
        return None
    if Path(text).exists():
        return read_wavelength_file(text)
    return to_quantity(text, u.um, name="--wavelengths")


def cmd_extract(args):
    from .extract import extract_kernel_phases
    from .io.cube import read_generic
    check_output_path(args.output, overwrite=args.overwrite)
    wl = parse_wavelengths(args.wavelengths)
    ps = None if args.pixscale is None else to_quantity(args.pixscale, u.mas,
                                                        name="--pixscale")
    km = _kernel_model(args)
    results = []
    for path in args.cubes:
        with read_generic(path, wavelengths=wl, pixscale=ps) as cube:
            results.append(extract_kernel_phases(
                cube.data, km, wavelengths=cube.wavelengths, pixscale=cube.pixscale,
                mask=cube.mask, window_size=args.window, window_radius=args.window_radius,
                centroid=args.centroid, on_nyquist=args.nyquist, header=cube.header,
                source=path))
    kpd = results[0]
    if len(results) > 1:
        from .extract import KernelPhaseData
        if any(r.n_kp != kpd.n_kp or not np.allclose(r.wavelengths, kpd.wavelengths)
               for r in results):
            raise KpifsError("the cubes do not share channels and kernel model")
        kpd = KernelPhaseData(np.concatenate([r.kp for r in results]), kpd.wavelengths,
                              kpd.pixscale, kpd.kernel_model,
                              phases=np.concatenate([r.phases for r in results]),
                              amplitudes=np.concatenate([r.amplitudes for r in results]),
                              header=kpd.header, meta=kpd.meta)
    kpd.write(args.output, overwrite=args.overwrite, inputs=args.cubes)
    print(f"{kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases "
          f"-> {args.output}")
    return 0


def cmd_simulate(args):
    from .io.layouts import write_observation
    from .simulate import simulate_scene
    over = {}
    if args.frames is not None:
        over["n_frames"] = args.frames
    if args.contrasts is not None:
        over["contrasts"] = [float(c) for c in args.contrasts.split(",")]
    if args.separation is not None or args.pa is not None:
        from .simulate import PRESETS, SceneParameters
        base = PRESETS[args.preset].get("companion_offset",
                                        SceneParameters().companion_offset).to_value(u.mas)
        sep = (to_quantity(args.separation, u.mas, name="--separation").value
               if args.separation is not None else np.hypot(*base))
        pa = (to_quantity(args.pa, u.deg, name="--pa").value if args.pa is not None
              else np.degrees(np.arctan2(base[1], base[0])))
        over["companion_offset"] = [sep * np.cos(np.radians(pa)),
                                    sep * np.sin(np.radians(pa))] * u.mas
    if args.wavefront is not None:
        over["wavefront_rms"] = to_quantity(args.wavefront, u.nm, name="--wavefront")
    obs = simulate_scene(args.preset, seed=args.seed, progress=not args.quiet, **over)
    paths = write_observation(obs, args.output, layout=args.layout, overwrite=args.overwrite)
    n = sum(len(v) for v in paths.values())
    print(f"wrote {n} file(s) ({args.layout} layout) in {args.output}: target with a "
          f"companion at ({obs.truth['KPSIMX'][0]:.1f}, {obs.truth['KPSIMY'][0]:.1f}) mas, "
          f"calibrator")
    return 0


def cmd_demo(args):
    from .demo import run_demo
    run_demo(args.output, frames=args.frames, seed=args.seed, overwrite=args.overwrite,
             progress=not args.quiet)
    return 0


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
    p.add_argument("cubes", nargs="+", metavar="CUBE", help="FITS cube(s)")
    p.add_argument("--wavelengths", help="list (1.52um,1.60um) or file (text/FITS, um or nm); "
                                         "default: header cards KPWLn")
    p.add_argument("--pixscale", help="pixel scale, e.g. 10.42mas; default: header PIXSCALE")
    _add_pupil_options(p)
    g = p.add_argument_group("extraction")
    g.add_argument("--window", type=int, help="cut-out size in pixels (default: image size)")
    g.add_argument("--window-radius", type=float,
                   help="super-Gaussian radius in pixels (default 0.8 x half the cut-out)")
    g.add_argument("--centroid", default="com", choices=("com", "peak", "quadratic", "2dg"),
                   help="star-centre method (default com)")
    g.add_argument("--nyquist", default="drop", choices=("drop", "raise"),
                   help="uv points beyond the Nyquist limit: drop (warn) or refuse")
    p.add_argument("-o", "--output", required=True, help="output KPFITS file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_extract)

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
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("-o", "--output", required=True, help="output directory")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("demo", parents=[common], help="run the whole chain on simulated data",
                       epilog="example:\n  kpifs demo -o demo_output",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("-o", "--output", default="kpifs_demo", help="output directory")
    p.add_argument("--frames", type=int, default=40, help="frames per star (default 40)")
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
