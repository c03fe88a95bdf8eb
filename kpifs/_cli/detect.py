"""``kpifs detect``: search kernel phases for companions and write the products."""
from astropy import units as u

from .._utils import check_output_path
from ..data import KernelPhaseData
from ..plotting import save_detection_plots
from ..workflow import detect_observation
from ._options import detect_options


def run(args):
    check_output_path(args.output, overwrite=args.overwrite)
    kpd = KernelPhaseData.read(args.kp)
    cals = [KernelPhaseData.read(c) for c in (args.calibrator or [])]
    res = detect_observation(kpd, detect_options(args), calibrators=cals,
                             progress=not args.quiet)
    res.write(args.output, inputs=[args.kp] + list(args.calibrator or []),
              overwrite=args.overwrite)
    print(f"{args.test} search, global P_FA {args.pfa:g}: {len(res.candidates)} candidate(s) "
          f"-> {args.output}")
    for row in res.candidates:
        x = row["fit_x"] if "fit_x" in row.colnames else row["x"]
        y = row["fit_y"] if "fit_y" in row.colnames else row["y"]
        print(f"  ({x.to_value(u.mas):.1f}, {y.to_value(u.mas):.1f}) mas, separation "
              f"{row['separation'].to_value(u.mas):.0f} mas, global P_FA {row['pfa_global']:.1e}")
    if args.plots:
        truth = None
        if "KPSIMX" in kpd.header and "KPSIMY" in kpd.header:
            truth = (kpd.header["KPSIMX"], kpd.header["KPSIMY"])
        save_detection_plots(res, args.plots, truth=truth)
        print(f"  figures in {args.plots}/")
    return 0
