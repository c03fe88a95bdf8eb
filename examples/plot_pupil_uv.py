"""
Pupil model and uv coverage
===========================

The Subaru pupil discretised on a 0.38 m grid, and the uv points of its
kernel model.
"""
import matplotlib.pyplot as plt
import numpy as np

from kpifs import KernelModel, make_pupil
from kpifs.model.pupil import pupil_image

pupil = make_pupil("subaru")
km = KernelModel.from_pupil(pupil)
image, dx = pupil_image("subaru", npix=256)

fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.6))
half = dx * 128
ax1.imshow(image, origin="lower", extent=[-half, half, -half, half], cmap="gray")
xy = pupil.xy.value
ax1.plot(xy[:, 0], xy[:, 1], "o", ms=3, color="tab:orange")
ax1.set_title(f"{pupil.n_sub} sub-apertures")
ax1.set_xlabel("x (m)")
ax1.set_ylabel("y (m)")
uv = km.uv.value
ax2.scatter(np.concatenate([uv[:, 0], -uv[:, 0]]), np.concatenate([uv[:, 1], -uv[:, 1]]),
            c=np.concatenate([km.redundancy] * 2), s=6, cmap="viridis")
ax2.set_aspect("equal")
ax2.set_title(f"{km.n_uv} uv points (and their mirrors), {km.n_kp} kernel phases")
ax2.set_xlabel("u (m)")
ax2.set_ylabel("v (m)")
fig.tight_layout()
