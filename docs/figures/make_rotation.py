"""Figure of docs/user/rotation.rst: what a rotation keeps of a companion, by separation.

For the CHARIS model (Subaru pupil, 0.38 m grid, 264 kernel phases) at 1.16, 1.6
and 2.37 um, white kernel-phase noise, 20 frames in blocks of 2, and spans of
10, 20, 40 and 60 deg of rotation: the squared signal of a companion fixed on
the sky that

- the mean of the sequence keeps (``||mean_b s_b||^2 / mean_b ||s_b||^2``: the
  smearing of a search of the mean alone);
- the blocks' departures keep (``sum n_b ||s_b - s_mean||^2 / sum n_b ||s_b||^2``:
  what survives the angular-differential removal of everything fixed on the
  detector, one minus its self-subtraction),

averaged over position angles. Run: ``python docs/figures/make_rotation.py``.
"""
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("agg")
import matplotlib.pyplot as plt  # noqa: E402

from kpifs import KernelModel, make_pupil  # noqa: E402
from kpifs.detect.sky import sky_to_detector  # noqa: E402
from kpifs.model.kernel import MAS  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "user" / "rotation_kept.png"


def kept(km, lams, sep, span, n_frames=20, block=2, n_pa=24):
    """(mean's fraction, departures' fraction) of the squared signal, PA-averaged."""
    angles = np.linspace(0, span, n_frames).reshape(-1, block).mean(axis=1)
    uv = km.uv.value
    mean_f, dev_f = [], []
    for pa in np.linspace(0, 360, n_pa, endpoint=False):
        dra, ddec = sep * np.sin(np.deg2rad(pa)), sep * np.cos(np.deg2rad(pa))
        for lam in lams:
            s = []
            for a in angles:
                x, y = sky_to_detector(dra, ddec, a)
                s.append(km.kernel @ np.sin(-2 * np.pi * (x * uv[:, 0] + y * uv[:, 1]) * MAS
                                            / lam))
            s = np.array(s)
            m = s.mean(axis=0)
            tot = np.sum(s ** 2) / len(s)
            mean_f.append(m @ m / tot)
            dev_f.append(np.sum((s - m) ** 2) / len(s) / tot)
    return np.mean(mean_f), np.mean(dev_f)


def main():
    km = KernelModel.from_pupil(make_pupil("subaru"))
    lams = [1.16e-6, 1.6e-6, 2.37e-6]
    seps = np.arange(25, 301, 25)
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6), sharey=True)
    for span in (10, 20, 40, 60):
        f = np.array([kept(km, lams, s, span) for s in seps])
        ax[0].plot(seps, f[:, 0], label=f"{span} deg")
        ax[1].plot(seps, f[:, 1], label=f"{span} deg")
    ax[0].set_title("the mean of the sequence (smeared)")
    ax[1].set_title("the blocks' departures (angular-differential)")
    for a in ax:
        a.set_xlabel("separation (mas)")
        a.grid(alpha=0.3)
    ax[0].set_ylabel("fraction of the squared signal kept")
    ax[1].legend(title="rotation")
    fig.tight_layout()
    fig.savefig(OUT, dpi=110)
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
