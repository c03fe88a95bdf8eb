"""``kpifs extract``: kernel phases of cubes, calibrated when calibrators are given."""
from .._checks import check_inputs
from .._utils import check_output_path
from ..adi import angular_differential
from ..filters import extract_filters, jwst_filters
from ..workflow import calibrate_observation, calibrator_options, extract_observation
from ._options import extract_options


def run(args):
    check_output_path(args.output, overwrite=args.overwrite)
    check_inputs(args.cubes, args.calibrator or [], outputs=[args.output])
    opts = extract_options(args)
    progress = not args.quiet
    cal_files = args.calibrator or []
    if len(jwst_filters(args.cubes)) > 1:        # JWST filters as the channels of one product
        kpd = extract_filters(args.cubes, cal_files, opts, progress=progress)
        cals = cal_files
    else:
        kpd = extract_observation(args.cubes, opts, progress=progress)
        cals = [extract_observation(files, calibrator_options(opts), model=kpd.kernel_model,
                                    progress=progress) for files in cal_files]
        target = kpd
        kpd = calibrate_observation(kpd, cals, opts)
        if args.angular_differential:               # issue 29
            kpd = angular_differential(target, kpd if cals else None)
    kpd.write(args.output, overwrite=args.overwrite,
              inputs=list(args.cubes) + [f for files in cal_files for f in files])
    what = "calibrated kernel phases" if cals else \
        "angular-differential time blocks" if args.angular_differential else \
        f"{kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases"
    print(f"{kpd.meta.get('instrument', 'cube')}: {what} -> {args.output}")
    return 0
