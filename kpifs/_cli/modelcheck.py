"""``kpifs model-check``: fit the pupil model's orientation and scale to a star's frames."""
import numpy as np
from astropy import units as u

from .._checks import check_inputs, check_memory, check_same_setup
from .._utils import check_output_path, to_quantity, write_table
from ..exceptions import KpifsError
from ..io.readers import read_cube
from ..io.wavelengths import parse_wavelengths
from ..modelcheck import check_pupil_model
from ..workflow import default_pupil
from ..model.window import ExtractionWindow


def _floats(text, name):
    try:
        return [float(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise KpifsError(f"{name} must be a comma list of numbers, "
                         f"got {text!r}") from None


def _read(files, args):
    with read_cube(files, instrument=args.instrument, dq_bits=args.dq_bits,
                   wavelengths=parse_wavelengths(args.wavelengths, source="--wavelengths"),
                   pixscale=None if args.pixscale is None
                   else to_quantity(args.pixscale, u.mas, name="pixel scale")) as cube:
        if cube.shape[0] < 4:              # before the frames are read
            raise KpifsError(f"{cube.name}: {cube.shape[0]} frame(s): kpifs model-check needs "
                             f"at least 4 frames of the star")
        check_memory(16.0 * np.prod(cube.shape), f"{cube.name}: {cube.shape[0]} frames of "
                     f"{' x '.join(map(str, cube.shape[1:]))}", "check the model on fewer "
                     "frames (files)")
        return (np.array(cube.data, float), cube.wavelengths, cube.pixscale,
                (cube.instrument, cube.header))


def run(args):
    if args.output:
        check_output_path(args.output, overwrite=args.overwrite)
    check_inputs(args.cubes, [args.calibrator] if args.calibrator else [])
    data, wl, ps, instrument = _read(args.cubes, args)
    cal = None
    if args.calibrator:
        cal, wl_c, _, (_, cal_header) = _read(args.calibrator, args)
        check_same_setup(instrument[1], cal_header)     # issue 37: one pupil, one filter
        if len(wl_c) != len(wl):
            raise KpifsError(f"{args.calibrator[0]} has {len(wl_c)} "
                             f"channels, {args.cubes[0]} {len(wl)}")
    pupil = args.pupil or default_pupil(*instrument)
    window = ExtractionWindow.default(data.shape, size=args.window_size,
                                      radius=args.window_radius)
    steps = None if args.steps is None else u.Quantity(_floats(args.steps, "--steps"), u.m)
    chk = check_pupil_model(data, cal, wavelengths=wl, pixscale=ps, pupil=pupil,
                            progress=not args.quiet, window=window,
                            pupil_scale=None if args.pupil_scale is None
                            else to_quantity(args.pupil_scale, u.m, name="--pupil-scale"),
                            rotations=u.Quantity(_floats(args.rotations, "--rotations"), u.deg),
                            scales=_floats(args.scales, "--scales"),
                            cuts=_floats(args.cuts, "--cuts"), steps=steps)
    if not args.quiet:
        t = chk.table.copy()
        for name in ("amp_mismatch", "chi2_red"):
            t[name].info.format = ".4f"
        for name in ("residual", "scatter"):
            t[name].info.format = ".5f"
        t["rotation"].info.format = ".2f"
        t["scale"].info.format = ".4f"
        t.pprint(max_lines=-1, max_width=-1)
        print(chk.summary())
    if args.output:
        write_table(chk.table, args.output, overwrite=args.overwrite)
    return 0
