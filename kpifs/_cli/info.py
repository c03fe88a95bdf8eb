"""``kpifs info``: describe a cube, a KPFITS file, a kernel model or detection products."""
import warnings

import numpy as np
from astropy import units as u
from astropy.table import QTable

from ..data import DetectionResult, KernelPhaseData
from ..exceptions import KpifsError, KpifsWarning, MissingInformation
from ..model.field import field_sentence
from ..io.cube import check_header_checksums, open_fits
from ..io.instruments import INSTRUMENTS
from ..io.kpfits_read import _layout, _read_pixscale, _read_wavelengths
from ..io.readers import detect_instrument, read_cube
from ..io.wavelengths import parse_wavelengths
from ..model.kernel import KernelModel, nyquist_usable
from ..model.sampling import aliased_channels
from ..workflow import default_pupil, kernel_model_for
from ._options import extract_options
from ._summary import contrast_text, pfa_text, position_text
from .inject import bracket_text

# model options the suggested next command repeats
_MODEL_OPTIONS = ("pupil_scale", "step", "offset", "min_transmission", "grey",
                  "min_redundancy", "rotation",
                  "hexagonal")


def _check_headers(path):
    """Say when a header no longer matches its CHECKSUM (issue 37: a header edited or
    corrupted after writing went unnoticed): the description that follows may be wrong."""
    try:
        check_header_checksums(path)
    except KpifsError as exc:
        warnings.warn(f"{exc} (edited without updating CHECKSUM, or corrupted): what follows "
                      f"describes the header as it is now", KpifsWarning, stacklevel=2)


def _instruments():
    """``kpifs info --instruments``: the registry, one block per instrument."""
    for inst in INSTRUMENTS.values():
        names = ", ".join(inst.instrume) or "any FITS cube (the fallback)"
        print(f"{inst.name}: {inst.title}\n  recognised by: {names}\n"
              f"  pupil: {inst.pupil}{' (or as the header names)' if inst.header_pupil else ''}"
              f"\n  pixel scale: {inst.pixscale}\n  detector angle: {inst.angles}\n"
              f"  simulator layout: {inst.layout or 'none'}")


def run(args):
    if args.instruments:
        _instruments()
    elif not args.files:
        raise KpifsError("kpifs info: give FITS file(s) to describe, or --instruments")
    for path in args.files:
        with open_fits(path) as hdul:
            _check_headers(path)
            is_kp = "KP-DATA" in hdul
            is_model = "KER-MAT" in hdul
            content = hdul[0].header.get("CONTENT")
            is_oi = "OI_T3" in hdul
            # kpifs's own KPFITS described from its headers (and small tables): no model
            # is rebuilt, no array read beyond what the checksums cover
            done = is_kp and _kpfits_headers(path, hdul)
        if done:
            continue
        if is_oi:
            _oifits(path)
        elif content == "KPIFS-DETECTION":
            _detection(path)
        elif content == "KPIFS-INJECTION":
            _injection(path)
        elif is_kp:
            _kpfits(path)
        elif is_model:
            print(f"{path}: kernel model\n  {KernelModel.read(path)!r}")
        else:
            _cube(path, args)
    return 0


def _detection(path):
    res = DetectionResult.read(path)
    print(f"{path}: kpifs detection products")
    print(f"  test {res.test}, global P_FA {res.pfa:g}, P_D {res.pd:g}, threshold "
          f"{res.threshold:.3f} ({res.meta['n_draws']} Monte-Carlo draws)")
    nul = res.meta.get("null") or {}
    if "threshold_empirical" in nul:
        gauss = nul.get("threshold_gaussian")
        gauss = "-" if gauss is None else f"{float(gauss):.3f}"
        print(f"  null {nul['method']}: Gaussian threshold {gauss}, empirical "
              f"{float(nul['threshold_empirical']):.3f} (sign flips of "
              f"{nul.get('n_blocks')} time blocks, {nul.get('empirical_draws')} draws)")
    sky = res.grid.frame == "sky"
    where = "on the sky (dRA, dDec; East left)" if sky else "on the detector (x, y)"
    print(f"  map {res.statistic.shape[1]} x {res.statistic.shape[0]} {where}"
          + ("; SEARCH: the residual map the search stopped on" if res.search_map is not None
             else ""))
    _noise_lines(res)
    if res.meta.get("field"):
        print("  " + field_sentence(res.meta["field"]))
    print(f"  {len(res.candidates)} candidate(s)")
    floors = [res.meta.get("n_draws"), nul.get("empirical_draws")]
    for i, row in enumerate(res.candidates, 1):
        known = sky or "dra" in row.colnames    # sky offsets only from known angles
        print(f"    {i}: {position_text(row, sky_known=known)}")
        print(f"       {contrast_text(row)}; global P_FA "
              f"{pfa_text(row['pfa_global'], row['pfa_global_tail'], floors)}")


def _noise_lines(res):
    """The error model against the data: energy, residual chi-square, the map's noise and
    the scales the tests were judged with."""
    e = res.energy
    if e.get("dof"):
        raw = e.get("raw")
        raw = "" if raw is None else f"whitened energy {raw / e['dof']:.3f} per dof; "
        print(f"  energy ({e['dof']} dof): {raw}energy test T_E = {e['statistic']:.1f} at the "
              f"noise scale, P_FA {e['pfa']:.2e}")
    parts = [f"{name} {float(v):.3f}" for name, v in (
        ("residual chi2_red", res.meta.get("chi2_red")), ("map noise", e.get("map_noise")),
        ("expected from the null's rows", e.get("map_expectation")),
        ("subspace map noise", e.get("subspace_noise")),
        ("noise scale of the test", res.meta.get("noise_scale"))) if v is not None]
    if parts:
        print(f"  noise: {', '.join(parts)}")


def _kpfits(path):
    kpd = KernelPhaseData.read(path)
    wl = kpd.wavelengths.to_value(u.um)
    meta = kpd.meta
    who = {"kpifs": "kpifs", "jwst-kpi": "jwst-kpi", "xara": "xara", "xara-legacy":
           "xara (legacy)", "pykernel": "PyKernel/pynrm"}.get(meta.get("layout"), "unknown")
    print(f"{path}: kernel-phase data (KPFITS, written by {who})")
    if meta.get("instrument") or meta.get("telescope"):
        print(f"  {meta.get('instrument') or '?'} on {meta.get('telescope') or '?'}")
    print(f"  {kpd.n_frame} frame(s) x {kpd.n_wave} channel(s) x {kpd.n_kp} kernel phases; "
          f"{wl.min():.4f}-{wl.max():.4f} um; {kpd.pixscale:.2f}")
    print(f"  model: {kpd.kernel_model!r}")
    _print_own_kernels(wl, meta.get("channel_n_kp"))
    cals = ", ".join(meta.get("calibrators", []))
    print(f"  calibrated: {'yes, with ' + cals if meta.get('calibrated') else 'no'}")
    cov = "per channel" if kpd.covariance is not None else "none"
    if kpd.joint_covariance is not None:
        cov += " and joint"
    if meta.get("covariance_source") and meta.get("layout") != "kpifs":
        cov += f" (from {meta['covariance_source']})"
    if kpd.kp_err is not None:
        cov += "; per-frame errors"
    print(f"  covariance: {cov}")
    _print_angles(kpd.detpa, meta.get("detpa_source") or "file")
    for note in meta.get("notes", []):
        print(f"  note: {note}")


def _oifits(path):
    kpd = KernelPhaseData.read(path, format="oifits")
    wl = kpd.wavelengths.to_value(u.um)
    cp = kpd.meta["closure_phases"]
    print(f"{path}: OIFITS closure phases ({kpd.meta.get('instrument') or '?'} on "
          f"{kpd.meta.get('telescope') or '?'})")
    print(f"  {cp['n_triangles']} triangles in {cp['n_tables']} OI_T3 table(s), "
          f"{cp['n_epochs']} epoch(s): {kpd.n_kp} independent closure phases x "
          f"{kpd.n_wave} channel(s), {wl.min():.4f}-{wl.max():.4f} um")
    print(f"  covariance: {kpd.meta['covariance_source']}"
          f"{'; channels correlated' if kpd.joint_covariance is not None else ''}")
    print("  (u, v) East/North: maps and candidates on the sky")
    for note in kpd.meta.get("notes", []):
        print(f"  note: {note}")
    print(f"  next: kpifs detect {path} -o detection.fits")


def _print_own_kernels(wl, counts):
    """Channels with their own kernels (JWST filters): each one's number of kernel phases."""
    if counts is not None and all(n is not None for n in counts):
        print("  each channel its own kernel (its first kernel phases): "
              + ", ".join(f"{w:.4f} um {int(n)}" for w, n in zip(wl, counts)))


def _print_angles(pa, source):
    """The frames' detector position angles in one line (a range, and how many unknown)."""
    if pa is None:
        print("  detector position angle: unknown")
        return
    pa = np.ravel(np.asarray(pa, float))
    known = pa[np.isfinite(pa)]
    text = "unknown" if known.size == 0 else (
        f"{known[0]:.2f} deg" if np.ptp(known) == 0 else
        f"{known.min():.2f} to {known.max():.2f} deg")
    if 0 < known.size < pa.size:
        text += f" ({pa.size - known.size} frame(s) unknown)"
    print(f"  detector position angle: {text} ({source})")


def _injection(path):
    with open_fits(path, verify=True) as hdul:
        hdr = hdul[0].header
        lim = QTable.read(hdul["LIMITS"]) if "LIMITS" in hdul else None
        n_rows = len(hdul["INJECTIONS"].data) if "INJECTIONS" in hdul else 0
    print(f"{path}: kpifs injection-recovery contrast curve")
    print(f"  global P_FA {hdr.get('PFA', float('nan')):g}, P_D {hdr.get('PD', 0.5):g}; "
          f"{hdr.get('NANGLES', '?')} position angle(s) per step, {n_rows} step(s) "
          f"({hdr.get('LADDER', 'given')} ladder)")
    for row in ([] if lim is None else lim):
        if "limit_low" in lim.colnames:      # the file names the interpolated value so
            text = bracket_text({"limit_low": row["limit_low"], "limit_high": row["limit_high"],
                                 "limit_interpolated": row["limit_injection"]})
        else:           # written before the brackets: the interpolated value and its flag
            flag = str(row["flag"]).strip() if "flag" in lim.colnames else "="
            text = ("" if flag in ("=", "") else flag + " ") + f"{row['limit_injection']:.2e}"
        print(f"  {row['separation'].to_value(u.mas):.0f} mas: injections {text}, analytic "
              f"{row['limit_analytic']:.2e}")


def _verify_small(path, hdul, limit=16 * 2 ** 20):
    """Check the DATASUM of every extension up to *limit* bytes (the large ones, such as
    a long sequence's phases, are left to the readers that use them)."""
    for h in hdul:
        if "DATASUM" not in h.header:
            continue
        nbytes = abs(h.header.get("BITPIX", 8)) // 8 * int(np.prod(
            [h.header.get(f"NAXIS{i}", 0) for i in range(1, h.header.get("NAXIS", 0) + 1)]))
        if nbytes <= limit and h.verify_datasum() == 0:
            raise KpifsError(f"{path}: checksum mismatch (corrupted?) in {h.name or 'HDU'}")


def _kpfits_headers(path, hdul):
    """Describe a KPFITS file kpifs wrote from its headers; False for other tools' files
    (the full reader checks and describes those)."""
    hdr = hdul[0].header
    names = [h.name for h in hdul]
    need = ("APERTURE", "UV-PLANE", "KER-MAT", "KP-DATA")
    if _layout(hdr, names) != "kpifs" or not all(n in names for n in need):
        return False
    kd = hdul["KP-DATA"].header
    if kd.get("NAXIS") != 3:
        return False
    _verify_small(path, hdul)
    nkp, nwave, nframe = kd["NAXIS1"], kd["NAXIS2"], kd["NAXIS3"]
    wl = _read_wavelengths(hdul, hdr, path)[0].to_value(u.um)
    if len(wl) != nwave:
        raise KpifsError(f"{path}: {len(wl)} wavelengths for {nwave} channels of KP-DATA")
    ps = _read_pixscale(hdr, path)
    inst = str(hdr.get("INSTRUME", "")).strip()
    tel = str(hdr.get("TELESCOP", "")).strip()
    print(f"{path}: kernel-phase data (KPFITS, written by kpifs)")
    if inst or tel:
        print(f"  {inst or '?'} on {tel or '?'}")
    print(f"  {nframe} frame(s) x {nwave} channel(s) x {nkp} kernel phases; "
          f"{wl.min():.4f}-{wl.max():.4f} um; {ps:.2f}")
    ap, uv, km = hdul["APERTURE"].header, hdul["UV-PLANE"].header, hdul["KER-MAT"].header
    n_uv = uv.get("NAXIS2", 0)
    rank = km.get("RANK", n_uv - nkp)
    print(f"  model: <KernelModel {str(ap.get('PUPNAME', 'pupil')).strip()!r}: "
          f"{ap.get('NAXIS2', 0)} sub-apertures, {n_uv} uv points, rank {rank}, {nkp} kernel "
          f"phases>")
    _print_own_kernels(wl, [hdr.get(f"NKPCH{i}") for i in range(1, nwave + 1)])
    cals = [str(hdr[k]) for k in hdr if k.startswith("KPCAL") and k[5:].isdigit()]
    print(f"  calibrated: {'yes, with ' + ', '.join(cals) if hdr.get('CALFLAG') else 'no'}")
    cov = "per channel" if "KP-COV" in names else "none"
    if "KP-JCOV" in names:
        cov += " and joint"
    sig = hdul["KP-SIGM"].header if "KP-SIGM" in names else None
    if (sig is not None and str(sig.get("SIGMFROM", "")).strip() != "KP-COV") or (
            "KP-COV" in names and not hdul["KP-COV"].header.get("COVSHARE", False)
            and nframe > 1):
        cov += "; per-frame errors"
    print(f"  covariance: {cov}")
    pa = (np.ravel(np.asarray(hdul["DETPA"].data, float)) if "DETPA" in names
          and hdul["DETPA"].is_image and hdul["DETPA"].data is not None else None)
    _print_angles(pa, None if pa is None else hdul["DETPA"].header.get("PASRC", "file"))
    return True


def _raw(path, why):
    """What can be said of a cube kpifs cannot read without more information."""
    print(f"{path}: {detect_instrument(path)} cube, incomplete: {why.split(': ', 1)[-1]}")
    with open_fits(path) as hdul:
        for i, h in enumerate(hdul):
            shape = "no data" if h.data is None else " x ".join(str(n) for n in h.data.shape)
            print(f"  HDU {i} {h.name or ''}: {shape}")
        for key in ("OBJECT", "INSTRUME", "TELESCOP", "EXPTIME", "PIXSCALE"):
            if key in hdul[0].header:
                print(f"  {key}: {hdul[0].header[key]}")


def _cube(path, args):
    opts = extract_options(args)
    try:
        cube = read_cube([path], instrument=opts.instrument, dq_bits=opts.dq_bits,
                         wavelengths=parse_wavelengths(opts.wavelengths, source="--wavelengths"),
                         pixscale=opts.pixscale)
    except MissingInformation as exc:
        _raw(path, str(exc))
        return
    with cube:
        wl = cube.wavelengths.to_value(u.um)
        print(f"{cube.name}: {cube.instrument} cube")
        print(f"  frames x channels x y x x: {' x '.join(str(n) for n in cube.shape)}")
        print(f"  wavelengths: {len(wl)} channels, {wl.min():.4f}-{wl.max():.4f} um")
        print(f"  pixel scale: {cube.pixscale:.2f}")
        if cube.angles is not None and np.any(np.isfinite(cube.angles.value)):
            print(f"  frame angles: {np.nanmin(cube.angles.value):.2f}-"
                  f"{np.nanmax(cube.angles.value):.2f} deg")
        if cube.detpa is not None:
            pa = cube.detpa.to_value(u.deg)
            text = ("unknown" if not np.any(np.isfinite(pa)) else
                    f"{np.nanmin(pa):.2f}-{np.nanmax(pa):.2f} deg")
            print(f"  detector position angle: {text} ({cube.detpa_source})")
        if cube.variance is not None:
            print(f"  per-pixel noise: {cube.variance_source} (-> kernel-phase errors)")
        for key in ("OBJECT", "TELESCOP", "EXPTIME", "KPSIMX", "KPSIMY"):
            if key in cube.header:
                print(f"  {key}: {cube.header[key]}")
        km = kernel_model_for(opts, cube.instrument, cube.header)
        pupil = opts.pupil or default_pupil(cube.instrument, cube.header)
        usable = nyquist_usable(km.uv, cube.wavelengths, cube.pixscale)
        lost = (~usable).sum(axis=1)
        print(f"  pupil model {pupil}: {km.pupil.n_sub} sub-apertures, {km.n_uv} uv points, "
              f"{km.n_kp} kernel phases")
        if lost.any():
            for w, n in zip(wl[lost > 0], lost[lost > 0]):
                print(f"  Nyquist: at {w:.4f} um, {n} of {km.n_uv} uv points are beyond the "
                      f"sampling limit")
            print("  extract drops them for every channel (--nyquist drop, the default) or "
                  "refuses (--nyquist raise)")
        else:
            print("  Nyquist: every channel is sampled well enough for every uv point")
        kept = km.subset(usable.all(axis=0)) if lost.any() and usable.all(axis=0).sum() > 1 \
            else km
        frac = aliased_channels(kept, cube.wavelengths, cube.pixscale)
        if frac.any():
            print("  aliasing: " + ", ".join(f"{w:.4f} um {f:.0%}" for w, f in
                                             zip(wl[frac > 0], frac[frac > 0]))
                  + " of the uv points kept see the sampling's copies; detect flags those "
                  "channels (--aliased exclude leaves them out)")
        files = cube.source[0] if len(cube.source) == 1 else f"{cube.source[0]} ..."
        print(f"  next: kpifs extract {files} {' '.join(_given(args, opts, pupil))} "
              f"[--calibrator CALIBRATOR_CUBE...] -o kp.fits")


def _given(args, opts, pupil):
    """The reading options this call was given and every model option, as the next
    command should repeat them (the model's options all shape the kernel phases)."""
    given = [f"--{opt.replace('_', '-')} {getattr(args, opt)}" for opt in (
        "instrument", "wavelengths", "pixscale", "dq_bits")
        if getattr(args, opt, None) not in (None, "auto")]
    given.append(f"--pupil {pupil}")
    for name in _MODEL_OPTIONS:
        value = getattr(args, name)
        flag = f"--{name.replace('_', '-')}"
        if name == "grey" and value is False:
            given.append("--binary")
        elif isinstance(value, bool):
            given += [flag] if value else []
        elif value is not None:
            given.append(f"{flag} {value}")
    return given
