"""Figures: detection map with candidates, contrast curves, candidate spectrum, ROC curves.

Every function takes an optional matplotlib ``ax`` and returns the figure, so
figures can be composed or saved by the caller; `save_detection_plots` and
`save_roc_plots` write the standard sets as PNG files (atomically, like every
kpifs output). matplotlib is imported when a figure is drawn, not before.
"""
from pathlib import Path

import numpy as np
from astropy import units as u

from ._utils import atomic_write
from .detect.statistics import REGISTRY, reference_test
from .inject import injection_brackets

__all__ = ["plot_detection_map", "plot_contrast_curves", "plot_candidate_spectrum",
           "plot_roc", "plot_injection_limits", "save_detection_plots", "save_roc_plots"]


def _save(fig, path, *, dpi=100):
    """Write *fig* as PNG at *path* atomically and close it."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"), overwrite=True)
    finally:
        plt.close(fig)
    return Path(path)


def _axes(ax, figsize=(5.5, 4.5)):
    import matplotlib.pyplot as plt
    if ax is None:
        fig, ax = plt.subplots(figsize=figsize)
    return ax.figure, ax


PFA = r"$P_\mathrm{FA}$"
PD = r"$P_\mathrm{D}$"


def _test_label(name):
    """What a test's name means, for legends (`DetectionTest.label
    <kpifs.detect.statistics.DetectionTest>`; the name of one not registered)."""
    test = REGISTRY.get(name)
    return test.label if test is not None else name


def _candidate_xy(row, sky):
    cx, cy = ("dra", "ddec") if sky else ("x", "y")
    x = row["fit_" + cx] if "fit_" + cx in row.colnames else row[cx]
    y = row["fit_" + cy] if "fit_" + cy in row.colnames else row[cy]
    return x.to_value(u.mas), y.to_value(u.mas)


def plot_detection_map(result, *, ax=None, truth=None):
    """The map the search decided on, in units of its threshold, candidates marked.

    Candidates are found one at a time: the strongest peak above the threshold
    is fitted and subtracted, and the map of what remains is searched again.
    The map drawn is that residual map once every candidate is subtracted
    (`~kpifs.data.DetectionResult.search_map`), at the noise scale the
    candidates were judged with: nothing left in it crosses the threshold
    contour. Each subtracted candidate is circled at its fitted position,
    numbered, with its own statistic in units of the threshold. Products
    written before the residual map was kept show the data's own map instead.
    The colour scale is asinh (linear up to the threshold, logarithmic far
    above it).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_detection_map
    >>> fig = plot_detection_map(_example_result(), truth=(60, -40))
    >>> len(fig.axes), fig.axes[1].get_ylabel()
    (2, 'B statistic of the residual / threshold (asinh scale)')
    """
    from matplotlib.colors import AsinhNorm
    from matplotlib.lines import Line2D
    fig, ax = _axes(ax, figsize=(6.4, 5.0))
    g = result.grid
    ext = [g.x[0], g.x[-1], g.y[0], g.y[-1]]
    test = result.meta.get("map_test", result.test)      # the energy test's map is B's
    residual = getattr(result, "search_map", None) is not None
    shown = result.search_map if residual else result.statistic
    ratio = np.asarray(shown, float) / result.threshold
    top = max(float(np.nanmax(ratio)) if np.isfinite(ratio).any() else 1.0, 1.5)
    im = ax.imshow(ratio, origin="lower", extent=ext, cmap="magma",
                   norm=AsinhNorm(linear_width=1.0, vmin=0, vmax=top))
    ticks = [t for t in (0, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if t <= top]
    what = "statistic of the residual" if residual else "statistic"
    fig.colorbar(im, ax=ax, label=f"{test} {what} / threshold (asinh scale)", ticks=ticks,
                 format="%g")
    ax.contour(g.X, g.Y, np.nan_to_num(ratio), levels=[1.0], colors="cyan", linewidths=0.8)
    handles = [Line2D([], [], color="cyan", lw=0.8,
                      label=f"threshold {result.threshold:.3g} (global {PFA} = {result.pfa:g})")]
    sky = getattr(g, "frame", "detector") == "sky"
    for i, row in enumerate(result.candidates, 1):
        x, y = _candidate_xy(row, sky)
        ax.plot(x, y, "o", mfc="none", mec="cyan", ms=14)
        ax.annotate(f"{i}: {float(row['statistic']) / result.threshold:.3g}x", (x, y),
                    xytext=(9, 9), textcoords="offset points", color="cyan", fontsize=9,
                    fontweight="bold")
    if len(result.candidates):
        what = "subtracted, " if residual else ""
        handles.append(Line2D([], [], ls="none", marker="o", mfc="none", mec="cyan", ms=10,
                              label=f"candidates ({what}fitted position): "
                                    f"n: statistic / threshold"))
    if truth is not None:
        handles += ax.plot(*truth, "+", color="lime", ms=12, label="simulated companion")
    ax.legend(handles=handles, loc="upper right", fontsize=7, framealpha=0.8)
    if sky:     # the grid runs East to West: East is on the left
        ax.set_xlabel("dRA (mas, East to the left)")
        ax.set_ylabel("dDec (mas)")
    else:
        ax.set_xlabel("offset along detector x (mas)")
        ax.set_ylabel("offset along detector y (mas)")
    after = ", the map once they are subtracted" if residual and len(result.candidates) else ""
    ax.set_title(f"search with {_test_label(result.test)}\n{len(result.candidates)} "
                 f"candidate(s) at global {PFA} = {result.pfa:g}{after}", fontsize=9)
    return fig


def plot_contrast_curves(result, *, ax=None):
    """Median (line) and min-max (band) limiting contrast versus separation, per test.

    Every test whose limits the result holds is drawn; the test the search
    used is the thick line, named first in the legend.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_contrast_curves
    >>> fig = plot_contrast_curves(_example_result())
    >>> [t.get_text().split(":")[0] for t in fig.axes[0].get_legend().get_texts()]
    ['B', 'NP', 'E', 'B-paper', 'S', 'band']
    """
    from matplotlib.patches import Patch
    fig, ax = _axes(ax, figsize=(6.4, 4.8))
    sep = result.curves["separation"].to_value(u.mas)
    order = [result.test] + [t for t in REGISTRY if t != result.test]
    for name in order:
        if f"{name}_median" not in result.curves.colnames:
            continue
        own = name == result.test
        med = np.asarray(result.curves[f"{name}_median"])
        label = _test_label(name) + (" (this search's test)" if own else "")
        line, = ax.semilogy(sep, med, label=label, lw=2.4 if own else 1.0, zorder=3 if own else 2)
        ax.fill_between(sep, result.curves[f"{name}_min"], result.curves[f"{name}_max"],
                        color=line.get_color(), alpha=0.15)
    handles = ax.get_legend_handles_labels()[0]
    handles.append(Patch(color="grey", alpha=0.3,
                         label="band: min to max over position angles (line: median)"))
    ax.set_xlabel("separation (mas)")
    ax.set_ylabel("limiting contrast (companion / star)")
    ax.set_title(f"detection limits of the {result.test} search: global {PFA} = "
                 f"{result.pfa:g}, {PD} = {result.pd:g}", fontsize=10)
    ax.legend(handles=handles, fontsize=7)
    return fig


def analytic_column(result):
    """The curve (``'<test>_median'``) of the test whose map *result*'s search used (the
    energy test's is B's: its candidates come from B's map), else None."""
    for test in (result.meta.get("map_test", result.test), result.test):
        if f"{test}_median" in result.curves.colnames:
            return f"{test}_median"
    return None


def plot_injection_limits(table, *, analytic=None, ax=None):
    """What injections say of the limit (points: the steps, coloured by the fraction found;
    bars: the bracket of `~kpifs.inject.limit_bracket`) beside the analytic limit.

    *table* is `~kpifs.inject.injection_limits`'s; *analytic* a
    `~kpifs.DetectionResult` of the same data without injections (its own test's median
    curve). Each separation's bar runs from the highest step found significantly
    less than P_D of the time to the lowest found significantly more; an arrow
    where the ladder has no such step (a bound). A point on the bar marks the
    interpolated limit, drawn only where the bracket's ends are adjacent steps.

    Examples
    --------
    >>> import astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.plotting import plot_injection_limits
    >>> tab = QTable({"separation": [100, 100] * u.mas, "contrast": [1e-3, 3e-3],
    ...               "n_injected": [4, 4], "n_detected": [0, 4], "pd": [0.0, 1.0]})
    >>> tab.meta.update(limits=[1.7e-3], separations_mas=[100.0], pd=0.5, pfa=1e-3)
    >>> plot_injection_limits(tab).axes[0].get_ylabel()
    'contrast (companion / star)'
    """
    from matplotlib.lines import Line2D
    fig, ax = _axes(ax, figsize=(6.4, 4.8))
    sep = np.asarray(table["separation"].to_value(u.mas))
    c = np.asarray(table["contrast"], float)
    p = np.asarray(table["pd"], float)
    pd = table.meta.get("pd", 0.5)
    sc = ax.scatter(sep, c, c=p, cmap="RdYlGn", vmin=0, vmax=1, s=30, edgecolors="k",
                    linewidths=0.3, label="injection steps (colour: fraction found)", zorder=3)
    fig.colorbar(sc, ax=ax, label="fraction of the injections found")
    handles = [sc]
    br = injection_brackets(table)
    s = br["separation"].to_value(u.mas)
    lo, hi, val = (np.asarray(br[k], float)
                   for k in ("limit_low", "limit_high", "limit_interpolated"))
    span = np.ptp(s) if len(s) > 1 else 100.0
    dx = 0.012 * max(span, 50.0)
    both = np.isfinite(lo) & np.isfinite(hi)
    if both.any():
        ax.vlines(s[both] + dx, lo[both], hi[both], color="k", lw=2.5)
        handles.append(Line2D([], [], color="k", lw=2.5,
                              label=f"injections: the {PD} = {pd:g} limit lies on the bar"))
    for sel, y, marker, text in ((~np.isfinite(lo) & np.isfinite(hi), hi, "v",
                                  "injections: below (no step found too rarely)"),
                                 (np.isfinite(lo) & ~np.isfinite(hi), lo, "^",
                                  "injections: above (no step found often enough)")):
        if sel.any():
            style = dict(color="k", marker=marker, ms=10, ls="none")
            ax.plot(s[sel] + dx, y[sel], **style)
            handles.append(Line2D([], [], label=text, **style))
    if np.isfinite(val).any():
        style = dict(color="k", marker="o", ms=7, mfc="w", mew=1.5, ls="none")
        ax.plot(s[np.isfinite(val)] + dx, val[np.isfinite(val)], **style)
        handles.append(Line2D([], [], label="interpolated (adjacent steps)", **style))
    col = None if analytic is None else analytic_column(analytic)
    if col is not None:
        handles += ax.plot(analytic.curves["separation"].to_value(u.mas),
                           analytic.curves[col], "b--",
                           label=f"analytic limit ({col.split('_')[0]} test, median over angles)")
    ax.set_yscale("log")
    ax.set_xlabel("separation (mas)")
    ax.set_ylabel("contrast (companion / star)")
    ax.set_title(f"injection-recovery at global {PFA} = "
                 f"{table.meta.get('pfa', float('nan')):g}", fontsize=10)
    ax.legend(handles=handles, fontsize=7)
    return fig


def plot_candidate_spectrum(result, index=0, *, ax=None, truth=None):
    """Per-channel contrasts of candidate ``index + 1`` (fitted, with 1-sigma errors).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_candidate_spectrum
    >>> fig = plot_candidate_spectrum(_example_result())
    >>> fig.axes[0].get_ylabel(), fig.axes[0].get_title()[:11]
    ('contrast (companion / star)', 'candidate 1')
    """
    fig, ax = _axes(ax)
    wl = result.wavelengths.to_value(u.um)
    title = f"candidate {index + 1}: none above the threshold"
    if len(result.candidates) > index:
        row = result.candidates[index]
        key = "fit_contrast" if "fit_contrast" in row.colnames else "contrast"
        ax.errorbar(wl, np.asarray(row[key]), yerr=np.asarray(row[key + "_err"]), fmt="o",
                    label=f"candidate {index + 1}: fitted contrast, 1σ errors")
        sky = getattr(result.grid, "frame", "detector") == "sky"
        x, y = _candidate_xy(row, sky)
        where = (f"dRA {x:.1f}, dDec {y:.1f} mas" if sky
                 else f"detector x {x:.1f}, y {y:.1f} mas")
        title = f"candidate {index + 1} of the {result.test} search, at {where}"
    if truth is not None:
        ax.plot(wl, truth, "k--", label="simulated companion's spectrum")
    ax.set_xlabel("wavelength (µm)")
    ax.set_ylabel("contrast (companion / star)")
    ax.set_title(title, fontsize=10)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    return fig


def plot_roc(curves, *, ax=None, theory=None, title=None):
    """ROC curves ``{label: (pfa, pd)}``; *theory* the same, drawn dashed.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.plotting import plot_roc
    >>> fig = plot_roc({"NP": (np.logspace(-4, 0, 5), np.linspace(0.2, 1, 5))})
    >>> fig.axes[0].get_legend().get_texts()[0].get_text()[:3]
    'NP:'
    """
    from matplotlib.lines import Line2D
    fig, ax = _axes(ax)
    for label, (pfa, pd) in curves.items():
        line, = ax.semilogx(pfa, pd, label=_test_label(label))
        if theory and label in theory:
            ax.semilogx(*theory[label], "--", color=line.get_color(), lw=0.9)
    handles = ax.get_legend_handles_labels()[0]
    if theory:
        handles.append(Line2D([], [], color="grey", ls="--", lw=0.9,
                              label="dashed: theory"))
    ax.set_xlabel(PFA)
    ax.set_ylabel(PD)
    ax.set_xlim(1e-4, 1)
    ax.set_ylim(0, 1.01)
    if title:
        ax.set_title(title, fontsize=10)
    ax.legend(handles=handles, fontsize=7, loc="lower right")
    return fig


def save_detection_plots(result, outdir, *, truth=None, truth_spectrum=None):
    """Write detection_map.png, contrast_curves.png and candidate_spectrum.png (candidate
    1; candidate_spectrum_2.png and on for the next ones, up to `MAX_SPECTRA`).

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import save_detection_plots
    >>> tmp = tempfile.TemporaryDirectory()
    >>> [p.name for p in save_detection_plots(_example_result(), tmp.name)]
    ['detection_map.png', 'contrast_curves.png', 'candidate_spectrum.png']
    >>> tmp.cleanup()
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    paths = [_save(fig, outdir / f"{name}.png") for name, fig in (
        ("detection_map", plot_detection_map(result, truth=truth)),
        ("contrast_curves", plot_contrast_curves(result)),
        ("candidate_spectrum", plot_candidate_spectrum(result, truth=truth_spectrum)))]
    for i in range(1, min(len(result.candidates), MAX_SPECTRA)):
        paths.append(_save(plot_candidate_spectrum(result, i),
                           outdir / f"candidate_spectrum_{i + 1}.png"))
    return paths


#: Candidates whose spectrum `save_detection_plots` draws (the first in
#: candidate_spectrum.png, candidate n in candidate_spectrum_n.png).
MAX_SPECTRA = 5


def _channels(name):
    """A channel set's name as the experiment gives it ('1.52um'), with its unit written."""
    return name[:-2] + " µm" if name.endswith("um") else name


def save_roc_plots(curves, outdir):
    """Write roc.png (every test, one panel per channel set) and roc_np_channels.png.

    *curves* is the second output of `~kpifs.detect.roc.paper_experiment`:
    ``{channel set: {test: (pfa, pd), 'test theory': (pfa, pd)}}``.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from kpifs.plotting import save_roc_plots
    >>> c = (np.logspace(-3, 0, 5), np.linspace(0.5, 1, 5))
    >>> tmp = tempfile.TemporaryDirectory()
    >>> [p.name for p in save_roc_plots({"all": {"NP": c, "NP theory": c}}, tmp.name)]
    ['roc.png', 'roc_np_channels.png']
    >>> tmp.cleanup()
    """
    import matplotlib.pyplot as plt
    outdir = Path(outdir)
    names = list(curves)
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 4), squeeze=False)
    for ax, name in zip(axes[0], names):
        c = curves[name]
        plot_roc({k: v for k, v in c.items() if "theory" not in k}, ax=ax,
                 theory={k.split()[0]: v for k, v in c.items() if "theory" in k},
                 title=f"channels: {_channels(name)}")
    paths = [_save(fig, outdir / "roc.png", dpi=90)]
    fig, ax = plt.subplots(figsize=(5, 4))
    ref = reference_test()
    plot_roc({_channels(n): curves[n][ref.name] for n in names}, ax=ax,
             theory={_channels(n): curves[n][f"{ref.name} theory"] for n in names},
             title=f"{ref.label}: channel sets")
    paths.append(_save(fig, outdir / "roc_np_channels.png", dpi=90))
    return paths
