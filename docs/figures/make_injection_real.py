"""Analytic and injection detection limits on the real PHARO frames of epsilon Her.

Writes the figure and table of the user guide's section "Analytic and injection
limits on real frames" (``docs/user/limits.rst``):

- ``docs/user/injection_real_pharo.png``
- ``docs/user/injection_real_pharo.csv``

Frames 0-49 of epsilon Her (no known companion) are the target, frames 50-99
the calibrator. The analytic curve is `kpifs.detect.detect`'s binary-test limit
(P_FA 1e-3, P_D 0.5, default error model; median over azimuth). The injection
curve comes from `kpifs.inject.injection_limits`: companions made of each
frame's own PSF, the whole reduction rerun, at a ladder of 0.5, 1, 2 and 4 times
the analytic limit at each separation (rounded to two significant digits, so
that ``kpifs inject --curve`` can be given the same ladder).

The frames are third-party data kept outside the package (``../shared/data/real``
next to the project, or ``$KPIFS_REAL_DATA``); without them the script says so
and exits. Run from anywhere::

    python docs/figures/make_injection_real.py            # about 10-15 minutes

``--replot`` redraws the figure from the table (no injections); ``--quick`` (2
separations, 2 angles, written to the current directory) only checks that the
script runs.
"""
import argparse
import csv
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import astropy.units as u

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]                        # the project (docs/figures/ -> ../..)
OUT = ROOT / "docs" / "user"
NAME = "pharo_ca2_cube_epsHer.fits"

WL = [2.145] * u.um                           # K band, published with the frames
PIX = 25 * u.mas
STEP = 0.16 * u.m                             # the discrete model published with them
PFA, PD = 1e-3, 0.5
SEPARATIONS = [100, 200, 300, 450, 600]       # mas
FACTORS = [0.5, 1, 2, 4]                      # ladder, in units of the analytic limit
N_ANGLES = 6
N_DRAWS = 10000                               # injection_limits' default
SEED = 0


def find_real_data():
    """The shared real-data folder, or None."""
    candidates = [Path(os.environ["KPIFS_REAL_DATA"])] if "KPIFS_REAL_DATA" in os.environ \
        else []
    for base in (Path.cwd().resolve(), ROOT):
        candidates += [p / ".." / "shared" / "data" / "real" for p in (base, *base.parents)]
    for folder in candidates:
        if (folder / NAME).is_file():
            return folder.resolve()
    return None


def two_digits(x):
    """*x* rounded to two significant digits."""
    return float(f"{x:.1e}")


def limit_50(contrasts, pd, level=PD):
    """The contrast where the detected fraction reaches *level*, as injection_limits
    computes it (fractions made monotone, interpolation in log contrast); the lowest
    rung when it is already reached there (an upper bound), NaN when never."""
    p = np.maximum.accumulate(np.asarray(pd, float))
    k = np.flatnonzero(p >= level)
    if not len(k):
        return np.nan
    i = k[0]
    if i == 0:
        return float(contrasts[0])
    lc = np.log(contrasts)
    f = (level - p[i - 1]) / (p[i] - p[i - 1])
    return float(np.exp(lc[i - 1] + f * (lc[i] - lc[i - 1])))


def limit_interval(contrasts, hits, n, rng, draws=4000):
    """16-84 % interval of the 50 % contrast from the binomial counts alone: the
    fraction of each rung drawn from its Jeffreys posterior Beta(k + 1/2, n - k + 1/2)
    and the limit recomputed. NaN (no bound) where a draw never reaches 50 %."""
    hits = np.asarray(hits, float)
    p = rng.beta(hits + 0.5, n - hits + 0.5, size=(draws, len(hits)))
    lims = np.array([limit_50(contrasts, row) for row in p])
    lims = np.where(np.isnan(lims), np.inf, lims)
    lo, hi = np.percentile(lims, [16, 84])
    return float(lo), (float(hi) if np.isfinite(hi) else np.nan)


COLUMNS = ["separation_mas", "analytic_B_median", "analytic_B_min", "analytic_B_max",
           "ladder", "detected", "n_injected", "injection_50", "injection_50_lo",
           "injection_50_hi", "ratio", "seed"]


def run_injections(target, cal, km, window, seps, ana, n_angles, n_draws, injection_limits):
    """One `injection_limits` run per separation, its ladder bracketing the analytic
    limit there; one table row per separation."""
    rows = []
    rng = np.random.default_rng(12345)
    for i, s in enumerate(seps):
        ladder = [two_digits(f * ana["median"][i]) for f in FACTORS]
        t0 = time.time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tab = injection_limits(target, [cal], km, wavelengths=WL, pixscale=PIX,
                                   window=window, separations=[s] * u.mas, contrasts=ladder,
                                   n_angles=n_angles, pfa=PFA, pd=PD, seed=SEED + i,
                                   n_draws=n_draws)
        hits = [int(v) for v in tab["n_detected"]]
        lim = tab.meta["limits"][0]
        lo, hi = limit_interval(np.array(ladder), hits, n_angles, rng)
        row = dict(separation_mas=s, analytic_B_median=ana["median"][i],
                   analytic_B_min=ana["min"][i], analytic_B_max=ana["max"][i],
                   ladder=";".join(f"{c:.1e}" for c in ladder),
                   detected=";".join(f"{h}/{n_angles}" for h in hits),
                   n_injected=n_angles * len(ladder), injection_50=lim,
                   injection_50_lo=lo, injection_50_hi=hi,
                   ratio=lim / ana["median"][i], seed=SEED + i)
        rows.append(row)
        print(f"{s:4.0f} mas: analytic {ana['median'][i]:.2e}; found {row['detected']} at "
              f"{row['ladder']}; injection 50 % {lim:.2e} (68 %: {lo:.2e}-{hi:.2e}); "
              f"ratio {row['ratio']:.2f}  ({time.time() - t0:.0f} s)")
    return rows


def write_table(rows, path):
    def fmt(key, value):
        if key == "ratio":
            return f"{value:.2f}"
        if isinstance(value, float) and key != "separation_mas":
            return f"{value:.3e}"
        return value
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: fmt(k, r[k]) for k in COLUMNS})
    print(f"table -> {path}")


def read_table(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        for k in COLUMNS:
            if k not in ("ladder", "detected"):
                r[k] = float(r[k])
    return rows


def plot(rows, curves, n_angles, plt):
    """Left: the analytic curve and the injection 50 % points; right: the fraction
    found against the injected contrast in units of the analytic limit."""
    import matplotlib.ticker
    rng = np.random.default_rng(1)
    rsep = curves["separation"].to_value(u.mas)
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(9.6, 3.9),
                                 gridspec_kw=dict(width_ratios=[1.25, 1]))
    ok = np.isfinite(rsep) & np.isfinite(np.asarray(curves["B_median"], float))
    ax.fill_between(rsep[ok], np.asarray(curves["B_min"], float)[ok],
                    np.asarray(curves["B_max"], float)[ok], color="C0", alpha=0.15, lw=0,
                    label="analytic, min-max over azimuth")
    ax.plot(rsep[ok], np.asarray(curves["B_median"], float)[ok], "C0-",
            label="analytic (B test, median)")
    s_arr = np.array([r["separation_mas"] for r in rows], float)
    lim = np.array([r["injection_50"] for r in rows], float)
    lo = np.array([r["injection_50_lo"] for r in rows], float)
    hi = np.array([r["injection_50_hi"] for r in rows], float)
    hi_plot = np.where(np.isfinite(hi), hi, lim * 3)
    ax.errorbar(s_arr, lim, yerr=[lim - np.minimum(lo, lim), hi_plot - lim], fmt="ko",
                capsize=3, label=f"injections: 50 % found ({n_angles} angles per rung)")
    for s, r in zip(s_arr, rows):
        for c, h in zip(r["ladder"].split(";"), r["detected"].split(";")):
            k = int(h.split("/")[0])
            ax.plot(s + 16, float(c), marker="s", ms=4, mec="k", mew=0.4,
                    color=plt.cm.RdYlGn(k / n_angles))
    ax.plot([], [], "s", ms=4, mec="k", mew=0.4, color=plt.cm.RdYlGn(0.5),
            label="contrasts tried (colour: fraction found)")
    ax.set_yscale("log")
    ax.set_xlim(40, 660)
    ax.set_ylim(1.2e-3, 1.5e-1)
    ticks = [2e-3, 5e-3, 1e-2, 2e-2, 5e-2, 1e-1]
    ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_yticks(ticks, [f"{t:.0e}".replace("e-0", "e-") for t in ticks])
    ax.set_xlabel("separation (mas)")
    ax.set_ylabel("contrast")
    ax.set_title(f"eps Her 0-49 / 50-99, PHARO K: P_FA {PFA:g}, P_D {PD:g}", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    for j, (s, r) in enumerate(zip(s_arr, rows)):
        f = np.array([float(c) for c in r["ladder"].split(";")]) / r["analytic_B_median"]
        k = np.array([int(h.split("/")[0]) for h in r["detected"].split(";")])
        el, eh = [], []
        for kk in k:
            a, b = np.percentile(rng.beta(kk + 0.5, n_angles - kk + 0.5, 4000), [16, 84])
            el.append(max(kk / n_angles - a, 0))
            eh.append(max(b - kk / n_angles, 0))
        bx.errorbar(f * (1 + 0.03 * (j - 2)), k / n_angles, yerr=[el, eh], fmt="o-", ms=4,
                    capsize=2, lw=1, label=f"{s:.0f} mas")
    bx.axhline(PD, color="0.6", lw=0.8, ls=":")
    bx.axvline(1, color="C0", lw=0.8)
    bx.set_xscale("log")
    bx.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    bx.set_xticks(FACTORS, [f"{f:g}" for f in FACTORS])
    bx.set_ylim(-0.05, 1.05)
    bx.set_xlabel("injected contrast / analytic limit")
    bx.set_ylabel("fraction found (68 % Jeffreys interval)")
    bx.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="2 separations, 2 angles, 2000 draws: a smoke test (writes to "
                             "the current directory, not docs/user)")
    parser.add_argument("--replot", action="store_true",
                        help="redraw the figure from the table already written (the analytic "
                             "curve recomputed, no injections)")
    args = parser.parse_args(argv)

    real = find_real_data()
    if real is None:
        print(f"The shared real data ({NAME}) are absent (../shared/data/real next to the "
              "project, or $KPIFS_REAL_DATA): nothing to do.")
        return 0

    import matplotlib
    matplotlib.use("agg")
    import matplotlib.pyplot as plt

    import kpifs
    from kpifs import KernelModel, extract_kernel_phases, make_pupil
    from kpifs.calibration.calibrate import calibrate
    from kpifs.detect import detect
    from kpifs.inject import injection_limits
    from kpifs.io import read_cube
    from kpifs.model.window import ExtractionWindow

    seps = SEPARATIONS[1:5:2] if args.quick else SEPARATIONS
    n_angles, n_draws = (2, 2000) if args.quick else (N_ANGLES, N_DRAWS)
    out = Path.cwd() if args.quick else OUT

    t_start = time.time()
    with read_cube(real / NAME, instrument="generic", wavelengths=WL, pixscale=PIX) as cube:
        frames = np.array(cube.data, float)
    if frames.shape[0] != 100:
        raise SystemExit(f"{NAME}: expected 100 frames, got {frames.shape}")
    target, calib = frames[:50], frames[50:]
    km = KernelModel.from_pupil(make_pupil("pharo", step=STEP))
    window = ExtractionWindow.default(frames.shape[-2:])
    ext = dict(wavelengths=WL, pixscale=PIX, window=window, keep_phases=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")     # few frames for the kernels: kpifs says so
        cal = extract_kernel_phases(calib, km, source="eps Her 50-99", **ext)
        tgt = extract_kernel_phases(target, km, source="eps Her 0-49", **ext)
        analytic = detect(calibrate(tgt, cal), pfa=PFA, pd=PD, seed=SEED)
    curves = analytic.curves
    rsep = curves["separation"].to_value(u.mas)
    ana = {k: np.interp(seps, rsep, np.asarray(curves[f"B_{k}"], float), left=np.nan,
                        right=np.nan) for k in ("min", "median", "max")}
    print(f"kpifs {kpifs.__version__}; {km.n_kp} kernel phases; error model "
          f"{analytic.meta.get('error_model', {}).get('model', '?')}; "
          f"{len(analytic.candidates)} candidate(s) without injections "
          f"({time.time() - t_start:.0f} s)")

    if args.replot:
        rows = read_table(out / "injection_real_pharo.csv")
        n_angles = int(rows[0]["detected"].split(";")[0].split("/")[1])
    else:
        rows = run_injections(target, cal, km, window, seps, ana, n_angles, n_draws,
                              injection_limits)
        runtime = time.time() - t_start
        n_total = sum(r["n_injected"] for r in rows)
        print(f"{n_total} injections, {runtime / 60:.1f} min in all")
        write_table(rows, out / "injection_real_pharo.csv")
    fig = plot(rows, curves, n_angles, plt)
    png = out / "injection_real_pharo.png"
    fig.savefig(png, dpi=100)
    print(f"figure -> {png} ({png.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
