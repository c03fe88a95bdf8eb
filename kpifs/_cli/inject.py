"""``kpifs inject``: companions made of each frame's own PSF; the injection contrast curve."""
import warnings
from pathlib import Path

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import QTable

from .._checks import check_inputs, check_memory, check_seed
from .._meta import VERSION
from .._utils import check_output_dir, check_output_path, to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning
from ..inject import inject_companion, injection_brackets, injection_limits
from ..io import parse_wavelengths, read_cube
from ..io._kpfits_common import ascii_text
from ..io.angles import frame_detpa, parse_angles
from ..io.instruments import INSTRUMENTS
from ..io.layouts_like import source_layout, write_added
from ..plotting import _save, analytic_column, plot_injection_limits
from ..workflow import (calibrate_observation, calibrator_options, detect_observation,
                        extract_observation, kernel_model_for, DetectOptions)
from ._options import extract_options


def _floats(text, name, unit=None):
    try:
        if unit is not None:
            return to_quantity(text, unit, name=name)
        return np.array([float(v) for v in str(text).split(",")])
    except (ValueError, TypeError) as exc:
        raise KpifsError(f"{name}: cannot read {text!r} ({exc})") from None


def _contrasts(text, option, n_channels=None):
    """Contrasts of a comma list, each in (0, 1), one or *n_channels* of them."""
    c = _floats(text, option)
    if not np.all(np.isfinite(c)) or np.any(c <= 0) or np.any(c >= 1):
        raise KpifsError(f"{option} {text}: contrasts are companion/star flux ratios, each in "
                         f"(0, 1)")
    if n_channels is not None and c.size not in (1, n_channels):
        raise KpifsError(f"{option} {text}: {c.size} contrasts for {n_channels} channel(s): "
                         f"give one, or one per channel")
    return c


def _check_args(args):
    """Refusals that need no data: made before anything is read."""
    check_seed(args.seed, "--seed")
    check_inputs(args.cubes, args.calibrator or [], outputs=[args.output])
    if args.curve:
        DetectOptions(pfa=args.pfa, draws=args.draws, seed=args.seed).validate()
        if args.angles < 1:
            raise KpifsError(f"--angles must be at least 1, got {args.angles}")
        if args.contrasts is not None:              # else the ladder is adaptive
            _contrasts(args.contrasts, "--contrasts")
        seps = np.atleast_1d(_floats(args.separations, "--separations", u.mas).value)
        if not np.all(np.isfinite(seps)) or np.any(seps <= 0):
            raise KpifsError(f"--separations {args.separations}: separations must be > 0")
    elif args.contrast is not None:
        _contrasts(args.contrast, "--contrast")


def _check_reach(args, seps, window, pixscale, wavelengths, model):
    """Refuse separations the search cannot reach (beyond the extraction window or the
    pupil model's aliasing limit): their limits would be NaN after all the work."""
    reach = window.radius * pixscale.to_value(u.mas)
    if model.pupil is not None and model.pupil.step is not None:
        alias = 0.95 * wavelengths.to_value(u.m).min() / (
            2 * model.pupil.step.to_value(u.m)) / (np.pi / 180 / 3600e3)
        reach = min(reach, alias)
    far = seps.value[seps.value > reach]
    if far.size:
        raise KpifsError(f"--separations: {', '.join(f'{v:g}' for v in far)} mas beyond the "
                         f"search's reach ({reach:.0f} mas: the extraction window and the "
                         f"pupil model's aliasing limit): nothing could be measured there")


def _read(args, options):
    wl = parse_wavelengths(options.wavelengths, source="--wavelengths")
    ps = (None if options.pixscale is None
          else to_quantity(options.pixscale, u.mas, name="pixel scale"))
    with read_cube(args.cubes, instrument=options.instrument, wavelengths=wl,
                   pixscale=ps, dq_bits=options.dq_bits, pa_given=args.pa is not None) as cube:
        if not args.curve and args.contrast is not None:
            _contrasts(args.contrast, "--contrast", cube.shape[1])   # before the data are read
        detpa = None if cube.detpa is None else cube.detpa.to_value(u.deg)
        # the frames, the injected copy and the companion, in float64 (issue 37)
        check_memory(24.0 * np.prod(cube.shape), f"{cube.name}: {cube.shape[0]} frames of "
                     f"{' x '.join(map(str, cube.shape[1:]))}", "inject into fewer frames "
                     "(files) at a time")
        # the header, and where each frame goes back in the files (issue 37)
        return (np.array(cube.data, float), cube.wavelengths, cube.pixscale, detpa,
                cube.instrument, cube.name, (cube.header, source_layout(cube)))


def _outputs(args):
    """The injected files: -o itself for one input file, else one file per input (its own
    name) in the folder -o; refused now if any exists (without --overwrite) or is an input."""
    if args.curve or len(args.cubes) == 1:
        check_output_path(args.output, overwrite=args.overwrite)
        return [Path(args.output)]
    folder = check_output_dir(args.output)
    outs = [folder / Path(c).name for c in args.cubes]
    if len(set(outs)) < len(outs):
        names = ", ".join(map(str, args.cubes))
        raise KpifsError(f"{args.output}: input files of the same name ({names}) would be "
                         f"written over each other: inject them in turn")
    if folder.is_dir():                          # else made when writing
        for o in outs:
            check_output_path(o, overwrite=args.overwrite)
    check_inputs(args.cubes, outputs=outs)
    return outs


def run(args):
    options = extract_options(args)
    outputs = _outputs(args)
    if args.plots:
        check_output_dir(args.plots)
    _check_args(args)
    data, wl, ps, detpa, instrument, name, (header, sources) = _read(args, options)
    if args.pa is not None:        # one rule for angle arguments (values, lists, files)
        detpa = frame_detpa(parse_angles(args.pa, source="--pa"), data.shape[0], source="--pa")
    if not args.curve:
        if args.position is None or args.contrast is None:
            raise KpifsError("inject: give --position and --contrast (or --curve)")
        pos = _floats(args.position, "--position", u.mas)
        c = _floats(args.contrast, "--contrast")
        out = inject_companion(data, position=pos, contrast=c if c.size > 1 else c[0],
                               pixscale=ps, frame="sky" if args.sky else "detector",
                               detpa=detpa)
        cards = {"INJFRAME": ("sky" if args.sky else "detector", "frame of INJPOS1/2"),
                 "INJPOS1": (float(pos.value[0]), "[mas] injected offset x or dRA"),
                 "INJPOS2": (float(pos.value[1]), "[mas] injected offset y or dDec"),
                 "INJSRC": (ascii_text(name)[-45:], "input cube")}
        for i, v in enumerate(np.broadcast_to(c, (len(wl),)), 1):
            cards[f"INJC{i}"] = (float(v), f"injected contrast, channel {i}")
        _write((header, sources), data, out, outputs, instrument, wl, ps, cards, name, args)
        print(f"injected a companion at {args.position} ({'sky' if args.sky else 'detector'}) "
              f"with contrast {args.contrast} into {name} -> {args.output}")
        return 0
    return _curve(args, options, data, wl, ps, instrument, name, header)


def _write(read_from, data, out, outputs, instrument, wl, ps, cards, name, args):
    """The injected images in copies of the input files, in their instrument's layout
    (`kpifs.io.layouts_like`): JWST keeps ERR, DQ, ROLL_REF and PUPIL, GPI its mirror and
    AVPARANG, CHARIS its inverse variance and PARANG, a plain cube its DETPA."""
    header, sources = read_from
    if instrument == "generic":               # what was given on the command line
        cards.update({f"KPWL{i}": (float(w), f"[um] wavelength of channel {i}")
                      for i, w in enumerate(wl.to_value(u.um), 1) if f"KPWL{i}" not in header})
        if "PIXSCALE" not in header:
            cards["PIXSCALE"] = (float(ps.to_value(u.mas)), "[mas] pixel scale")
    outputs[0].parent.mkdir(parents=True, exist_ok=True)
    write_added(sources, data, out - data, outputs, cards=cards, overwrite=args.overwrite,
                history=f"kpifs {VERSION}: companion injected into {ascii_text(name)}")
    note = INSTRUMENTS.get_instrument(instrument).copy_note
    if note:                                  # its reader reads files beside the cube
        warnings.warn(f"{outputs[0]}: {note} {name}; copy them beside it, or give them "
                      f"(--wavelengths, --pa) to read it", KpifsWarning, stacklevel=2)


def _curve(args, options, data, wl, ps, instrument, name, header):
    if not args.calibrator:
        raise KpifsError("inject --curve: give the calibrator's cubes (--calibrator)")
    say = (lambda text: None) if args.quiet else (lambda text: print(text, flush=True))
    seps = np.atleast_1d(_floats(args.separations, "--separations", u.mas))
    say("[1/2] the analytic limits: extraction, calibration and search of the target")
    model = kernel_model_for(options, instrument, header)     # the header's pupil (issue 37)
    window = options.window_for(data.shape)
    _check_reach(args, seps, window, ps, wl, model)
    cals = [extract_observation(c, calibrator_options(options), model=model)
            for c in args.calibrator]
    # the analytic limits first: the ladders start from them
    target = extract_observation(args.cubes, options, model=model)
    analytic = detect_observation(calibrate_observation(target, cals, options),
                                  DetectOptions(pfa=args.pfa, draws=args.draws, seed=args.seed))
    # the limit of the test the injections are searched with (detect's default)
    ana = np.interp(seps.value, analytic.curves["separation"].to_value(u.mas),
                    analytic.curves[analytic_column(analytic)], left=np.nan, right=np.nan)
    ladder = None if args.contrasts is None else _floats(args.contrasts, "--contrasts")
    if ladder is None and not np.all(np.isfinite(ana)):
        bad = ", ".join(f"{s:g}" for s in seps.value[~np.isfinite(ana)])
        raise KpifsError(f"inject --curve: no analytic limit at {bad} mas (outside the search "
                         f"grid) to start the contrast ladder from; give --contrasts")
    say(f"[2/2] injections: {args.angles} position angles per contrast step, from 0.5 to 2 "
        f"times the analytic limit until the steps bracket P_D 0.5" if ladder is None else
        f"[2/2] injections: {args.angles} position angles at each of {len(ladder)} contrasts")
    tab = injection_limits(data, cals, cals[0].kernel_model, wavelengths=wl, pixscale=ps,
                           window=window, separations=seps, contrasts=ladder, start=ana,
                           n_angles=args.angles, pfa=args.pfa, seed=args.seed,
                           n_draws=args.injection_draws, progress=not args.quiet,
                           reference=target, extract_kwargs=dict(
                               centroid=options.centroid, bad_pixels=options.bad_pixels,
                               bad_frames=options.bad_frames, on_nyquist=options.on_nyquist,
                               precision=options.precision))
    write_hdulist(_curve_hdulist(tab, seps, ana, args, name), args.output,
                  overwrite=args.overwrite)
    print(f"injection curve of {name} (P_FA {args.pfa:g}, P_D 0.5, {args.angles} position "
          f"angle(s) per step) -> {args.output}")
    brackets = injection_brackets(tab)
    for s, b, row in zip(seps.value, ana, brackets):
        print(f"  {s:.0f} mas: injections {bracket_text(row)}; analytic {b:.2e}{_inside(row, b)}")
        print(f"    found {_steps_text(tab, s)}")
    if args.plots:
        Path(args.plots).mkdir(parents=True, exist_ok=True)
        _save(plot_injection_limits(tab, analytic=analytic), f"{args.plots}/injection_limits.png")
        print(f"  figure in {args.plots}/")
    return 0


def bracket_text(row):
    """The limit the steps allow one to state: a value within its bracket, the bracket,
    or a bound.

    Examples
    --------
    >>> from kpifs._cli.inject import bracket_text
    >>> bracket_text({"limit_low": 1e-4, "limit_high": 4e-4, "limit_interpolated": float("nan")})
    'between 1.0e-04 and 4.0e-04'
    >>> bracket_text({"limit_low": 1e-4, "limit_high": 2e-4, "limit_interpolated": 1.4e-4})
    '1.4e-04 (interpolated between 1.0e-04 and 2.0e-04)'
    >>> bracket_text({"limit_low": float("nan"), "limit_high": 2e-4,
    ...               "limit_interpolated": float("nan")})
    'below 2.0e-04 (no step found significantly less than half the time)'
    """
    lo, hi, val = (float(row[k]) for k in ("limit_low", "limit_high", "limit_interpolated"))
    if np.isfinite(val):
        return f"{val:.1e} (interpolated between {lo:.1e} and {hi:.1e})"
    if np.isfinite(lo) and np.isfinite(hi):
        return f"between {lo:.1e} and {hi:.1e}"
    if np.isfinite(hi):
        return f"below {hi:.1e} (no step found significantly less than half the time)"
    if np.isfinite(lo):
        return f"above {lo:.1e} (no step found significantly more than half the time)"
    return "not bracketed (no step is conclusive: more angles, or --contrasts further apart)"


def _inside(row, analytic):
    lo, hi = float(row["limit_low"]), float(row["limit_high"])
    if not np.isfinite(analytic):
        return ""
    if (np.isfinite(lo) and analytic < lo) or (np.isfinite(hi) and analytic > hi):
        return " (outside the injections' bracket)"
    return " (within it)" if np.isfinite(lo) and np.isfinite(hi) else ""


def _steps_text(tab, sep):
    m = np.isclose(tab["separation"].to_value(u.mas), sep)
    return ", ".join(f"{int(k)}/{int(n)} at {c:.1e}" for c, k, n in zip(
        np.asarray(tab["contrast"])[m], np.asarray(tab["n_detected"])[m],
        np.asarray(tab["n_injected"])[m]))


def _curve_hdulist(tab, seps, ana, args, name):
    """The curve's FITS: the primary header, the injections and the limits (with flags)."""
    br = injection_brackets(tab)
    lim = QTable({"separation": seps, "limit_low": br["limit_low"],
                  "limit_high": br["limit_high"], "limit_injection": br["limit_interpolated"],
                  "flag": tab.meta["flags"], "limit_analytic": ana})
    hdr = fits.Header()
    hdr["CONTENT"] = ("KPIFS-INJECTION", "kpifs injection-recovery contrast curve")
    hdr["KPIFSVER"] = (VERSION, "kpifs version")
    hdr["PFA"] = (args.pfa, "global false-alarm probability of detections")
    hdr["PD"] = (0.5, "detection probability of the limits")
    hdr["NANGLES"] = (args.angles, "position angles per separation, contrast")
    hdr["SEED"] = (args.seed, "seed of the position angles")
    hdr["LADDER"] = (tab.meta["ladder"], "contrast ladder: given, or adaptive")
    hdr["NDRAWS"] = (tab.meta["n_draws"], "null draws of each injection's search")
    hdr.add_history(f"kpifs {VERSION}: injections into {ascii_text(name)}")
    hdr["COMMENT"] = tab.meta["method"]
    hdr["COMMENT"] = ("LIMITS: the limit lies between limit_low and limit_high (the highest "
                      "step found significantly less than P_D of the time, the lowest found "
                      "significantly more; NaN: none); limit_injection is interpolated only "
                      "when they are adjacent steps, else NaN")
    hdr["COMMENT"] = ("LIMITS.flag: '=' bracketed by the ladder, '<' an upper bound (the "
                      "lowest step found), '>' a lower bound (the highest step not found)")
    # the table's own meta holds lists (the limits: in LIMITS) and long names: plain cards
    inj = tab.copy(copy_data=False)
    inj.meta = {"PFA": tab.meta["pfa"], "PD": tab.meta["pd"], "NANGLES": tab.meta["n_angles"],
                "SEED": tab.meta["seed"], "NDRAWS": tab.meta["n_draws"]}
    t1 = fits.table_to_hdu(inj)
    t1.name = "INJECTIONS"
    t2 = fits.table_to_hdu(lim)
    t2.name = "LIMITS"
    return fits.HDUList([fits.PrimaryHDU(header=hdr), t1, t2])
