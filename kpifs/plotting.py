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


def plot_detection_map(result, *, ax=None, truth=None):
    """The map statistic with candidates circled (and the truth marked, if given).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_detection_map
    >>> fig = plot_detection_map(_example_result(), truth=(60, -40))
    >>> len(fig.axes)
    2
    """
    fig, ax = _axes(ax)
    g = result.grid
    ext = [g.x[0], g.x[-1], g.y[0], g.y[-1]]
    im = ax.imshow(result.statistic, origin="lower", extent=ext, cmap="magma")
    fig.colorbar(im, ax=ax, label=f"{result.meta.get('test', result.test)} statistic")
    ax.contour(g.X, g.Y, np.nan_to_num(result.statistic), levels=[result.threshold],
               colors="cyan", linewidths=0.8)
    sky = getattr(g, "frame", "detector") == "sky"
    cx, cy = ("dra", "ddec") if sky else ("x", "y")
    for row in result.candidates:
        x = row["fit_" + cx] if "fit_" + cx in row.colnames else row[cx]
        y = row["fit_" + cy] if "fit_" + cy in row.colnames else row[cy]
        ax.plot(x.to_value(u.mas), y.to_value(u.mas), "o", mfc="none", mec="cyan", ms=14)
    if truth is not None:
        ax.plot(*truth, "+", color="lime", ms=12, label="truth")
        ax.legend(loc="upper right", fontsize=8)
    if sky:     # the grid runs East to West: East is on the left
        ax.set_xlabel("dRA (mas, East to the left)")
        ax.set_ylabel("dDec (mas)")
    else:
        ax.set_xlabel("offset along x (mas)")
        ax.set_ylabel("offset along y (mas)")
    ax.set_title(f"P_FA = {result.pfa:g}: {len(result.candidates)} candidate(s)")
    return fig


def plot_contrast_curves(result, *, ax=None):
    """Median (line) and min-max (band) limiting contrast versus separation, per test.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_contrast_curves
    >>> fig = plot_contrast_curves(_example_result())
    >>> fig.axes[0].get_xlabel()
    'separation (mas)'
    """
    fig, ax = _axes(ax)
    sep = result.curves["separation"].to_value(u.mas)
    for name in ("NP", "B", "B-paper", "E"):
        if f"{name}_median" not in result.curves.colnames:
            continue
        med = np.asarray(result.curves[f"{name}_median"])
        line, = ax.semilogy(sep, med, label=name)
        ax.fill_between(sep, result.curves[f"{name}_min"], result.curves[f"{name}_max"],
                        color=line.get_color(), alpha=0.15)
    ax.set_xlabel("separation (mas)")
    ax.set_ylabel("limiting contrast")
    ax.set_title(f"P_FA = {result.pfa:g}, P_D = {result.pd:g}")
    ax.legend(fontsize=8)
    return fig


def plot_injection_limits(table, *, analytic=None, ax=None):
    """Empirical 50 % limit from injections (points: found / not found) beside the analytic one.

    *table* is `~kpifs.inject.injection_limits`'s; *analytic* a
    `~kpifs.DetectionResult` of the same data without injections (its B median curve).

    Examples
    --------
    >>> import astropy.units as u
    >>> from astropy.table import QTable
    >>> from kpifs.plotting import plot_injection_limits
    >>> tab = QTable({"separation": [100, 100] * u.mas, "contrast": [1e-3, 3e-3],
    ...               "n_injected": [4, 4], "n_detected": [0, 4], "pd": [0.0, 1.0]})
    >>> tab.meta.update(limits=[1.7e-3], separations_mas=[100.0], pd=0.5, pfa=1e-3)
    >>> plot_injection_limits(tab).axes[0].get_ylabel()
    'contrast'
    """
    fig, ax = _axes(ax)
    sep = np.asarray(table["separation"].to_value(u.mas))
    c = np.asarray(table["contrast"], float)
    p = np.asarray(table["pd"], float)
    sc = ax.scatter(sep, c, c=p, cmap="RdYlGn", vmin=0, vmax=1, s=25, edgecolors="k",
                    linewidths=0.3)
    fig.colorbar(sc, ax=ax, label="fraction detected")
    ax.plot(table.meta["separations_mas"], table.meta["limits"], "ko-",
            label=f"injections, P_D = {table.meta.get('pd', 0.5):g}")
    if analytic is not None and "B_median" in analytic.curves.colnames:
        ax.plot(analytic.curves["separation"].to_value(u.mas), analytic.curves["B_median"],
                "b--", label="analytic (B, median)")
    ax.set_yscale("log")
    ax.set_xlabel("separation (mas)")
    ax.set_ylabel("contrast")
    ax.set_title(f"P_FA = {table.meta.get('pfa', float('nan')):g}")
    ax.legend(fontsize=8)
    return fig


def plot_candidate_spectrum(result, index=0, *, ax=None, truth=None):
    """Per-channel contrasts of a candidate (fitted, with 1-sigma errors).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import plot_candidate_spectrum
    >>> fig = plot_candidate_spectrum(_example_result())
    >>> fig.axes[0].get_ylabel()
    'contrast'
    """
    fig, ax = _axes(ax)
    wl = result.wavelengths.to_value(u.um)
    if len(result.candidates) > index:
        row = result.candidates[index]
        key = "fit_contrast" if "fit_contrast" in row.colnames else "contrast"
        ax.errorbar(wl, np.asarray(row[key]), yerr=np.asarray(row[key + "_err"]), fmt="o",
                    label="candidate")
    if truth is not None:
        ax.plot(wl, truth, "k--", label="truth")
    ax.set_xlabel("wavelength (um)")
    ax.set_ylabel("contrast")
    ax.legend(fontsize=8)
    return fig


def plot_roc(curves, *, ax=None, theory=None, title=None):
    """ROC curves ``{label: (pfa, pd)}``; *theory* the same, drawn dashed.

    Examples
    --------
    >>> import numpy as np
    >>> from kpifs.plotting import plot_roc
    >>> fig = plot_roc({"test": (np.logspace(-4, 0, 5), np.linspace(0.2, 1, 5))})
    >>> fig.axes[0].get_xlabel()
    'P_FA'
    """
    fig, ax = _axes(ax)
    for label, (pfa, pd) in curves.items():
        line, = ax.semilogx(pfa, pd, label=label)
        if theory and label in theory:
            ax.semilogx(*theory[label], "--", color=line.get_color(), lw=0.9)
    ax.set_xlabel("P_FA")
    ax.set_ylabel("P_D")
    ax.set_xlim(1e-4, 1)
    ax.set_ylim(0, 1.01)
    if title:
        ax.set_title(title)
    ax.legend(fontsize=7, loc="lower right")
    return fig


def save_detection_plots(result, outdir, *, truth=None, truth_spectrum=None):
    """Write detection_map.png, contrast_curves.png and candidate_spectrum.png.

    Examples
    --------
    >>> import tempfile
    >>> from kpifs.detect.pipeline import _example_result
    >>> from kpifs.plotting import save_detection_plots
    >>> [p.name for p in save_detection_plots(_example_result(), tempfile.mkdtemp())]
    ['detection_map.png', 'contrast_curves.png', 'candidate_spectrum.png']
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    return [_save(fig, outdir / f"{name}.png") for name, fig in (
        ("detection_map", plot_detection_map(result, truth=truth)),
        ("contrast_curves", plot_contrast_curves(result)),
        ("candidate_spectrum", plot_candidate_spectrum(result, truth=truth_spectrum)))]


def save_roc_plots(curves, outdir):
    """Write roc.png (every test, one panel per channel set) and roc_np_channels.png.

    *curves* is the second output of `~kpifs.detect.roc.paper_experiment`:
    ``{channel set: {test: (pfa, pd), 'test theory': (pfa, pd)}}``.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from kpifs.plotting import save_roc_plots
    >>> c = (np.logspace(-3, 0, 5), np.linspace(0.5, 1, 5))
    >>> [p.name for p in save_roc_plots({"all": {"NP": c, "NP theory": c}}, tempfile.mkdtemp())]
    ['roc.png', 'roc_np_channels.png']
    """
    import matplotlib.pyplot as plt
    outdir = Path(outdir)
    names = list(curves)
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 4), squeeze=False)
    for ax, name in zip(axes[0], names):
        c = curves[name]
        plot_roc({k: v for k, v in c.items() if "theory" not in k}, ax=ax,
                 theory={k.split()[0]: v for k, v in c.items() if "theory" in k},
                 title=f"channels: {name}")
    paths = [_save(fig, outdir / "roc.png", dpi=90)]
    fig, ax = plt.subplots(figsize=(5, 4))
    plot_roc({n: curves[n]["NP"] for n in names}, ax=ax,
             theory={n: curves[n]["NP theory"] for n in names}, title="NP: channel sets")
    paths.append(_save(fig, outdir / "roc_np_channels.png", dpi=90))
    return paths
