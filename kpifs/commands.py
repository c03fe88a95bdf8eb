"""Implementations of the ``kpifs`` subcommands (the parser lives in `kpifs.cli`).

Each ``cmd_*`` takes the parsed arguments and returns an exit status; bad input
raises `~kpifs.KpifsError`, which `kpifs.cli.main` turns into a one-line message.
"""
import logging
import sys
from pathlib import Path

import numpy as np
from astropy import units as u

from ._utils import check_output_path, to_quantity
from .exceptions import KpifsError

__all__ = ["parse_wavelengths"]

log = logging.getLogger("kpifs")


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
    if args.pupil is None:
        args.pupil = "subaru"
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


DEFAULT_PUPIL = {"charis": "subaru", "sphere": "vlt", "generic": "subaru"}


def _read(paths, args, wl, ps):
    from .io import read_cube
    return read_cube(paths, instrument=args.instrument, wavelengths=wl, pixscale=ps)


def _extract(cube, km, args):
    from .extract import extract_kernel_phases
    with cube:
        return extract_kernel_phases(
            cube.data, km, wavelengths=cube.wavelengths, pixscale=cube.pixscale,
            mask=cube.mask, window_size=args.window, window_radius=args.window_radius,
            centroid=args.centroid, bad_pixels=args.bad_pixels, on_nyquist=args.nyquist,
            header=cube.header, source=cube.name, progress=not args.quiet)


def cmd_extract(args):
    from .calibrate import calibrate
    check_output_path(args.output, overwrite=args.overwrite)
    wl = parse_wavelengths(args.wavelengths)
    ps = None if args.pixscale is None else to_quantity(args.pixscale, u.mas,
                                                        name="--pixscale")
    with _read(args.cubes, args, wl, ps) as cube:
        if args.pupil is None:
            args.pupil = DEFAULT_PUPIL[cube.instrument]
        log.info("%s read as %s: %s", cube.name, cube.instrument, cube.shape)
        km = _kernel_model(args)
        kpd = _extract(cube, km, args)
    inputs = list(args.cubes)
    if args.calibrator:
        cals = []
        for files in args.calibrator:
            cal_cube = _read(files, args, wl, ps)
            cals.append(_extract(cal_cube, km, args))
            inputs += files
        kpd = calibrate(kpd, cals, shrinkage=args.shrinkage, joint=args.joint_covariance)
    elif args.joint_covariance or args.covariance:
        from .covariance import empirical_covariance
        if kpd.n_frame < 2:
            raise KpifsError(f"{cube.name}: one frame: no covariance can be estimated")
        kpd.covariance = empirical_covariance(kpd.kp, shrinkage=args.shrinkage,
                                              source=cube.name)
        if args.joint_covariance:
            kpd.joint_covariance = empirical_covariance(kpd.kp, joint=True,
                                                        shrinkage=args.shrinkage,
                                                        source=cube.name)
    kpd.write(args.output, overwrite=args.overwrite, inputs=inputs)
    what = "calibrated kernel phases" if args.calibrator else \
        f"{kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases"
    print(f"{cube.instrument}: {what} -> {args.output}")
    return 0


def cmd_info(args):
    from .io import read_cube
    from .io.cube import _open_fits
    from .kernel import KernelModel
    for path in args.files:
        with _open_fits(path) as hdul:
            is_kp = "KP-DATA" in hdul
            is_model = "KER-MAT" in hdul
            is_det = hdul[0].header.get("CONTENT") == "KPIFS-DETECTION"
        if is_det:
            _info_detection(path)
        elif is_kp:
            _info_kpfits(path)
        elif is_model:
            print(f"{path}: kernel model\n  {KernelModel.read(path)!r}")
        else:
            wl = parse_wavelengths(args.wavelengths)
            ps = None if args.pixscale is None else to_quantity(args.pixscale, u.mas,
                                                                name="--pixscale")
            with read_cube([path], instrument=args.instrument, wavelengths=wl,
                           pixscale=ps) as cube:
                _info_cube(cube, args)
    return 0


def _info_detection(path):
    from .io.products import read_detection
    d = read_detection(path)
    h = d["header"]
    print(f"{path}: kpifs detection products")
    print(f"  test {h['TEST']}, global P_FA {h['PFA']:g}, P_D {h['PD']:g}, threshold "
          f"{h['THRESH']:.3f} ({h['NDRAWS']} Monte-Carlo draws)")
    print(f"  map {d['DETECTION'].shape[1]} x {d['DETECTION'].shape[0]}; energy detector: "
          f"T_E = {h['ESTAT']:.1f} for {h['EDOF']} degrees of freedom, P_FA {h['EPFA']:.2e}")
    cands = d["CANDIDATES"]
    print(f"  {len(cands)} candidate(s)")
    for row in cands:
        print(f"    ({row['x'].to_value(u.mas):.1f}, {row['y'].to_value(u.mas):.1f}) mas, "
              f"global P_FA {row['pfa_global']:.1e}")


def _info_kpfits(path):
    from .extract import KernelPhaseData
    kpd = KernelPhaseData.read(path)
    wl = kpd.wavelengths.to_value(u.um)
    print(f"{path}: kernel-phase data (KPFITS)")
    print(f"  {kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases; "
          f"{wl.min():.4f}-{wl.max():.4f} um; {kpd.pixscale:.2f}")
    print(f"  model: {kpd.kernel_model!r}")
    cals = ", ".join(kpd.meta.get("calibrators", []))
    print(f"  calibrated: {'yes, with ' + cals if kpd.meta.get('calibrated') else 'no'}")
    cov = "per channel" if kpd.covariance is not None else "none"
    if kpd.joint_covariance is not None:
        cov += " and joint"
    print(f"  covariance: {cov}")


def _info_cube(cube, args):
    from .kernel import nyquist_usable
    wl = cube.wavelengths.to_value(u.um)
    print(f"{cube.name}: {cube.instrument} cube")
    print(f"  frames x channels x y x x: {' x '.join(str(n) for n in cube.shape)}")
    print(f"  wavelengths: {len(wl)} channels, {wl.min():.4f}-{wl.max():.4f} um")
    print(f"  pixel scale: {cube.pixscale:.2f}")
    if cube.angles is not None and np.any(np.isfinite(cube.angles.value)):
        print(f"  frame angles: {np.nanmin(cube.angles.value):.2f}-"
              f"{np.nanmax(cube.angles.value):.2f} deg")
    for key in ("OBJECT", "TELESCOP", "EXPTIME", "KPSIMX", "KPSIMY"):
        if key in cube.header:
            print(f"  {key}: {cube.header[key]}")
    if args.pupil is None:
        args.pupil = DEFAULT_PUPIL[cube.instrument]
    km = _kernel_model(args)
    usable = nyquist_usable(km.uv, cube.wavelengths, cube.pixscale)
    lost = (~usable).sum(axis=1)
    print(f"  pupil model {args.pupil}: {km.pupil.n_sub} sub-apertures, {km.n_uv} uv points, "
          f"{km.n_kp} kernel phases")
    if lost.any():
        for w, n in zip(wl[lost > 0], lost[lost > 0]):
            print(f"  Nyquist: at {w:.4f} um, {n} of {km.n_uv} uv points are beyond the "
                  f"sampling limit")
        print("  extract drops them for every channel (--nyquist drop, the default) or "
              "refuses (--nyquist raise)")
    else:
        print("  Nyquist: every channel is sampled well enough for every uv point")
    given = [f"--{opt} {getattr(args, opt)}" for opt in ("instrument", "wavelengths", "pixscale")
             if getattr(args, opt) not in (None, "auto")]
    files = cube.source[0] if len(cube.source) == 1 else f"{cube.source[0]} ..."
    print(f"  next: kpifs extract {files} {' '.join(given + [f'--pupil {args.pupil}'])} "
          f"[--calibrator CAL] -o kp.fits")


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
    if args.shape is not None:
        if args.shape < 8:
            raise KpifsError(f"--shape must be at least 8 pixels, got {args.shape}")
        over["shape"] = (args.shape, args.shape)
    if args.exptime is not None:
        over["exptime"] = to_quantity(args.exptime, u.s, name="--exptime")
    obs = simulate_scene(args.preset, seed=args.seed, progress=not args.quiet, **over)
    paths = write_observation(obs, args.output, layout=args.layout, overwrite=args.overwrite)
    n = sum(len(v) for v in paths.values())
    print(f"wrote {n} file(s) ({args.layout} layout) in {args.output}: target with a "
          f"companion at ({obs.truth['KPSIMX'][0]:.1f}, {obs.truth['KPSIMY'][0]:.1f}) mas, "
          f"calibrator")
    return 0


def _spectrum(text, nwave):
    if text is None or text == "flat":
        return None
    if Path(text).exists():
        return np.loadtxt(text, ndmin=1)
    try:
        return np.array([float(v) for v in text.split(",")])
    except ValueError:
        raise KpifsError(f"--spectrum: expected 'flat', comma-separated values or a file, "
                         f"got {text!r}") from None


def cmd_detect(args):
    from .detect import detect
    from .extract import KernelPhaseData
    from .io.products import write_detection
    check_output_path(args.output, overwrite=args.overwrite)
    kpd = KernelPhaseData.read(args.kp)
    cals = [KernelPhaseData.read(c) for c in (args.calibrator or [])]
    grid = None
    if args.max_sep or args.step or args.min_sep:
        from .detect import default_grid
        grid = default_grid(kpd, step=_mas(args.step), max_sep=_mas(args.max_sep),
                            min_sep=_mas(args.min_sep))
    res = detect(kpd, calibrator=cals or None, test=args.test, pfa=args.pfa, pd=args.pd,
                 grid=grid, spectrum=_spectrum(args.spectrum, kpd.n_wave),
                 n_draws=args.draws, seed=args.seed, progress=not args.quiet)
    inputs = [args.kp] + list(args.calibrator or [])
    write_detection(res, args.output, header=kpd.header, inputs=inputs,
                    overwrite=args.overwrite)
    print(f"{args.test} search, global P_FA {args.pfa:g}: {len(res.candidates)} candidate(s) "
          f"-> {args.output}")
    for row in res.candidates:
        x = row["fit_x"] if "fit_x" in row.colnames else row["x"]
        y = row["fit_y"] if "fit_y" in row.colnames else row["y"]
        print(f"  ({x.to_value(u.mas):.1f}, {y.to_value(u.mas):.1f}) mas, separation "
              f"{row['separation'].to_value(u.mas):.0f} mas, global P_FA {row['pfa_global']:.1e}")
    if args.plots:
        from .plotting import save_detection_plots
        truth = None
        if "KPSIMX" in kpd.header and "KPSIMY" in kpd.header:
            truth = (kpd.header["KPSIMX"], kpd.header["KPSIMY"])
        save_detection_plots(res, args.plots, truth=truth)
        print(f"  figures in {args.plots}/")
    return 0


def _mas(text):
    return None if text is None else to_quantity(text, u.mas, name="grid option")


def cmd_roc(args):
    from .detect.roc import paper_experiment
    from .plotting import plot_roc
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise KpifsError(f"{out}: exists and is not a directory")
    table_path = out / "roc.ecsv"
    if table_path.exists() and not args.overwrite:
        raise KpifsError(f"{table_path}: output exists; pass --overwrite to replace it")
    table, curves = paper_experiment(preset=args.preset, n_frames=args.frames,
                                     n_draws=args.draws, seed=args.seed,
                                     progress=not args.quiet)
    out.mkdir(parents=True, exist_ok=True)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    names = list(curves)
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 4), squeeze=False)
    for ax, name in zip(axes[0], names):
        c = curves[name]
        plot_roc({k: v for k, v in c.items() if "theory" not in k}, ax=ax,
                 theory={k.split()[0]: v for k, v in c.items() if "theory" in k},
                 title=f"channels: {name}")
    fig.tight_layout()
    fig.savefig(out / "roc.png", dpi=90)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(5, 4))
    plot_roc({n: curves[n]["NP"] for n in names}, ax=ax,
             theory={n: curves[n]["NP theory"] for n in names}, title="NP: channel sets")
    fig.tight_layout()
    fig.savefig(out / "roc_np_channels.png", dpi=90)
    plt.close(fig)
    import tempfile
    import os
    fd, tmp = tempfile.mkstemp(dir=out, suffix=".ecsv")
    os.close(fd)
    table.write(tmp, overwrite=True, format="ascii.ecsv")
    os.replace(tmp, table_path)
    os.chmod(table_path, 0o644)
    for row in table:
        if row["channels"] == "all":
            print(f"{row['test']:8s} all channels: AUC {row['auc']:.4f}, P_D(P_FA=0.01) "
                  f"{row['pd']:.3f}")
    print(f"-> {out}/roc.ecsv, roc.png, roc_np_channels.png")
    return 0


def cmd_batch(args):
    from .batch import BatchOptions, entries_from_glob, read_manifest, run_batch
    entries = []
    for m in args.manifest or []:
        entries += read_manifest(m)
    if args.glob:
        if not args.calibrator:
            raise KpifsError("--glob needs --calibrator PATTERN (the calibrator rule)")
        entries += entries_from_glob(args.glob, args.calibrator)
    if not entries:
        raise KpifsError("nothing to do: give a MANIFEST or --glob PATTERN --calibrator PATTERN")
    opts = BatchOptions(test=args.test, pfa=args.pfa, pd=args.pd, draws=args.draws,
                        seed=args.seed, pupil=args.pupil, step=to_quantity(
                            args.step, u.m, name="--step").value, window=args.window,
                        overwrite=args.overwrite)
    table = run_batch(entries, args.output, options=opts, scheduler=args.scheduler,
                      n_workers=args.workers, progress=not args.quiet)
    counts = {s: int(np.sum(table["status"] == s)) for s in ("ok", "skipped", "failed")}
    print(f"{len(table)} entries: {counts['ok']} processed, {counts['skipped']} done earlier, "
          f"{counts['failed']} failed -> {args.output}/summary.ecsv")
    for row in table[table["status"] == "failed"]:
        print(f"  {row['name']}: {row['message'][:200]}", file=sys.stderr)
    return 0 if counts["failed"] == 0 else 1


def cmd_demo(args):
    from .demo import run_demo
    run_demo(args.output, frames=args.frames, seed=args.seed, overwrite=args.overwrite,
             progress=not args.quiet, draws=args.draws)
    return 0
