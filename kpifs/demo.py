"""``kpifs demo``: the whole chain on data kpifs makes itself."""
import logging
from pathlib import Path

import numpy as np
from astropy import units as u

from .exceptions import KpifsError

__all__ = ["run_demo"]

log = logging.getLogger(__name__)


def run_demo(outdir, *, frames=40, seed=1, overwrite=False, progress=True):
    """Simulate the seed paper's scene, extract and calibrate kernel phases.

    Writes ``sim/target.fits``, ``sim/calibrator.fits``, ``target_kp.fits``,
    ``calibrator_kp.fits`` and ``kernel_phases.png`` in *outdir*, and returns
    a dict of summary figures.
    """
    from .extract import extract_kernel_phases
    from .io.layouts import write_observation
    from .kernel import KernelModel
    from .pupil import make_pupil
    from .simulate import simulate_scene

    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise KpifsError(f"{outdir}: exists and is not a directory")
    products = [outdir / n for n in ("target_kp.fits", "calibrator_kp.fits",
                                     "kernel_phases.png")]
    if not overwrite and any(p.exists() for p in products):
        raise KpifsError(f"{outdir}: holds the products of an earlier demo; pass --overwrite")
    outdir.mkdir(parents=True, exist_ok=True)
    obs = simulate_scene("paper", n_frames=frames, seed=seed, progress=progress)
    files = write_observation(obs, outdir / "sim", overwrite=overwrite)
    km = KernelModel.from_pupil(make_pupil("subaru"))
    kps = {}
    for role, cube in (("target", obs.target), ("calibrator", obs.calibrator)):
        kps[role] = extract_kernel_phases(cube, km, wavelengths=obs.wavelengths,
                                          pixscale=obs.params.pixscale,
                                          source=str(files[role][0]))
        kps[role].header.update({k: v for k, v in obs.truth.items()} if role == "target"
                                else {})
        kps[role].write(outdir / f"{role}_kp.fits", overwrite=overwrite,
                        inputs=[files[role][0]])
    cal = kps["target"].kp.mean(0) - kps["calibrator"].kp.mean(0)
    err = np.sqrt(kps["target"].kp.var(0, ddof=1) / frames
                  + kps["calibrator"].kp.var(0, ddof=1) / frames)
    model = km.binary_kernel_phases(obs.params.companion_offset, obs.params.contrasts,
                                    obs.wavelengths)
    summary = {"chi2_null": float(np.sum((cal / err) ** 2)),
               "chi2_model": float(np.sum(((cal - model) / err) ** 2)),
               "n_data": int(cal.size)}
    _plot(outdir / "kernel_phases.png", cal, err, model, obs.wavelengths)
    print(f"kpifs demo: {frames} frames per star, {km.n_kp} kernel phases x "
          f"{len(obs.wavelengths)} channels")
    print(f"  chi2 of calibrated kernel phases against zero:      {summary['chi2_null']:.0f}")
    print(f"  chi2 against the true companion ({summary['n_data']} values): "
          f"{summary['chi2_model']:.0f}")
    print(f"  products in {outdir}/")
    return summary


def _plot(path, cal, err, model, wavelengths):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(cal), figsize=(4 * len(cal), 3.6), squeeze=False)
    for i, ax in enumerate(axes[0]):
        ax.errorbar(model[i], cal[i], yerr=err[i], fmt=".", ms=3, alpha=0.6)
        lim = np.max(np.abs(model[i])) * 1.2
        ax.plot([-lim, lim], [-lim, lim], "k--", lw=0.8)
        ax.set_title(f"{wavelengths[i].to_value(u.um):.2f} um")
        ax.set_xlabel("model kernel phase (rad)")
    axes[0, 0].set_ylabel("calibrated kernel phase (rad)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
