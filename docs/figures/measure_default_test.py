"""Which test should be the default: false alarms and depth of ``B`` and ``S``.

On CHARIS simulations written in the CHARIS pipeline's layout (``kpifs simulate
--preset charis --layout charis --shape 64 --frames 20 --drift 20nm
--static-diff 15nm``: 22 channels, one calibrator whose static aberrations
differ from the target's by 15 nm rms, 20 nm of aberrations drifting from frame
to frame), reduced the way ``kpifs extract TARGET --calibrator CAL`` and
``kpifs detect --test T`` reduce them (`kpifs.workflow`, the same options):

``false-alarms``
    No companion. Each seed's calibrated data are searched with ``B`` and with
    ``S`` at P_FA 0.05; a data set has a false alarm at level ``a`` when its
    strongest candidate's global P_FA is below ``a`` (0.05 and 0.01 are
    counted).
``companion``
    A companion of mean contrast *contrast* (the preset's spectrum, brighter in
    the blue) at 150 mas: whether each test finds it at P_FA 1e-3, within
    ``lambda_min / D`` of the truth.

Run from the project root, e.g.::

    python docs/figures/measure_default_test.py false-alarms --seeds 1-40
    python docs/figures/measure_default_test.py companion --seeds 1-20

Each seed costs about 15 s of CPU (2026-11, one core). Results go to a JSON
file (``--out``) and a summary is printed.
"""
import argparse
import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import astropy.units as u

TESTS = ("B", "S")


def seeds(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def calibrated(folder, seed, contrast):
    """The calibrated kernel phases of one simulated CHARIS sequence."""
    from kpifs.io import write_observation
    from kpifs.simulation.simulate import simulate_scene
    from kpifs.workflow import (ExtractOptions, calibrate_observation, calibrator_options,
                                extract_observation)
    extra = {} if contrast is None else {
        "contrasts": contrast * np.linspace(1.4, 0.6, 22)}
    obs = simulate_scene("charis", n_frames=20, seed=seed, shape=(64, 64),
                         drift_rms=20 * u.nm, static_diff_rms=15 * u.nm,
                         **({"contrasts": 0.0} if contrast is None else extra))
    files = write_observation(obs, folder, layout="charis", overwrite=True)
    options = ExtractOptions()
    target = extract_observation(files["target"], options)
    cal = extract_observation(files["calibrator"], calibrator_options(options),
                              model=target.kernel_model)
    return calibrate_observation(target, [cal], options), obs


def search(kpd, test, pfa):
    """``kpifs detect --test TEST --pfa PFA`` with its defaults, without the limits."""
    from kpifs.detect import detect
    return detect(kpd, test=test, pfa=pfa, limits=False)


def false_alarms(args, tmp):
    out = {}
    for s in args.seeds:
        kpd, _ = calibrated(tmp / f"s{s}", s, None)
        out[s] = {}
        for test in TESTS:
            res = search(kpd, test, 0.05)
            best = float(np.min(res.candidates["pfa_global"])) if len(res.candidates) else 1.0
            out[s][test] = {"best_pfa": best,
                            "noise_scale": float(res.meta.get("noise_scale", np.nan))}
        print(f"seed {s}: " + ", ".join(
            f"{t} best P_FA {out[s][t]['best_pfa']:.3g} (noise scale "
            f"{out[s][t]['noise_scale']:.2f})" for t in TESTS), flush=True)
    for test in TESTS:
        for level in (0.05, 0.01):
            n = sum(v[test]["best_pfa"] < level for v in out.values())
            print(f"{test}: {n} of {len(out)} companion-free sets with a candidate at "
                  f"P_FA {level}")
    return out


def companion(args, tmp):
    out = {}
    for s in args.seeds:
        kpd, obs = calibrated(tmp / f"c{s}", s, args.contrast)
        truth = obs.params.companion_offset.to_value(u.mas)
        radius = float(np.min(obs.wavelengths.to_value(u.m)) / 7.92 * 206264806.2)
        out[s] = {}
        for test in TESTS:
            res = search(kpd, test, 1e-3)
            found = False
            for row in res.candidates:
                x, y = row["fit_x"].to_value(u.mas), row["fit_y"].to_value(u.mas)
                found |= bool(np.hypot(x - truth[0], y - truth[1]) < radius)
            out[s][test] = {"found": found, "n_candidates": len(res.candidates)}
        print(f"seed {s}: " + ", ".join(
            f"{t} {'found' if out[s][t]['found'] else 'missed'} "
            f"({out[s][t]['n_candidates']} candidate(s))" for t in TESTS), flush=True)
    for test in TESTS:
        n = sum(v[test]["found"] for v in out.values())
        print(f"{test}: found in {n} of {len(out)} sets (mean contrast {args.contrast:g})")
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("experiment", choices=("false-alarms", "companion"))
    p.add_argument("--seeds", type=seeds, default=seeds("1-20"))
    p.add_argument("--contrast", type=float, default=6.3e-4)
    p.add_argument("--out", default="default_test.json")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="kpifs-default-") as tmp, \
            warnings.catch_warnings():
        warnings.simplefilter("ignore")     # 20 frames: kpifs says the covariance is coarse
        run = false_alarms if args.experiment == "false-alarms" else companion
        out = run(args, Path(tmp))
    Path(args.out).write_text(json.dumps({"experiment": args.experiment, "seeds": args.seeds,
                                          "results": out}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
