"""Field rotation's false alarms and limits on CHARIS simulations (issue 29).

Three experiments, each on ``kpifs simulate --preset charis --layout charis``
sequences (22 channels), run the way a user runs them (``kpifs extract``,
``kpifs detect``), one process at a time:

``false-alarms``
    Angular-differential calibration with no calibrator: 40 frames over 60 deg
    of rotation, 15 nm of static aberration (``--static``, the same on every
    frame: fixed on the detector), no companion. ``kpifs extract TARGET
    --angular-differential`` then ``kpifs detect --pfa PFA``; counts the
    sequences with a candidate, and records the default test's limits
    (median by separation).
``injection``
    Injection-recovery on such sequences: companions of a flat spectrum made of
    each frame's own PSF (`kpifs.inject.inject_companion`, fixed on the sky) at
    *angles* position angles and *factors* times the stated limit (the
    companion-free sequence's default-test limit at those positions, P_FA
    PFA, P_D 0.5) at each separation, the target re-extracted, the
    angular-differential product made and searched at PFA; a companion is
    found when a candidate lies within ``lambda_min / D`` of it. The 50 %
    level is interpolated in log contrast and set beside the stated limit.
``calibrator``
    One calibrator, a 15 nm static difference between target and calibrator
    (``--static-diff``), 20 frames over 40 deg, no companion: ``kpifs detect
    --pfa PFA`` of the calibrated product with the angular-differential term
    (``kpifs extract ... --angular-differential``) and without it (the block
    search of the mean and the blocks, ``--blocks rotation``); counts the sets
    with a candidate and the ratio of the two default-test limits by separation.

``smearing``
    One calibrator, 20 frames, no static difference: the default test's limits
    of the sequence with 40 deg of rotation over those without (median by
    separation), the limit at 150 mas without rotation, then a companion at 1.3 times
    it (the preset's, 150 mas) in the same sequence without rotation and with
    40 deg of it: its global P_FA, the fit's offset from the truth (mas, deg)
    and its median contrast over the truth, ``kpifs detect`` with its defaults.

Seeds are given as ``1-20`` or ``1,5,7``. Results go to a JSON file (``--out``)
and a summary is printed. Run e.g.::

    python docs/figures/measure_rotation.py false-alarms --seeds 1-20
    python docs/figures/measure_rotation.py injection --seeds 1,2
    python docs/figures/measure_rotation.py calibrator --seeds 1-20
"""
import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import astropy.units as u

SEPARATIONS = (100, 150, 200, 250, 300)
KPIFS = [sys.executable, "-m", "kpifs"]


def seeds(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def run(*args):
    subprocess.run(KPIFS + [str(a) for a in args] + ["-q"], check=True)


def simulate(folder, seed, *, frames, rotation, calibrator=False, contrast=0.0, static=True):
    extra = [] if not static else ["--static-diff", "15nm"] if calibrator else \
        ["--static", "15nm"]
    run("simulate", "--preset", "charis", "--layout", "charis", "--frames", frames,
        "--rotation", f"{rotation}deg", "--contrasts", contrast, "--seed", seed, "-o", folder,
        "--overwrite", *extra)
    return (sorted(map(str, (folder / "target").glob("*.fits"))),
            sorted(map(str, (folder / "calibrator").glob("*.fits"))))


def summary(path, pfa):
    """Candidates at *pfa* and the default test's limit curve (median) of a detection."""
    from kpifs.data import DetectionResult
    return summary_of(DetectionResult.read(path), pfa)


def summary_of(res, pfa=1.0):
    cands = res.candidates
    found = [] if not len(cands) else [
        {"pfa": float(r["pfa_global"]), "dra": float(r["fit_dra"].to_value(u.mas)),
         "ddec": float(r["fit_ddec"].to_value(u.mas))} for r in cands
        if r["pfa_global"] < pfa]
    curve = res.curves
    sep = curve["separation"].to_value(u.mas)
    med = np.asarray(curve[f"{res.test}_median"], float)
    return {"candidates": found, "test": res.test,
            "limits": {s: float(np.interp(s, sep, med)) for s in SEPARATIONS},
            "noise_scale": float(res.meta.get("noise_scale", np.nan)),
            "mean_scale": (res.meta.get("blocks") or {}).get("mean_scale")}


def false_alarms(args, tmp):
    out = {}
    for s in args.seeds:
        folder = tmp / f"adi{s}"
        target, _ = simulate(folder, s, frames=40, rotation=60)
        run("extract", *target, "--angular-differential", "-o", tmp / "adi.fits", "--overwrite")
        shutil.rmtree(folder)
        run("detect", tmp / "adi.fits", "--pfa", args.pfa, "-o", tmp / "det.fits", "--overwrite")
        out[s] = summary(tmp / "det.fits", args.pfa)
        print(f"seed {s}: {len(out[s]['candidates'])} candidate(s), limits "
              f"{[round(v, 5) for v in out[s]['limits'].values()]}", flush=True)
    n = sum(bool(v["candidates"]) for v in out.values())
    print(f"{n} of {len(out)} companion-free sequences give a candidate at P_FA {args.pfa}")
    return out


def calibrator(args, tmp):
    out = {}
    for s in args.seeds:
        folder = tmp / f"cal{s}"
        target, cal = simulate(folder, s, frames=20, rotation=40, calibrator=True)
        res = {}
        for name, extra in (("adi", ["--angular-differential"]), ("blocks", [])):
            run("extract", *target, "--calibrator", *cal, *extra, "-o", tmp / "c.fits",
                "--overwrite")
            run("detect", tmp / "c.fits", "--pfa", args.pfa, "-o", tmp / "det.fits",
                "--overwrite")
            res[name] = summary(tmp / "det.fits", args.pfa)
        shutil.rmtree(folder)
        out[s] = res
        ratio = [res["adi"]["limits"][k] / res["blocks"]["limits"][k] for k in SEPARATIONS]
        print(f"seed {s}: candidates ADI {len(res['adi']['candidates'])}, blocks "
              f"{len(res['blocks']['candidates'])}; limits ADI / blocks "
              f"{np.round(ratio, 3).tolist()}", flush=True)
    for name in ("adi", "blocks"):
        n = sum(bool(v[name]["candidates"]) for v in out.values())
        print(f"{name}: {n} of {len(out)} sets give a candidate at P_FA {args.pfa}")
    ratio = np.array([[v["adi"]["limits"][k] / v["blocks"]["limits"][k] for k in SEPARATIONS]
                      for v in out.values()])
    print("limits with / without the term, median by separation "
          f"{dict(zip(SEPARATIONS, np.round(np.median(ratio, axis=0), 3).tolist()))}")
    return out


def smearing(args, tmp):
    from kpifs.data import DetectionResult
    from kpifs.detect.sky import detector_to_sky
    out = {}
    # the preset's companion: (120, 90) mas on the detector at the first frame (150 mas)
    truth = np.array(detector_to_sky(120.0, 90.0, 113.0))

    def reduce(rotation, contrast):
        target, cal = simulate(tmp / "sim", s, frames=20, rotation=rotation, static=False,
                               contrast=contrast)
        run("extract", *target, "--calibrator", *cal, "-o", tmp / "c.fits", "--overwrite")
        run("detect", tmp / "c.fits", "-o", tmp / "det.fits", "--overwrite")
        return DetectionResult.read(tmp / "det.fits")

    for s in args.seeds:
        free = summary_of(reduce(0, 0.0))
        turning = summary_of(reduce(40, 0.0))
        c = 1.3 * free["limits"][150]
        # the companion-free limits with rotation over those without (median by separation)
        row = {"limit_150": free["limits"][150], "contrast": c,
               "limit_ratio": {k: turning["limits"][k] / free["limits"][k]
                               for k in SEPARATIONS}}
        for name, rot in (("fixed", 0), ("rotating", 40)):
            res = reduce(rot, c)
            tab = res.candidates
            if not len(tab):
                row[name] = None
                continue
            d = np.hypot(tab["fit_dra"].to_value(u.mas) - truth[0],
                         tab["fit_ddec"].to_value(u.mas) - truth[1])
            r = tab[int(np.argmin(d))]
            pa = np.degrees(np.arctan2(r["fit_dra"].to_value(u.mas),
                                       r["fit_ddec"].to_value(u.mas)))
            pa0 = np.degrees(np.arctan2(*truth))
            fc, fe = np.asarray(r["fit_contrast"], float), np.asarray(r["fit_contrast_err"], float)
            row[name] = {"pfa": float(r["pfa_global"]), "offset_mas": float(d.min()),
                         "pa_err": float((pa - pa0 + 180) % 360 - 180),
                         "contrast_ratio": float(np.median(fc) / c),
                         # the median's own error (channels' errors, as independent: a
                         # lower bound) and the channels' ratios and errors over the truth
                         "contrast_ratio_err": float(1.2533 * np.sqrt(np.mean(fe ** 2))
                                                     / np.sqrt(len(fe)) / c),
                         "channel_ratio": np.round(fc / c, 3).tolist(),
                         "channel_err": np.round(fe / c, 3).tolist(),
                         "noise_scale": float(res.meta.get("noise_scale", np.nan))}
        out[s] = row
        finds = "; ".join(
            f"{k}: " + ("not found" if row[k] is None else
                        f"P_FA {row[k]['pfa']:.1e}, {row[k]['offset_mas']:.1f} mas, "
                        f"{row[k]['pa_err']:+.2f} deg, contrast x {row[k]['contrast_ratio']:.2f} "
                        f"+- {row[k]['contrast_ratio_err']:.2f}, "
                        f"noise scale {row[k]['noise_scale']:.2f}")
            for k in ("fixed", "rotating"))
        print(f"seed {s}: limit {row['limit_150']:.3g}, with / without rotation "
              f"{[round(v, 3) for v in row['limit_ratio'].values()]}; {finds}", flush=True)
    ratio = np.array([list(v["limit_ratio"].values()) for v in out.values()])
    print("limits with / without rotation, median by separation "
          f"{dict(zip(SEPARATIONS, np.round(np.median(ratio, axis=0), 3).tolist()))}")
    for k in ("fixed", "rotating"):
        pf = np.array([np.nan if v[k] is None else v[k]["pfa"] for v in out.values()])
        print(f"{k}: P_FA below 1e-6 in {np.sum(pf < 1e-6)} of {len(pf)} seeds; log10 P_FA "
              f"median {np.nanmedian(np.log10(pf)):.1f}, quartiles "
              f"{np.round(np.nanpercentile(np.log10(pf), [25, 75]), 1).tolist()}")
    return out


def _search(kpd, pfa, *, limits, seed=0):
    from kpifs.calibration.adi import angular_differential
    from kpifs.detect import detect
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return detect(angular_differential(kpd), pfa=pfa, limits=limits, seed=seed,
                      n_draws=5000 if limits else 2000, max_candidates=5)


def injection(args, tmp):
    from kpifs.extraction.extract import extract_kernel_phases
    from kpifs.inject import _detected, _limit, inject_companion
    from kpifs.io import read_cube
    from kpifs.workflow import ExtractOptions, extract_observation
    out = {}
    for s in args.seeds:
        folder = tmp / f"inj{s}"
        target, _ = simulate(folder, s, frames=40, rotation=60)
        kpd0 = extract_observation(target, ExtractOptions())
        with read_cube(target) as cube:
            data, mask = np.array(cube.data, float), cube.mask
            wl, ps = cube.wavelengths, cube.pixscale
        shutil.rmtree(folder)
        res0 = _search(kpd0, args.pfa, limits=True)
        g = res0.grid
        km = kpd0.kernel_model
        radius = wl.to_value(u.m).min() / float(np.max(np.hypot(*km.uv.to_value(u.m).T))) \
            / (np.pi / 180 / 3600e3)
        start = np.random.default_rng(s).uniform(0, 360)
        per = {}
        for sep in args.separations:
            pas = start + np.arange(args.angles) * 360 / args.angles
            pos = [(sep * np.sin(np.deg2rad(a)), sep * np.cos(np.deg2rad(a))) for a in pas]
            # the stated limit there: the limit map at the nearest grid positions
            lim = float(np.median([res0.limit[np.argmin(np.abs(g.y - dd)),
                                              np.argmin(np.abs(g.x - da))] for da, dd in pos]))
            rows = []
            for f in args.factors:
                found = 0
                for k, (da, dd) in enumerate(pos):
                    cube = inject_companion(data, position=[da, dd] * u.mas, contrast=f * lim,
                                            pixscale=ps, frame="sky", detpa=kpd0.detpa)
                    kpd = extract_kernel_phases(cube, km, wavelengths=wl, pixscale=ps,
                                                window=kpd0.window, mask=mask,
                                                detpa=kpd0.detpa, keep_phases=False,
                                                source=f"seed {s}")
                    kpd.meta.update(kpd0.meta)
                    res = _search(kpd, args.pfa, limits=False, seed=k)
                    tab = res.candidates
                    if len(tab):
                        tab["fit_x"], tab["fit_y"] = tab["fit_dra"], tab["fit_ddec"]
                    found += _detected(res, da, dd, radius)
                rows.append([f * lim, found / args.angles])
                print(f"seed {s}, {sep} mas: {f:.2f} x limit {lim:.3g}: {found}/{args.angles}",
                      flush=True)
            per[sep] = {"limit": lim, "steps": rows}
        out[s] = per
    for sep in args.separations:
        # all seeds' trials pooled by factor of each seed's own limit
        steps = np.array([v[sep]["steps"] for v in out.values()])          # (seed, f, 2)
        lims = np.array([v[sep]["limit"] for v in out.values()])
        frac = steps[:, :, 1].mean(axis=0)
        c50, flag = _limit(np.asarray(args.factors), frac, 0.5)
        print(f"{sep} mas: found {np.round(frac, 2).tolist()} at {args.factors} x the limit; "
              f"50 % at {flag}{c50:.2f} x the stated limit (limits {np.round(lims, 5).tolist()})")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", choices=("false-alarms", "injection", "calibrator",
                                           "smearing"))
    ap.add_argument("--seeds", type=seeds, default=seeds("1-20"))
    ap.add_argument("--pfa", type=float, default=1e-2)
    ap.add_argument("--separations", type=lambda t: [float(v) for v in t.split(",")],
                    default=[150.0, 300.0])
    ap.add_argument("--factors", type=lambda t: [float(v) for v in t.split(",")],
                    default=[0.5, 0.71, 1.0, 1.41, 2.0])
    ap.add_argument("--angles", type=int, default=4)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="kpifs-rotation-"))
    try:
        out = {"false-alarms": false_alarms, "calibrator": calibrator,
               "injection": injection, "smearing": smearing}[args.experiment](args, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if args.out:
        Path(args.out).write_text(json.dumps({"args": {k: v for k, v in vars(args).items()},
                                              "results": out}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
