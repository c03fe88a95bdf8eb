"""ASDI (issue 39): spectral- and angular-differential kernel phases together, against
angular-differential kernel phases alone (ADK), with no calibrator.

CHARIS simulations (``simulate_scene('charis', shape=(80, 80), n_frames=20,
**TYPICAL_STATIC)``: 22 channels, 50 nm of static aberration at low order plus 15 nm of
the target's own, 10 nm drifting) over 40 deg of field rotation (20 frames evenly
from 100 to 140 deg), extracted as ``kpifs extract`` does and searched at P_FA 1e-2
with 1000 draws:

``null``
    No companion. Per seed, ADK (``--angular-differential``) and ASDI (with
    ``--spectral-differential`` too, static basis): candidates, the energy test's
    P_FA, the median limits at 150 and 250 mas and over 200-300 mas (the 80-pixel
    images' pupil grid stops at 299 mas).
``companion``
    A companion (flat spectrum, fixed on the sky) at *factors* times the ASDI limit
    that ``null`` measured on the same seed at 150 and 250 mas, at 4 position angles:
    found within 5 mas, and its fitted contrast (the simulator draws other noise once a
    companion is added: each case is its own noise realisation).
``inject``
    The same companions as the model's kernel phases added to the companion-free
    frames of ``null``'s seeds (each frame at its own angle): the same noise.

Run from the project root::

    python docs/figures/measure_asdi.py null --seeds 1-6 --out /tmp/asdi_null.json
    python docs/figures/measure_asdi.py companion --seeds 1-2 --limits /tmp/asdi_null.json
"""
import argparse
import copy
import json
import warnings

import numpy as np
from astropy import units as u

from kpifs.calibration.adi import angular_differential
from kpifs.calibration.spectral_diff import spectral_differential
from kpifs.detect import detect
from kpifs.detect.sky import sky_to_detector
from kpifs.io.layouts import write_observation
from kpifs.simulation.aberrations import static_residual_rows
from kpifs.simulation.simulate import TYPICAL_STATIC, simulate_scene
from kpifs.workflow import ExtractOptions, extract_observation

PFA, DRAWS = 1e-2, 1000
ANGLES = np.linspace(100.0, 140.0, 20)
_ROWS = {}


def _seeds(text):
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def _target(seed, tmp, contrast=0.0, sky=(0.0, 150.0)):
    obs = simulate_scene("charis", seed=seed, shape=(80, 80), n_frames=20, contrasts=contrast,
                         detpa=ANGLES, sky_offset=list(sky) * u.mas, **TYPICAL_STATIC)
    files = write_observation(obs, f"{tmp}/asdi{seed}", overwrite=True)
    return extract_observation(files["target"], ExtractOptions())


def _products(tkp):
    key = (tkp.n_wave, tkp.n_kp)
    if key not in _ROWS:
        _ROWS[key] = static_residual_rows(tkp.kernel_model, tkp.wavelengths, tkp.pixscale,
                                          window=tkp.window)
    sdk = spectral_differential(tkp, basis="static", static_rows=_ROWS[key])
    return {"adk": angular_differential(tkp), "asdi": angular_differential(tkp, sdk)}


def _search(kpd, limits=True):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = detect(kpd, pfa=PFA, n_draws=DRAWS, limits=limits)
    cands = [(float(r["fit_dra"].value), float(r["fit_ddec"].value),
              float(np.mean(r["fit_contrast"])), float(r["pfa_global"]))
             for r in res.candidates] if len(res.candidates) else []
    out = {"test": res.test, "n_candidates": len(res.candidates), "candidates": cands,
           "energy_pfa": res.energy["pfa"], "noise_scale": res.energy["noise_scale"]}
    if limits:
        sep = np.asarray(res.curves["separation"], float)
        lim = np.asarray(res.curves[f"{res.test}_median"], float)
        out.update({f"limit_{s}": float(np.interp(s, sep, lim)) for s in (150, 250)})
        out["limit_200_300"] = float(np.median(lim[(sep >= 200) & (sep <= 300)]))
    return out


def null(seeds, tmp):
    out = []
    for seed in seeds:
        row = {"seed": seed}
        for name, kpd in _products(_target(seed, tmp)).items():
            row[name] = _search(kpd)
        out.append(row)
        print(json.dumps(row), flush=True)
    return out


def companion(seeds, tmp, limits, factors=(1.0, 2.0), n_pa=4):
    out = []
    for seed in seeds:
        for sep in (150, 250):
            for f in factors:
                for pa in 20.0 + 360.0 * np.arange(n_pa) / n_pa + 13 * seed:
                    sky = (sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa)))
                    c = f * limits[seed][f"limit_{sep}"]
                    r = _search(_products(_target(seed, tmp, c, sky))["asdi"], limits=False)
                    d = min((np.hypot(x - sky[0], y - sky[1]) for x, y, _, _ in r["candidates"]),
                            default=float("nan"))
                    fit = [cc for x, y, cc, _ in r["candidates"]
                           if np.hypot(x - sky[0], y - sky[1]) < 5]
                    out.append({"seed": seed, "sep": sep, "factor": f, "pa": float(pa),
                                "contrast": c, "found_within": d,
                                "fit_contrast": fit[0] if fit else None,
                                "n_candidates": r["n_candidates"]})
                    print(json.dumps(out[-1]), flush=True)
    return out


def _with_companion(tkp, sky, c):
    """The target's frames plus the model's kernel phases of a companion fixed on the sky
    at *sky* (dRA, dDec; mas) of contrast *c* (the window's attenuation included), each
    frame at its own angle: the same noise as the companion-free sequence."""
    att = float(tkp.window.at(np.hypot(*sky), tkp.pixscale)) if tkp.window is not None else 1.0
    add = np.stack([np.asarray(tkp.kernel_model.binary_kernel_phases(
        list(sky_to_detector(sky[0], sky[1], a)) * u.mas, np.full(tkp.n_wave, c * att),
        tkp.wavelengths)) for a in tkp.detpa])
    out = copy.copy(tkp)
    out.kp = tkp.kp + add
    return out


def inject(seeds, tmp, limits, factors=(1.0, 2.0), n_pa=4):
    """Injection-recovery in the companion-free sequences themselves (`_with_companion`):
    found within 5 mas at *factors* times the ASDI limit at 150 and 250 mas."""
    out = []
    for seed in seeds:
        tkp = _target(seed, tmp)
        for sep in (150, 250):
            for f in factors:
                for pa in 20.0 + 360.0 * np.arange(n_pa) / n_pa + 13 * seed:
                    sky = (sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa)))
                    c = f * limits[seed][f"limit_{sep}"]
                    r = _search(_products(_with_companion(tkp, sky, c))["asdi"], limits=False)
                    d = [float(np.hypot(x - sky[0], y - sky[1])) for x, y, _, _ in r["candidates"]]
                    out.append({"seed": seed, "sep": sep, "factor": f, "pa": float(pa),
                                "contrast": c, "found_within": min(d, default=float("nan")),
                                "candidates": r["candidates"]})
                    print(json.dumps(out[-1]), flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("case", choices=("null", "companion", "inject"))
    ap.add_argument("--seeds", default="1-3")
    ap.add_argument("--tmp", default="/tmp/measure_asdi")
    ap.add_argument("--limits", help="JSON of a null run: its ASDI limits per seed")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    seeds = _seeds(args.seeds)
    if args.case == "null":
        res = null(seeds, args.tmp)
    else:
        with open(args.limits) as fh:
            limits = {row["seed"]: row["asdi"] for row in json.load(fh)}
        res = (companion if args.case == "companion" else inject)(seeds, args.tmp, limits)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
