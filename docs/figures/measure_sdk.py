"""Spectral-differential kernel phases (issue 39): false alarms, limits and companions.

CHARIS simulations (``simulate_scene('charis', shape=(S, S), n_frames=20,
**TYPICAL_STATIC)``: 22 channels, 50 nm of static aberration common to target
and calibrator at low order, 15 nm of the target's own, 10 nm drifting; the
calibrator's static aberrations are the common part only, so that target and
calibrator differ by 15 nm), extracted as ``kpifs extract`` does
(`kpifs.workflow`), and searched at P_FA 1e-2 with 1000 draws:

``null``
    No companion. Per seed, four searches of the same data: the target alone
    with ``--spectral-differential`` (``sdk``), the target alone as it is
    (``--allow-uncalibrated``, ``raw``), calibrated by the calibrator (``cal``),
    and calibrated with the option too (``cal+sdk``): candidates, the energy
    test's P_FA, and the median limit of the test searched at 200-400 mas
    (``--no-cal``: the first two only; ``--no-raw``: without ``raw``; ``--n-dead 0``:
    the same frames without the preset's dead spaxels). With no calibrator the static
    term has the group of the pixels filled in every frame (the dead spaxels near the
    star), as ``kpifs extract`` writes it (``--no-filled``: without).
``companion``
    One companion (flat spectrum) per separation (150 and 250 mas), at twice
    the ``sdk`` limit measured on the first seed of ``null``: found, and how far
    from the truth.
``inject``
    Injection-recovery per companion-free sequence (`inject`): model companions
    at 0.5, 1, 1.5 and 2 times the stated limit (the limit map's value at the
    position; ``--kinds median``: the radial curve's median), 8 position angles
    (``--n-pa``), at ``--seps`` (150 and 250 mas): the fractions whose reported
    (fitted) position is within 5 mas, and within 30 mas (detected), and the
    offsets in units of the reported position errors (pulls). 400 mas
    needs ``--step 0.27m`` (the default pupil step stops the grid at 299 mas).
``sphere``
    The same for SPHERE-IFS YJ (39 channels, 0.957-1.329 um; ``null`` only, one
    seed): inner separation and limits.
``bench``
    ``detect`` on the same 20-frame 22-channel data with the option and without
    (``--allow-uncalibrated``): the ratio of their times (measured under the
    machine's load at the time; a ratio, not a speed).

Run from the project root, e.g.::

    python docs/figures/measure_sdk.py null --seeds 1-10 --out /tmp/sdk_null.json

Results go to a JSON file (``--out``) and a summary is printed.
"""
import argparse
import copy
import functools
import hashlib
import json
import pathlib
import pickle
import time
import warnings

import numpy as np
from astropy import units as u

from kpifs.calibration.calibrate import calibrate
from kpifs.calibration.spectral_diff import spectral_differential
from kpifs.detect import detect
from kpifs.detect.sdk import SpectralStack, static_term_rows
from kpifs.io.layouts import write_observation
from kpifs.simulation.aberrations import static_residual_rows
from kpifs.simulation.simulate import TYPICAL_STATIC, simulate_scene
from kpifs.workflow import ExtractOptions, _filled_group, extract_observation

PFA, DRAWS = 1e-2, 1000
#: A candidate this close (mas, a resolution element at 1.16 um) counts as detected.
DETECTED = 30.0
BASIS = "static"
#: Channel profiles of the static basis (``--n-static``; the default's 3 unless given).
N_STATIC = {"n": None}
#: The pupil model's grid step (``--step``; the default's unless given): the grid reaches
#: ``0.95 lambda_min / (2 step)`` (299 mas at 1.16 um with the default 0.38 m).
STEP = {"step": None}


def _seeds(text):
    """Seeds from ``a-b`` (a range), ``a,b,c`` (a list) or both (``1-3,9``)."""
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def _reduce(preset, seed, tmp, shape, **kw):
    """The target and calibrator of one simulated sequence, extracted; cached under *tmp*
    (a pickle per preset, seed, shape and simulation options)."""
    what = (preset, seed, shape, sorted((k, str(v)) for k, v in kw.items()))
    if STEP["step"] is not None:
        what += (STEP["step"],)
    if LAYOUT["layout"] != "plain":
        what += (LAYOUT["layout"],)
    key = hashlib.sha1(repr(what).encode()).hexdigest()[:12]
    path = pathlib.Path(tmp) / f"{preset}{seed}_{shape}_{key}.pkl"
    if path.exists():
        with open(path, "rb") as f:
            tkp, ckp, *filled = pickle.load(f)
        FILLED[id(tkp)] = filled[0] if filled else None
        return tkp, ckp
    path.parent.mkdir(parents=True, exist_ok=True)
    obs = simulate_scene(preset, seed=seed, shape=(shape, shape), n_frames=20,
                         **dict(TYPICAL_STATIC, **kw))
    files = write_observation(obs, f"{tmp}/{preset}{seed}", overwrite=True,
                              layout=LAYOUT["layout"])
    opts = ExtractOptions() if STEP["step"] is None else ExtractOptions(step=STEP["step"])
    tkp = extract_observation(files["target"], opts)
    ckp = extract_observation(files["calibrator"], opts, model=tkp.kernel_model)
    # the static term's group of the pixels filled in every frame, as `kpifs extract
    # --spectral-differential` images it with no calibrator (issue 39)
    filled = _filled_group(files["target"], tkp, opts)[0]
    FILLED[id(tkp)] = filled
    with open(path, "wb") as f:
        pickle.dump((tkp, ckp, filled), f)
    return tkp, ckp


#: The files' layout (``--layout``): 'plain' writes the images alone (the dead spaxels'
#: garbage values unmarked, extracted as they are); 'charis' the CHARIS pipeline's cubes
#: with their inverse variance (0 at the dead spaxels: masked, filled by the extraction).
LAYOUT = {"layout": "plain"}
#: Each target's filled-pixel rows (`kpifs.workflow._filled_group`), by ``id``.
FILLED = {}
#: Whether the searches with no calibrator fit the filled pixels' group (``--no-filled``).
USE_FILLED = {"on": True}


_ROWS = {}


def _sdk(kpd, tkp, basis=BASIS):
    key = (tkp.n_wave, tkp.n_kp)
    if key not in _ROWS and basis != "poly":
        _ROWS[key] = static_residual_rows(tkp.kernel_model, tkp.wavelengths, tkp.pixscale,
                                          window=tkp.window)
    extra = {} if N_STATIC["n"] is None else {"n_static": N_STATIC["n"]}
    out = spectral_differential(tkp, kpd, basis=basis, static_rows=_ROWS.get(key), **extra)
    filled = FILLED.get(id(tkp))
    if kpd is None and USE_FILLED["on"] and filled is not None:
        # the product's static term as `kpifs.workflow` writes it with no calibrator
        rows, sizes = static_term_rows(tkp)
        if filled.shape[1:] == rows.shape[1:]:
            out.spectral["static_rows"] = np.concatenate([rows, filled])
            out.spectral["static_groups"] = sizes + [len(filled)]
    return out


def _search(kpd, **kw):
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = detect(kpd, pfa=PFA, n_draws=DRAWS, **kw)
    dt = time.perf_counter() - t0
    cur = res.curves
    sep = np.asarray(cur["separation"], float)
    col = f"{res.test}_median"
    sel = (sep >= 200) & (sep <= 400)
    lim = float(np.median(np.asarray(cur[col], float)[sel])) if sel.any() else float("nan")
    cands = [(float(r["x"].value), float(r["y"].value), float(r["pfa_global"]))
             for r in res.candidates] if len(res.candidates) else []
    blocks = res.meta.get("blocks") or {}
    return {"test": res.test, "n_candidates": len(res.candidates), "candidates": cands,
            "positions": _positions(res),
            "energy_pfa": res.energy["pfa"], "energy_raw": res.energy["raw"],
            "dof": res.energy["dof"], "noise_scale": res.energy["noise_scale"],
            "limit_200_400": lim, "seconds": dt, "max_sep": float(res.grid.max_sep),
            "inner_separation": blocks.get("inner_separation"),
            "static_amplitudes": blocks.get("static_amplitudes"),
            "retained": blocks.get("retained"),
            "curve": [[float(s), float(v)] for s, v in zip(sep, np.asarray(cur[col], float))]}


#: Simulation options of ``null`` beyond the preset's (``--n-dead``).
SIM = {}


def null(seeds, tmp, preset="charis", shape=80, with_cal=True, with_raw=True):
    out = []
    for seed in seeds:
        tkp, ckp = _reduce(preset, seed, tmp, shape, static_diff_rms=0 * u.nm, contrasts=0.0,
                           **SIM)
        row = {"seed": seed, "sdk": _search(_sdk(None, tkp))}
        if with_raw:
            row["raw"] = _search(tkp, allow_uncalibrated=True)
        if with_cal:
            row["cal"] = _search(calibrate(tkp, [ckp]))
            row["cal+sdk"] = _search(_sdk(calibrate(tkp, [ckp]), tkp))
        out.append(row)
        print(json.dumps({k: (v if k == "seed" else {q: v[q] for q in (
            "n_candidates", "candidates", "energy_pfa", "limit_200_400", "inner_separation",
            "static_amplitudes", "seconds")})
            for k, v in row.items()}), flush=True)
    return out


def companion(seeds, tmp, limit, shape=80):
    out = []
    for seed in seeds:
        for sep in (150.0, 250.0):
            c = 2 * limit(sep)
            pa = np.deg2rad(30.0 + 70 * seed)
            xy = [sep * np.cos(pa), sep * np.sin(pa)]
            tkp, _ = _reduce("charis", seed, tmp, shape, contrasts=c,
                             companion_offset=xy * u.mas)
            r = _search(_sdk(None, tkp))
            d = min((np.hypot(x - xy[0], y - xy[1]) for x, y in r["positions"]),
                    default=float("nan"))
            out.append({"seed": seed, "sep": sep, "contrast": c, "found_within": d,
                        "n_candidates": r["n_candidates"]})
            print(json.dumps(out[-1]), flush=True)
    return out


def _found(kpd, xy, c, pa_model):
    """How far (mas) from *xy* the nearest candidate is reported (its fitted position,
    the grid point where the fit failed; inf with none) when a companion of contrast
    *c* at *xy* (mas) is added to *kpd* as the model's kernel phases (the window's
    attenuation included); with that candidate's offsets (x, y) in units of its
    reported position errors (the pulls; NaN without a fit or a candidate)."""
    att = float(kpd.window.at(np.hypot(*xy), kpd.pixscale)) if kpd.window is not None else 1.0
    sig = np.asarray(pa_model.binary_kernel_phases(np.asarray(xy) * u.mas,
                                                   np.full(kpd.n_wave, c * att),
                                                   kpd.wavelengths))
    q = copy.copy(kpd)
    q.kp = kpd.kp + sig[None]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = detect(q, pfa=PFA, n_draws=DRAWS, limits=False)
    pos = _positions(res)
    if not pos:
        return np.inf, (np.nan, np.nan)
    d = [np.hypot(x - xy[0], y - xy[1]) for x, y in pos]
    j = int(np.argmin(d))
    r = res.candidates[j]
    err = [float(r[k].value) if k in r.colnames else np.nan for k in ("fit_x_err", "fit_y_err")]
    return float(d[j]), tuple(float(v) for v in (np.subtract(pos[j], xy) / err))


def _positions(res):
    """The candidates' reported positions (mas): fitted, or the grid point."""
    out = []
    for r in res.candidates:
        fx, fy = (float(r[k].value) if k in r.colnames else np.nan for k in ("fit_x", "fit_y"))
        ok = np.isfinite(fx) and np.isfinite(fy)
        out.append((fx, fy) if ok else (float(r["x"].value), float(r["y"].value)))
    return out


def _local_limit(res, xy):
    """The limit map of the searched test at the grid point nearest *xy* (mas)."""
    g = res.grid
    return float(res.limit[np.argmin(np.abs(g.y - xy[1])), np.argmin(np.abs(g.x - xy[0]))])


def _num(v):
    return float(v) if np.isfinite(v) else None


def _rms(values):
    """Root mean square of the finite *values* (None with none)."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v ** 2))) if v.size else None


def inject(seeds, tmp, shape=80, seps=(150.0, 250.0), factors=(0.5, 1.0, 1.5, 2.0), n_pa=8,
           kinds=("local",)):
    """Injection-recovery against the stated limits, per companion-free sequence: the
    model's kernel phases (which the simulator's companions follow: correlation 0.999
    in noise-free simulations, the window's attenuation aside) added to the
    spectral-differential product at *n_pa* position angles and *factors* times the
    limit map's value there (``local``) and/or times the median limit at that separation
    (``median``, the radial curve); the fractions found within 5 mas, and the reported
    positions' offsets in units of their reported errors (``*_pulls``, x and y; their
    rms over the detected, ``*_rms_pull``: of order 1 where the errors cover the
    offsets)."""
    out = []
    for seed in seeds:
        tkp, _ = _reduce("charis", seed, tmp, shape, static_diff_rms=0 * u.nm, contrasts=0.0)
        kpd = _sdk(None, tkp)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = detect(kpd, pfa=PFA, n_draws=DRAWS)
        cur = res.curves
        curve = (np.asarray(cur["separation"], float),
                 np.asarray(cur[f"{res.test}_median"], float))
        for sep in seps:
            med = float(np.interp(sep, *curve))
            pos = [(sep * np.cos(a), sep * np.sin(a))
                   for a in np.deg2rad(7.0 + 360.0 * np.arange(n_pa) / n_pa)]
            row = {"seed": seed, "sep": sep, "shape": shape, "median_limit": med,
                   "factors": list(factors), "n_candidates_null": len(res.candidates),
                   "noise_scale": res.energy["noise_scale"], "energy_pfa": res.energy["pfa"],
                   "local_limits": [_local_limit(res, xy) for xy in pos]}
            for kind in kinds:
                found = [[_found(kpd, xy, f * (loc if kind == "local" else med),
                                 tkp.kernel_model) for xy, loc in zip(pos, row["local_limits"])]
                         for f in factors]
                dist = [[d for d, _ in r] for r in found]
                # offsets / reported errors: of order 1 where the errors cover the offsets
                # (the rms over the detected, x and y)
                row[kind + "_pulls"] = [[[_num(v) for v in p] for _, p in r] for r in found]
                row[kind + "_rms_pull"] = [_rms([v for d, p in r if d < DETECTED for v in p])
                                           for r in found]
                row[kind + "_distance"] = [[float(min(d, 1e9)) for d in r] for r in dist]
                row[kind] = [float(np.mean(np.asarray(r) < 5)) for r in dist]
                row[kind + "_detected"] = [float(np.mean(np.asarray(r) < DETECTED))
                                           for r in dist]
            out.append(row)
            print(json.dumps(out[-1]), flush=True)
    return out


def bench(tmp, shape=80):
    tkp, _ = _reduce("charis", 1, tmp, shape, contrasts=0.0)
    sdk = _sdk(None, tkp)
    t = {}
    for name, kpd, kw in (("without", tkp, {"allow_uncalibrated": True}), ("with", sdk, {}),
                          ("without2", tkp, {"allow_uncalibrated": True}), ("with2", sdk, {})):
        t[name] = _search(kpd, **kw)["seconds"]
    ratio = (t["with"] + t["with2"]) / (t["without"] + t["without2"])
    print(json.dumps({**t, "ratio": ratio}), flush=True)
    return {**t, "ratio": ratio}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=("null", "companion", "inject", "sphere", "bench"))
    ap.add_argument("--no-cal", action="store_true", help="null: no calibrated searches")
    ap.add_argument("--no-raw", action="store_true",
                    help="null: no search of the target as it is (--allow-uncalibrated)")
    ap.add_argument("--n-dead", type=int, help="null: dead spaxels simulated (the preset's "
                    "unless given; drawn after the frames, which stay the same)")
    ap.add_argument("--n-static", type=int, help="profiles of the static basis")
    ap.add_argument("--seeds", default="1-3")
    ap.add_argument("--tmp", default="/tmp/measure_sdk")
    ap.add_argument("--limits", help="JSON of a null run: the sdk limit curve of its first seed")
    ap.add_argument("--out")
    ap.add_argument("--shape", type=int, default=80, help="simulated image side (pixels)")
    ap.add_argument("--seps", default="150,250", help="inject: separations (mas)")
    ap.add_argument("--factors", default="0.5,1,1.5,2", help="inject: times the limit")
    ap.add_argument("--kinds", default="local", help="inject: local and/or median")
    ap.add_argument("--no-filled", action="store_true",
                    help="no group of the filled pixels in the static term (as before issue "
                         "39's fill group)")
    ap.add_argument("--layout", default="plain",
                    help="files written: plain (images alone) or the instrument's (charis: "
                         "with the inverse variance, which marks the dead spaxels)")
    ap.add_argument("--step", help="pupil model grid step, e.g. 0.27m (reaches 420 mas)")
    ap.add_argument("--n-pa", type=int, default=8, help="inject: position angles")
    ap.add_argument("--stack", default="", help="SpectralStack options, e.g. "
                    "'normalise=none,static=none' (the defaults unless given)")
    a = ap.parse_args()
    seeds = _seeds(a.seeds)
    if a.stack:
        opts = dict(kv.split("=") for kv in a.stack.split(","))
        SpectralStack.__init__ = functools.partialmethod(SpectralStack.__init__, **opts)
    N_STATIC["n"] = a.n_static
    STEP["step"] = a.step
    USE_FILLED["on"] = not a.no_filled
    LAYOUT["layout"] = a.layout
    if a.n_dead is not None:
        SIM["n_dead"] = a.n_dead
    if a.case == "null":
        res = null(seeds, a.tmp, with_cal=not a.no_cal, shape=a.shape, with_raw=not a.no_raw)
    elif a.case == "inject":
        res = inject(seeds, a.tmp, shape=a.shape,
                     seps=[float(v) for v in a.seps.split(",")],
                     factors=[float(v) for v in a.factors.split(",")],
                     kinds=tuple(a.kinds.split(",")), n_pa=a.n_pa)
    elif a.case == "sphere":
        res = null(seeds, a.tmp, preset="sphere", shape=64)
    elif a.case == "bench":
        res = bench(a.tmp)
    else:
        curve = np.array(json.load(open(a.limits))[0]["sdk"]["curve"])
        res = companion(seeds, a.tmp, lambda s: float(np.interp(s, curve[:, 0], curve[:, 1])))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
