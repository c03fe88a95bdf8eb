"""Regression corpus: every product kpifs writes for a fixed set of cases, digested.

Used to check that a change meant to keep the numbers (a refactor) keeps them:

    python tools/regression_corpus.py make before/          # on the old code
    python tools/regression_corpus.py make after/           # on the new code
    python tools/regression_corpus.py compare before/ after/

``make`` runs each case through the command line (``kpifs.cli.main``, in this
process), from simulated files written in each instrument's own layout with
fixed seeds, and writes, per case, ``digest.npz`` (every array of every HDU of
every FITS product, as float64 or as text) and ``cards.json`` (every header
card but the volatile ones: dates, checksums, version, the run's folder).
``compare`` reports every array that differs by more than ``--rtol`` (1e-9)
relative to its own largest value and every card whose value changed, and
exits 1 when anything differs. ``--only`` runs some cases.

Cases: CHARIS and SPHERE-IFS with a calibrator (tests B and auto), a JWST
NIRCam filter pair, GPI, an OIFITS written by kpifs and read back, the
angular-differential mode (CHARIS, no calibrator), the spectral-differential mode
and ASDI (CHARIS with a typical static aberration, no calibrator), uncalibrated
single-channel data, the README's command-line examples, and the real files
of ../shared/data/real where that folder exists (PHARO halves, alpha Oph,
the NIRISS AMI OIFITS).
"""
import argparse
import contextlib
import io
import json
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
from astropy.io import fits

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real"
VOLATILE = {"DATE", "CHECKSUM", "DATASUM", "KPIFSVER", "VERSION", "CREATOR", "DATE-HDR",
            "ORIGIN", "HISTORY", "COMMENT", "KPHASH", "KPINHASH"}
WORK = Path(tempfile.gettempdir()) / "kpifs-regression-corpus"   # one folder: same paths


def kpifs(*argv):
    """Run one kpifs command in this process; raise if it fails."""
    from kpifs.cli import main
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        rc = main([str(a) for a in argv])
    if rc != 0:
        raise RuntimeError(f"kpifs {' '.join(map(str, argv))} -> {rc}\n{out.getvalue()}")
    return out.getvalue()


def _sim(d, preset, layout, frames, seed, *extra):
    kpifs("simulate", "--preset", preset, "--layout", layout, "--frames", frames,
          "--seed", seed, "-q", "-o", d / "sim", *extra)
    return d / "sim"


def _files(folder, pattern="*.fits"):
    return sorted(str(p) for p in Path(folder).glob(pattern))


def case_charis(d):
    s = _sim(d, "charis", "charis", 8, 11)
    kpifs("extract", *_files(s / "target"), "--calibrator", *_files(s / "calibrator"),
          "-q", "-o", d / "calibrated_kp.fits")
    for test in ("B", "auto"):
        kpifs("detect", d / "calibrated_kp.fits", "--test", test, "--draws", 1000, "-q",
              "-o", d / f"detection_{test}.fits")


def case_sphere(d):
    s = _sim(d, "sphere", "sphere", 8, 12)
    kpifs("extract", s / "target" / "science_cube.fits", "--instrument", "sphere",
          "--wavelengths", s / "target" / "wavelength.fits", "--calibrator",
          s / "calibrator" / "science_cube.fits", "-q", "-o", d / "calibrated_kp.fits")
    kpifs("detect", d / "calibrated_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_jwst_pair(d):
    import astropy.units as u
    from kpifs.simulation.simulate import simulate_scene
    from kpifs.io.layouts import write_observation
    target, cal = [], []
    for wl, ps, seed, con in ((1.5106, 31.0, 1, 0.076), (4.8213, 63.0, 2, 0.19)):
        obs = simulate_scene("nircam", wavelengths=[wl] * u.um, pixscale=ps * u.mas,
                             contrasts=[con], n_frames=8, seed=seed, detpa=[250.0])
        f = write_observation(obs, d / f"{ps:.0f}", layout="jwst")
        target += [str(x) for x in f["target"]]
        cal += [str(x) for x in f["calibrator"]]
    kpifs("extract", *target, "--calibrator", *cal, "-q", "-o", d / "calibrated_kp.fits")
    kpifs("detect", d / "calibrated_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_gpi(d):
    s = _sim(d, "gpi", "gpi", 6, 13)
    kpifs("extract", *_files(s / "target"), "--calibrator", *_files(s / "calibrator"),
          "-q", "-o", d / "calibrated_kp.fits")
    kpifs("detect", d / "calibrated_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_oifits(d):
    """A SPHERE SAM sequence behind the IFS: closure phases written as OIFITS2, read back."""
    s = _sim(d, "sphere-sam", "plain", 8, 14)
    kpifs("extract", s / "target.fits", "--pupil", "sphere_sam7", "--calibrator",
          s / "calibrator.fits", "-q", "-o", d / "calibrated.oifits")
    kpifs("detect", d / "calibrated.oifits", "--draws", 1000, "-q", "-o",
          d / "detection_oifits.fits")


def case_adk(d):
    s = _sim(d, "charis", "charis", 12, 15, "--rotation", "40deg")
    kpifs("extract", *_files(s / "target"), "--angular-differential", "-q",
          "-o", d / "adk_kp.fits")
    kpifs("detect", d / "adk_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_sdk(d):
    """Spectral-differential kernel phases: CHARIS with a typical static aberration and no
    calibrator, the companion of the preset."""
    s = _sim(d, "charis", "plain", 12, 17, "--typical-static", "--shape", 80)
    kpifs("extract", s / "target.fits", "--spectral-differential", "-q",
          "-o", d / "sdk_kp.fits")
    kpifs("detect", d / "sdk_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_asdi(d):
    """Spectral- and angular-differential together (ASDI), no calibrator, 40 deg."""
    s = _sim(d, "charis", "plain", 12, 18, "--typical-static", "--shape", 80,
             "--rotation", "40deg")
    kpifs("extract", s / "target.fits", "--spectral-differential", "--angular-differential",
          "-q", "-o", d / "asdi_kp.fits")
    kpifs("detect", d / "asdi_kp.fits", "--draws", 1000, "-q", "-o", d / "detection.fits")


def case_single_channel(d):
    import astropy.units as u
    from kpifs.simulation.simulate import simulate_scene
    from kpifs.io.layouts import write_observation
    obs = simulate_scene("paper", wavelengths=[1.6] * u.um, contrasts=[0.02], n_frames=12,
                         seed=16)
    write_observation(obs, d / "sim", layout="plain")
    kpifs("extract", d / "sim" / "target.fits", "-q", "-o", d / "target_kp.fits")
    kpifs("detect", d / "target_kp.fits", "--allow-uncalibrated", "--draws", 1000, "-q",
          "-o", d / "detection.fits")


def case_readme(d):
    """The README's command-line section, with fewer frames."""
    kpifs("kernel", "--pupil", "subaru", "--step", "0.38m", "-q", "-o", d / "subaru_model.fits")
    kpifs("simulate", "--preset", "paper", "--frames", 40, "-q", "-o", d / "sim")
    kpifs("extract", d / "sim" / "target.fits", "--wavelengths", "1.52um,1.60um,1.68um",
          "--pixscale", "10.42mas", "--pupil", "subaru", "-q", "-o", d / "target_kp.fits")
    kpifs("extract", d / "sim" / "calibrator.fits", "-q", "-o", d / "calibrator_kp.fits")
    kpifs("detect", d / "target_kp.fits", "--calibrator", d / "calibrator_kp.fits",
          "--pfa", "1e-3", "-q", "-o", d / "detection.fits")
    kpifs("inject", d / "sim" / "target.fits", "--calibrator", d / "sim" / "calibrator.fits",
          "--curve", "--separations", "60,120mas", "-q", "-o", d / "curve.fits")
    kpifs("roc", "--preset", "paper", "--frames", 200, "-q", "-o", d / "roc")


def case_real(d):
    if not REAL.is_dir():
        return "skipped: no ../shared/data/real"
    d0 = fits.getdata(REAL / "pharo_ca2_cube_epsHer.fits")
    fits.writeto(d / "h1.fits", d0[:50])
    fits.writeto(d / "h2.fits", d0[50:])
    opts = ["--instrument", "generic", "--wavelengths", "2.145um", "--pixscale", "25mas",
            "--pupil", "pharo", "--step", "0.16m", "-q"]
    for name, src in (("h1", d / "h1.fits"), ("h2", d / "h2.fits"),
                      ("a", REAL / "pharo_tgt_cube_alphaOph.fits"),
                      ("e", REAL / "pharo_ca2_cube_epsHer.fits")):
        kpifs("extract", src, *opts, "-o", d / f"{name}kp.fits")
    kpifs("detect", d / "h1kp.fits", "--calibrator", d / "h2kp.fits", "--pfa", "1e-3", "-q",
          "-o", d / "null.fits")
    kpifs("detect", d / "akp.fits", "--calibrator", d / "ekp.fits", "-q", "-o",
          d / "alphaoph.fits")
    kpifs("detect", d / "akp.fits", "--allow-uncalibrated", "-q", "-o", d / "alphaoph_alone.fits")
    try:
        kpifs("detect", REAL / "jwst_niriss_ami_nuhor_f480m.oifits", "-q", "-o",
              d / "nuhor.fits")
    except RuntimeError as exc:            # refused today (issue 35 item 2): recorded
        (d / "nuhor_refused.txt").write_text(str(exc).splitlines()[-1] + "\n")


CASES = {name[5:]: f for name, f in globals().items() if name.startswith("case_")}


def _hdu_arrays(hdu):
    if hdu.data is None:
        return {}
    if isinstance(hdu, (fits.BinTableHDU, fits.TableHDU)):
        return {c: np.asarray(hdu.data[c]) for c in hdu.columns.names}
    return {"data": np.asarray(hdu.data)}


def _card_value(value, root):
    if isinstance(value, str):       # inputs' digests change with their DATE cards
        return re.sub(r"sha256:[0-9a-f]+", "sha256:-", value.replace(str(root), "<run>"))
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    return float(value) if isinstance(value, (int, float, np.number)) else str(value)


def digest(folder, root):
    """Every FITS product under ``folder`` (inputs under ``sim`` left out)."""
    arrays, cards = {}, {}
    for path in sorted(Path(folder).rglob("*")):
        rel = path.relative_to(folder).as_posix()
        if not path.is_file() or rel.startswith(("sim/", "in/")) or path.suffix == ".png":
            continue
        if path.suffix == ".txt":
            cards[rel] = {"text": path.read_text().replace(str(root), "<run>")}
            continue
        try:
            hdul = fits.open(path)
        except OSError:
            continue
        with hdul:
            for i, hdu in enumerate(hdul):
                key = f"{rel}[{i}:{hdu.name}]"
                cards[key] = {k: _card_value(v, root) for k, v in hdu.header.items()
                              if k not in VOLATILE}
                for col, arr in _hdu_arrays(hdu).items():
                    arrays[f"{key}:{col}"] = (arr.astype(np.float64) if arr.dtype.kind in "biuf"
                                              else arr.astype(str))
    return arrays, cards


def make(outdir, only):
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    for name in only or CASES:
        work = WORK / name
        shutil.rmtree(WORK, ignore_errors=True)
        work.mkdir(parents=True)
        try:
            note = CASES[name](work)
            arrays, cards = digest(work, WORK)
        finally:
            shutil.rmtree(WORK, ignore_errors=True)
        dest = outdir / name
        shutil.rmtree(dest, ignore_errors=True)
        dest.mkdir()
        np.savez_compressed(dest / "digest.npz", **arrays)
        (dest / "cards.json").write_text(json.dumps(cards, indent=1, sort_keys=True))
        extra = f" ({note})" if note else ""
        print(f"{name}: {len(arrays)} arrays, {len(cards)} headers{extra}")


def _compare_arrays(a, b, rtol):
    out = []
    for key in sorted(set(a) | set(b)):
        if key not in a or key not in b:
            out.append(f"  {key}: only in {'after' if key in b else 'before'}")
            continue
        x, y = a[key], b[key]
        if x.shape != y.shape:
            out.append(f"  {key}: shape {x.shape} -> {y.shape}")
        elif x.dtype.kind == "U" or y.dtype.kind == "U":
            if not np.array_equal(x, y):
                out.append(f"  {key}: text differs")
        else:
            scale = np.nanmax(np.abs(x)) if x.size and np.isfinite(x).any() else 0.0
            same_nan = np.array_equal(np.isnan(x), np.isnan(y))
            finite = np.isfinite(x) & np.isfinite(y)
            diff = np.abs(x - y)[finite].max() if finite.any() and same_nan else 0.0
            if not same_nan or diff > rtol * max(scale, 1e-300):
                out.append(f"  {key}: max |diff| {diff:.3g} (scale {scale:.3g})"
                           + ("" if same_nan else ", NaNs differ"))
    return out


def _compare_cards(a, b, rtol):
    out = []
    for hdu in sorted(set(a) | set(b)):
        ca, cb = a.get(hdu, {}), b.get(hdu, {})
        for k in sorted(set(ca) | set(cb)):
            va, vb = ca.get(k), cb.get(k)
            if isinstance(va, float) and isinstance(vb, float):
                if abs(va - vb) <= rtol * max(abs(va), abs(vb)) or va == vb:
                    continue
            elif va == vb:
                continue
            out.append(f"  {hdu} {k}: {va!r} -> {vb!r}")
    return out


def compare(before, after, rtol, only):
    bad = 0
    for name in only or sorted(p.name for p in Path(before).iterdir() if p.is_dir()):
        try:
            a = dict(np.load(Path(before) / name / "digest.npz"))
            b = dict(np.load(Path(after) / name / "digest.npz"))
            ca = json.loads((Path(before) / name / "cards.json").read_text())
            cb = json.loads((Path(after) / name / "cards.json").read_text())
        except OSError as exc:
            print(f"{name}: cannot compare ({exc})")
            bad += 1
            continue
        diffs = _compare_arrays(a, b, rtol) + _compare_cards(ca, cb, rtol)
        print(f"{name}: {'identical' if not diffs else f'{len(diffs)} difference(s)'}")
        print("\n".join(diffs[:60]))
        bad += bool(diffs)
    return 1 if bad else 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="verb", required=True)
    m = sub.add_parser("make")
    m.add_argument("outdir")
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    c.add_argument("--rtol", type=float, default=1e-9)
    for q in (m, c):
        q.add_argument("--only", nargs="+", choices=sorted(CASES))
    args = p.parse_args(argv)
    if args.verb == "make":
        make(args.outdir, args.only)
        return 0
    return compare(args.before, args.after, args.rtol, args.only)


if __name__ == "__main__":
    sys.exit(main())
