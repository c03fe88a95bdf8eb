"""``kpifs extract``: kernel phases of cubes, calibrated when calibrators are given."""
from .._checks import check_inputs
from .._utils import check_output_path
from ..workflow import reduce_observation
from ._options import extract_options


def run(args):
    check_output_path(args.output, overwrite=args.overwrite)
    check_inputs(args.cubes, args.calibrator or [], outputs=[args.output])
    opts = extract_options(args)
    cal_files = args.calibrator or []
    kpd, _ = reduce_observation(args.cubes, cal_files, opts, progress=not args.quiet)
    kpd.write(args.output, overwrite=args.overwrite,
              inputs=list(args.cubes) + [f for files in cal_files for f in files])
    what = "calibrated kernel phases" if kpd.meta.get("calibrated") else \
        "spectral-differential kernel phases" if opts.spectral_differential else \
        "angular-differential time blocks" if opts.angular_differential else \
        f"{kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases"
    print(f"{kpd.meta.get('instrument', 'cube')}: {what} -> {args.output}")
    return 0
