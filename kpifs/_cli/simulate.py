"""``kpifs simulate``: a simulated target (with a companion) and calibrator on disk."""
import numpy as np
from astropy import units as u

from .._checks import check_seed
from .._utils import check_output_dir, to_quantity
from ..exceptions import KpifsError
from ..io.instruments import INSTRUMENTS
from ..io.layouts import write_observation
from ..detect.sky import detector_to_sky
from ..rotation import sequence_angles
from ..simulation.simulate import PRESETS, TYPICAL_STATIC, SceneParameters, simulate_scene


def run(args):
    check_seed(args.seed)
    if args.preset not in PRESETS:
        raise KpifsError(f"--preset {args.preset}: unknown; use one of {', '.join(PRESETS)}")
    INSTRUMENTS.by_layout(args.layout)           # an unknown layout: refused before any work
    out = check_output_dir(args.output)          # refused now, not after the simulation
    earlier = [n for n in ("target.fits", "calibrator.fits", "target", "calibrator")
               if (out / n).exists()]
    if earlier and not args.overwrite:
        raise KpifsError(f"{out}: an earlier simulation exists there ({', '.join(earlier)}); "
                         f"pass --overwrite to replace it")
    over = {}
    if args.frames is not None:
        over["n_frames"] = args.frames
    if args.contrasts is not None:
        try:
            over["contrasts"] = [float(c) for c in args.contrasts.split(",")]
        except ValueError:
            raise KpifsError(f"--contrasts: expected comma-separated numbers, got "
                             f"{args.contrasts!r}") from None
    sky = PRESETS[args.preset].get("sky_offset")
    if sky is not None and (args.separation is not None or args.pa is not None):
        # a preset fixed on the sky: --pa is the position angle East of North
        dra, ddec = sky.to_value(u.mas)
        sep = (to_quantity(args.separation, u.mas, name="--separation").value
               if args.separation is not None else np.hypot(dra, ddec))
        pa = (to_quantity(args.pa, u.deg, name="--pa").value if args.pa is not None
              else np.degrees(np.arctan2(dra, ddec)))
        over["sky_offset"] = [sep * np.sin(np.radians(pa)),
                              sep * np.cos(np.radians(pa))] * u.mas
    elif args.separation is not None or args.pa is not None:
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
    if args.shape is not None:
        if args.shape < 8:
            raise KpifsError(f"--shape must be at least 8 pixels, got {args.shape}")
        over["shape"] = (args.shape, args.shape)
    if args.exptime is not None:
        over["exptime"] = to_quantity(args.exptime, u.s, name="--exptime")
    if getattr(args, "typical_static", False):      # issue 39
        over.update(TYPICAL_STATIC)
    for opt, name in (("drift", "drift_rms"), ("static", "static_rms"),
                      ("static_diff", "static_diff_rms")):
        if getattr(args, opt) is not None:
            over[name] = to_quantity(getattr(args, opt), u.nm, name=f"--{opt.replace('_', '-')}")
    if args.drift_time is not None:
        over["drift_time"] = args.drift_time
    _rotation(args, over)
    obs = simulate_scene(args.preset, seed=args.seed, progress=not args.quiet, **over)
    paths = write_observation(obs, args.output, layout=args.layout, overwrite=args.overwrite)
    n = sum(len(v) for v in paths.values())
    print(f"wrote {n} file(s) ({args.layout} layout) in {args.output}: target with a "
          f"companion at ({obs.truth['KPSIMX'][0]:.1f}, {obs.truth['KPSIMY'][0]:.1f}) mas, "
          f"calibrator")
    return 0


#: Detector angle at parallactic angle 0 and the site of a preset that no instrument's
#: ``sequence`` gives (issue 29).
_SEQUENCE = (0.0, "maunakea")


def _sequence(preset):
    """The detector angle at parallactic angle 0 and the site of *preset*'s sequences:
    those of the instrument that adds it (`kpifs.io.instrument.Instrument.sequence`)."""
    inst = INSTRUMENTS.of_scene(preset)
    return _SEQUENCE if inst is None or inst.sequence is None else inst.sequence


def _rotation(args, over):
    """--rotation or --hour-angle: a sequence turning on the sky, companion fixed there."""
    if args.rotation is None and args.hour_angle is None:
        if args.declination is not None or args.site is not None:
            raise KpifsError("--declination and --site go with --hour-angle")
        return
    if args.rotation is not None and args.hour_angle is not None:
        raise KpifsError("give --rotation or --hour-angle, not both")
    offset, site = _sequence(args.preset)
    params = dict(PRESETS[args.preset])
    params.update(over)
    n = params.get("n_frames", SceneParameters().n_frames)
    if args.rotation is not None:
        span = to_quantity(args.rotation, u.deg, name="--rotation")
        if not abs(span.value) <= 360:
            raise KpifsError(f"--rotation {args.rotation}: a sequence turns by at most 360 deg")
        det = sequence_angles(n, span=span,
                              start=offset)
    else:
        try:
            ha = [float(v) for v in str(args.hour_angle).split(",")]
        except ValueError:
            ha = []
        if len(ha) != 2:
            raise KpifsError(f"--hour-angle: expected start,end in hours, e.g. -1,1; got "
                             f"{args.hour_angle!r}")
        if args.declination is None:
            raise KpifsError("--hour-angle needs the star's --declination")
        if not abs(to_quantity(args.declination, u.deg, name="--declination").value) <= 90:
            raise KpifsError(f"--declination {args.declination}: a declination is within "
                             f"+-90 deg")
        lat = args.site if args.site is not None else site
        try:
            lat = float(lat) * u.deg
        except ValueError:
            pass
        det = sequence_angles(n, hour_angle=ha * u.hourangle, latitude=lat, start=offset,
                              declination=to_quantity(args.declination, u.deg,
                                                      name="--declination"))
    if params.get("sky_offset") is None:
        # the companion where the preset puts it on the detector at the first frame
        x, y = u.Quantity(params.get("companion_offset",
                                     SceneParameters().companion_offset), u.mas).value
        over["sky_offset"] = list(detector_to_sky(x, y, det[0])) * u.mas
    over["detpa"] = det
