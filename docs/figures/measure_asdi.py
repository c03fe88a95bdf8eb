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
    frames of ``null``'s seeds (each frame at its own angle): the same noise. Each
    candidate with its fitted offset's errors (dRA, dDec).
``pulls``
    Are the fitted positions noise-limited? Per seed, the ASDI stack of the
    companion-free sequence (its error model fixed), and at 150 and 250 mas, 4 position
    angles, a companion whose whitened signature has the norm *snr* (5 and 10, about
    1x and 2x the limit) added to the stacked data (the frames' injection through the
    stack gives the same vector to 1e-13: checked on the first case): fitted from the
    truth, its offset and the fit's errors (``(J^T J)^-1``) along the radius and the
    azimuth, and ``chi2(truth) - chi2(fit)`` (contrast profiled; chi-square with 2
    degrees of freedom if the whitened noise is white); the same fit on the signature
    alone (no noise) from 7 mas off; the share of the signature's squared norm in the
    blocks' departures (the rest is in the combinations' mean); and the r.m.s. over the
    grid of the noise's matched filter (one contrast scale) from the combinations' mean
    alone and from the blocks' departures alone, by separation (1 for white noise).
``sidelobes``
    The companions of ``pulls`` (no noise): the normalised correlation of the whitened
    signature at the truth with the grid's, its strongest value beyond 30 mas from the
    companion and on the star's other side, and where (separation, position angle from
    the companion's).

Run from the project root::

    python docs/figures/measure_asdi.py null --seeds 1-6 --out /tmp/asdi_null.json
    python docs/figures/measure_asdi.py companion --seeds 1-2 --limits /tmp/asdi_null.json
    python docs/figures/measure_asdi.py pulls --seeds 1-12 --out /tmp/asdi_pulls.json
    python docs/figures/measure_asdi.py sidelobes --seeds 1-3
"""
import argparse
import copy
import json
import warnings

import numpy as np
from astropy import units as u
from scipy import optimize

from kpifs.calibration.adi import angular_differential
from kpifs.calibration.spectral_diff import spectral_differential
from kpifs.detect import detect
from kpifs.detect import pipeline
from kpifs.detect.options import SearchOptions
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
              float(np.mean(r["fit_contrast"])), float(r["pfa_global"]),
              float(r["fit_dra_err"].value), float(r["fit_ddec_err"].value))
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
                    d = min((np.hypot(x - sky[0], y - sky[1]) for x, y, *_ in r["candidates"]),
                            default=float("nan"))
                    fit = [cc for x, y, cc, *_ in r["candidates"]
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
                    d = [float(np.hypot(x - sky[0], y - sky[1])) for x, y, *_ in r["candidates"]]
                    out.append({"seed": seed, "sep": sep, "factor": f, "pa": float(pa),
                                "contrast": c, "found_within": min(d, default=float("nan")),
                                "candidates": r["candidates"]})
                    if d and min(d) < 30:      # the companion's: offset along radius, azimuth
                        x, y, _, _, ex, ey = r["candidates"][int(np.argmin(d))]
                        er = np.array(sky) / sep
                        out[-1]["offset_rad_az"] = [float(er @ [x - sky[0], y - sky[1]]),
                                                    float([er[1], -er[0]] @ np.subtract(
                                                        (x, y), sky))]
                        out[-1]["pull_dra_ddec"] = [(x - sky[0]) / ex, (y - sky[1]) / ey]
                    print(json.dumps(out[-1]), flush=True)
    return out


def _stack(kpd):
    """The ASDI search's `~kpifs.detect.blocks.BlockStack` and its model, as `detect` makes
    them (its first two stages)."""
    opts = SearchOptions.from_keywords(pfa=PFA, n_draws=DRAWS)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        white = pipeline._whiten_stage(pipeline._prepare_stage(kpd, opts), opts)
    return white.stack, white.model


def _fit(st, data, sky, c):
    """Least-squares position and contrast scale of a companion in the stacked *data*,
    from *sky* (within 20 mas)."""
    def resid(par):
        att = st._attenuation(*par[:2])
        return (data - st.model_kp(par[:2], np.full(st.n_comb, par[2] * c * att))).ravel()
    return optimize.least_squares(resid, [sky[0], sky[1], 1.0], diff_step=1e-6,
                                  bounds=([sky[0] - 20, sky[1] - 20, -np.inf],
                                          [sky[0] + 20, sky[1] + 20, np.inf]))


def _noise_filters(st, model, sep_rings):
    """The r.m.s. of the noise's one-scale matched filter over the grid, by ring, from the
    stack's mean part, its departures and both."""
    g, rm, n = model.grid, st.comp_mean.shape[1], st.kp
    rows = np.flatnonzero(g.valid.ravel())
    sep = np.hypot(g.X, g.Y).ravel()[rows]
    parts = {"mean": slice(0, rm), "departures": slice(rm, None), "both": slice(None)}
    z = {k: [] for k in parts}
    for a in range(0, len(rows), 128):
        s = model._stacked_mixed(rows[a:a + 128])                       # (k, npos, dim)
        for k, sl in parts.items():
            z[k].append(np.einsum("kpd,kd->p", s[:, :, sl], n[:, sl])
                        / np.sqrt(np.einsum("kpd,kpd->p", s[:, :, sl], s[:, :, sl])))
    out = {}
    for k, v in z.items():
        v = np.concatenate(v)
        out[k] = {f"{lo}-{hi}": float(np.sqrt(np.mean(v[(sep >= lo) & (sep < hi)] ** 2)))
                  for lo, hi in sep_rings}
    return out


def pulls(seeds, tmp, snrs=(5.0, 10.0), n_pa=4):
    """Fitted positions against the fit's errors in the stack (see the module's text)."""
    out = []
    for seed in seeds:
        tkp = _target(seed, tmp)
        free = _products(tkp)["asdi"]
        st, model = _stack(free)
        rank, rm = float(np.sum(st.rank)), st.comp_mean.shape[1]
        head = {"seed": seed, "chi2_data": float(np.sum(st.kp ** 2) / rank),
                "mean_scale": st.mean_scale,
                "noise_filter": _noise_filters(st, model, ((50, 100), (100, 150), (150, 200),
                                                           (200, 250), (250, 300)))}
        print(json.dumps(head), flush=True)
        for sep in (150, 250):
            for pa in 20.0 + 360.0 * np.arange(n_pa) / n_pa + 13 * seed:
                sky = (sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa)))
                unit = st.model_kp(sky, np.full(st.n_comb, 1e-4 * st._attenuation(*sky)))
                if not out:                 # the frames' injection through the stack
                    inj = _products(_with_companion(tkp, sky, 1e-4))["asdi"]
                    frames = _through(st, inj.kp[0] - free.kp[0],
                                      inj.rotation.data - free.rotation.data)
                    head["injection_vs_model"] = float(np.linalg.norm(frames - unit)
                                                       / np.linalg.norm(unit))
                er = np.array(sky) / sep
                rot = np.stack([er, [er[1], -er[0]]])           # radius, azimuth
                for snr in snrs:
                    c = 1e-4 * snr / np.linalg.norm(unit)
                    sig = unit * (c / 1e-4)
                    r = _fit(st, sig + st.kp, sky, c)
                    cov = np.linalg.pinv(r.jac.T @ r.jac)[:2, :2]
                    off = r.x[:2] - np.array(sky)
                    chi2_truth = float(np.sum((sig + st.kp) ** 2) - np.sum(
                        unit * (sig + st.kp)) ** 2 / np.sum(unit ** 2))
                    nf = _fit(st, sig, (sky[0] + 5, sky[1] - 5), c)
                    out.append({"seed": seed, "sep": sep, "pa": float(pa), "snr": snr,
                                "contrast": c, "offset": (rot @ off).tolist(),
                                "error": np.sqrt(np.diag(rot @ cov @ rot.T)).tolist(),
                                "d2": float(off @ np.linalg.solve(cov, off)),
                                "dchi2": chi2_truth - 2 * float(r.cost),
                                "fit_contrast": float(r.x[2]),
                                "departures_share": float(np.sum(unit[:, rm:] ** 2)
                                                          / np.sum(unit ** 2)),
                                "noise_free_offset": float(np.hypot(*(nf.x[:2] - sky)))})
                    print(json.dumps(out[-1]), flush=True)
        out.append(head)
    return out


def sidelobes(seeds, tmp, n_pa=4):
    """The companions' own side lobes in the ASDI search (see the module's text)."""
    out = []
    for seed in seeds:
        st, model = _stack(_products(_target(seed, tmp))["asdi"])
        g = model.grid
        for sep in (150, 250):
            for pa in 20.0 + 360.0 * np.arange(n_pa) / n_pa + 13 * seed:
                sky = (sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa)))
                sig = st.model_kp(sky, np.full(st.n_comb, 1e-4 * st._attenuation(*sky)))
                with np.errstate(invalid="ignore", divide="ignore"):
                    rho = model.dot_maps(sig).sum(0) / np.sqrt(model.norm2.sum(0)
                                                               * np.sum(sig ** 2))
                far = (np.hypot(g.X - sky[0], g.Y - sky[1]) > 30) & g.valid
                row = {"seed": seed, "sep": sep, "pa": float(pa)}
                # anywhere beyond 30 mas, and on the star's other side
                other = far & (g.X * sky[0] + g.Y * sky[1] < 0)
                for key, where in (("any", far), ("other_side", other)):
                    r = np.where(where, rho, -np.inf)
                    iy, ix = np.unravel_index(np.argmax(r), r.shape)
                    x, y = float(g.X[iy, ix]), float(g.Y[iy, ix])
                    row[key] = {"rho": float(r[iy, ix]), "at": [x, y],
                                "sep": float(np.hypot(x, y)),
                                "pa_from_companion": float((np.degrees(np.arctan2(x, y))
                                                            - pa + 180) % 360 - 180)}
                out.append(row)
                print(json.dumps(out[-1]), flush=True)
    return out


def _through(st, kp, blocks):
    """The ASDI stack's transform (its error model fixed) of channel data: the mean *kp*
    (q, p) and the blocks (B, q, p)."""
    mix = st.data_mixing
    ym = np.einsum("iap,ip->ia", st.comp_mean, mix @ kp)
    bd = np.einsum("kc,bcp->bkp", mix, blocks)
    n = st.blocks.frames
    dev = np.sqrt(n)[:, None, None] * (bd - np.tensordot(n / n.sum(), bd, axes=(0, 0)))
    dev = np.einsum("iap,bip->iba", st.comp_frame, dev).reshape(len(mix), -1)
    return np.concatenate([ym, dev], axis=-1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("case", choices=("null", "companion", "inject", "pulls", "sidelobes"))
    ap.add_argument("--seeds", default="1-3")
    ap.add_argument("--tmp", default="/tmp/measure_asdi")
    ap.add_argument("--limits", help="JSON of a null run: its ASDI limits per seed")
    ap.add_argument("--out")
    args = ap.parse_args(argv)
    seeds = _seeds(args.seeds)
    if args.case == "null":
        res = null(seeds, args.tmp)
    elif args.case in ("pulls", "sidelobes"):
        res = (pulls if args.case == "pulls" else sidelobes)(seeds, args.tmp)
    else:
        with open(args.limits) as fh:
            limits = {row["seed"]: row["asdi"] for row in json.load(fh)}
        res = (companion if args.case == "companion" else inject)(seeds, args.tmp, limits)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
