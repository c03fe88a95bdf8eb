"""Kernel model: uv points, redundancies, phase-transfer matrix and kernel (Martinache 2010).

Every pair of sub-apertures ``(j, k)`` gives a baseline ``b = r_j - r_k``. The
baselines are folded into the half plane ``v > 0`` (or ``v == 0, u > 0``) and
merged into unique uv points. With pair weights ``t_j t_k`` (1 for a binary
model) the baseline-mapping matrix is ``A[b, j] += w``, ``A[b, k] -= w`` and
the redundancy ``R[b]`` is the summed weight; the phase-transfer matrix
``R^-1 A`` maps pupil phases to Fourier phases,
``Phi(b) = sum_pairs w (phi_j - phi_k) / R[b]``. The kernel ``K`` is an
orthonormal basis of the left null space of ``R^-1 A`` obtained from its SVD,
so that ``K R^-1 A = 0`` and ``n_kp = n_uv - rank``.
"""
import logging
import warnings

import numpy as np
from astropy import units as u

from ._baselines import _blm_for_uv, _kernel_from_tfm, _uv_from_pupil
from .._registry import io_methods, register
from .._utils import to_quantity, write_hdulist
from ..exceptions import KpifsError, KpifsWarning
from .fourier import fourier_operator
from ..io.kpfits import has_kernel_model, model_hdulist, read_model_file, read_model_parts
from .pupil import PupilModel, make_pupil
from .sampling import nested_kernel

__all__ = ["KernelModel", "nyquist_usable", "load_kernel_model"]

log = logging.getLogger(__name__)

MAS = np.pi / 180 / 3600 / 1000  # radians per milliarcsecond


def nyquist_usable(uv, wavelengths, pixscale):
    """Which uv points are sampled at each wavelength.

    A uv point of length ``|b|`` is usable at wavelength ``lam`` for an image of
    pixel scale ``p`` when ``|b| / lam <= 1 / (2 p)``.

    Parameters
    ----------
    uv : `~astropy.units.Quantity`, shape (nuv, 2)
        Baselines (m).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
        Angular size of a pixel.

    Returns
    -------
    usable : ndarray of bool, shape (nwave, nuv)

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.model.kernel import nyquist_usable
    >>> nyquist_usable([[7.9, 0]] * u.m, [1.16, 1.6] * u.um, 16.2 * u.mas)
    array([[False],
           [ True]])
    """
    uv = to_quantity(uv, u.m, name="uv").value
    wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
    p = to_quantity(pixscale, u.mas, name="pixel scale").value * MAS
    blen = np.hypot(uv[:, 0], uv[:, 1])
    return blen[None, :] / wl[:, None] <= 1 / (2 * p) * (1 + 1e-12)


class KernelModel:
    """Linear model of the Fourier phase of a discrete pupil and its kernel.

    Build one with `KernelModel.from_pupil`, or read one with
    `KernelModel.read` / `load_kernel_model`.

    Attributes
    ----------
    pupil : `~kpifs.model.pupil.PupilModel`
        The discrete pupil.
    uv : `~astropy.units.Quantity`, shape (nuv, 2)
        Unique baselines in the half plane (m).
    redundancy : ndarray, shape (nuv,)
        Summed pair weights per uv point (integers for a binary model).
    blm : ndarray, shape (nuv, nsub)
        Baseline-mapping matrix ``A``.
    kernel : ndarray, shape (nkp, nuv)
        Kernel matrix ``K``.
    rank : int
        Rank of the phase-transfer matrix.

    Examples
    --------
    >>> from kpifs import KernelModel, make_pupil
    >>> km = KernelModel.from_pupil(make_pupil("subaru"))
    >>> km.n_kp == km.n_uv - km.rank
    True
    """

    def __init__(self, pupil, uv, redundancy, blm, kernel=None, *, rank=None, rtol=1e-9,
                 meta=None):
        self.pupil = pupil
        self._uv = np.asarray(u.Quantity(uv, u.m).value, float)
        self.redundancy = np.asarray(redundancy, float)
        self.blm = np.asarray(blm, float)
        nuv = len(self._uv)
        if self.redundancy.shape != (nuv,) or self.blm.shape != (nuv, pupil.n_sub):
            raise KpifsError(f"inconsistent kernel model: {nuv} uv points, redundancy "
                             f"{self.redundancy.shape}, BLM {self.blm.shape}, "
                             f"{pupil.n_sub} sub-apertures")
        self._rtol = rtol
        self._kernel = None
        self._rank = None if rank is None else int(rank)
        if kernel is not None:
            self._kernel = np.asarray(kernel, float)
            if self._kernel.ndim != 2 or self._kernel.shape[1] != nuv:
                raise KpifsError(f"kernel matrix has shape {self._kernel.shape}, expected "
                                 f"(nkp, {nuv})")
        self.meta = dict(meta or {})

    # the SVD is the costly part of a model, and a model made only to be cut down by
    # `for_wavelengths` never needs its own: kernel and rank are computed on first use
    @property
    def kernel(self):
        """Kernel matrix ``K`` (nkp, nuv), rows orthonormal."""
        if self._kernel is None:
            self._solve()
        return self._kernel

    def _solve(self):
        self._kernel, self._rank, _ = _kernel_from_tfm(self.tfm, self._rtol)

    @kernel.setter
    def kernel(self, value):
        self._kernel = np.asarray(value, float)

    @property
    def rank(self):
        """Rank of the phase-transfer matrix."""
        if self._rank is None:
            if self._kernel is None:
                self._solve()
            else:
                tfm = self.tfm
                self._rank = int(np.linalg.matrix_rank(tfm, tol=self._rtol
                                                       * np.linalg.norm(tfm, 2)))
        return self._rank

    @rank.setter
    def rank(self, value):
        self._rank = int(value)

    @classmethod
    def from_pupil(cls, pupil, *, rtol=1e-9, uv_tol=None, min_redundancy=None):
        """Build the kernel model of a `~kpifs.model.pupil.PupilModel`.

        Parameters
        ----------
        pupil : `~kpifs.model.pupil.PupilModel`
        rtol : float
            Singular values below ``rtol`` times the largest count as zero when
            computing the rank.
        uv_tol : float, optional
            Baselines closer than this (m) are merged; default a thousandth of
            the grid step.
        min_redundancy : float, optional
            Leave out uv points whose redundancy is below this (default: the
            pupil's ``meta['min_redundancy']``, 0.5 for kpifs's grey models,
            else 0): made only of barely covered cells, they sample the real
            transfer function where it is near zero.
        """
        if not isinstance(pupil, PupilModel):
            raise KpifsError(f"expected a PupilModel, got {type(pupil).__name__}")
        xy = pupil.xy.value
        if uv_tol is None:
            step = pupil.step.to_value(u.m) if pupil.step is not None else None
            if step is None:
                d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
                step = np.min(d[d > 0])
            uv_tol = 1e-3 * step
        uv, red, A = _uv_from_pupil(xy, pupil.transmission, uv_tol)
        if min_redundancy is None:
            min_redundancy = float(pupil.meta.get("min_redundancy", 0.0))
        keep = red >= min_redundancy
        if keep.sum() < 2:
            raise KpifsError(f"fewer than two uv points have redundancy >= {min_redundancy}")
        uv, red, A = uv[keep], red[keep], A[keep]
        meta = {"rtol": rtol, "uv_tol_m": uv_tol, "min_redundancy": min_redundancy,
                "n_uv_low_redundancy": int((~keep).sum())}
        km = cls(pupil, uv, red, A, rtol=rtol, meta=meta)
        log.info("kernel model: %d sub-apertures, %d uv points", pupil.n_sub, km.n_uv)
        return km

    # --- basic properties -------------------------------------------------
    @property
    def uv(self):
        """Baselines, `~astropy.units.Quantity` (nuv, 2) in m."""
        return self._uv * u.m

    @property
    def n_uv(self):
        return len(self._uv)

    @property
    def n_kp(self):
        return self.kernel.shape[0]

    @property
    def tfm(self):
        """Phase-transfer matrix ``R^-1 A`` (nuv, nsub)."""
        return self.blm / self.redundancy[:, None]

    @property
    def baseline_length(self):
        """Length of each uv point (m)."""
        return np.hypot(*self._uv.T) * u.m

    def __repr__(self):
        return (f"<KernelModel {self.pupil.name!r}: {self.pupil.n_sub} sub-apertures, "
                f"{self.n_uv} uv points, rank {self.rank}, {self.n_kp} kernel phases>")

    # --- derived models ---------------------------------------------------
    def subset(self, keep):
        """Return the model restricted to the uv points where *keep* is True.

        The kernel is recomputed for the reduced phase-transfer matrix.
        """
        keep = np.asarray(keep, bool)
        if keep.shape != (self.n_uv,):
            raise KpifsError(f"uv selection has shape {keep.shape}, expected ({self.n_uv},)")
        if keep.all():
            return self
        if keep.sum() < 2:
            raise KpifsError("fewer than two uv points are left in the kernel model")
        km = KernelModel(self.pupil, self._uv[keep], self.redundancy[keep], self.blm[keep],
                         rtol=self.meta.get("rtol", 1e-9), meta=self.meta)
        km.meta["n_uv_dropped"] = int((~keep).sum()) + self.meta.get("n_uv_dropped", 0)
        return km

    def transformed(self, *, rotation=0 * u.deg, scale=1.0):
        """The same model turned by *rotation* and scaled by *scale* as a whole.

        Sub-aperture positions and uv points rotate (counter-clockwise from +x
        to +y) and scale together; redundancies, baseline mapping and kernel
        are unchanged, so kernel phases of the new model are comparable with
        the old one's. A *scale* ``f`` is the same as a pixel scale ``f``
        times larger: this is how `~kpifs.modelcheck.check_pupil_model` tries
        orientations and scales of the pupil on the detector.

        Examples
        --------
        >>> import astropy.units as u
        >>> from kpifs import KernelModel, make_pupil
        >>> km = KernelModel.from_pupil(make_pupil("subaru", step=0.6 * u.m))
        >>> km2 = km.transformed(rotation=90 * u.deg)
        >>> bool(abs(km2.uv[0, 0] + km.uv[0, 1]) < 1e-9 * u.m), km2.n_kp == km.n_kp
        (True, True)
        """
        ang = np.deg2rad(to_quantity(rotation, u.deg, name="rotation").value)
        scale = float(scale)
        if not np.isfinite(ang) or not (np.isfinite(scale) and scale > 0):
            raise KpifsError(f"rotation must be finite and scale > 0, got {rotation}, {scale}")
        if ang == 0 and scale == 1:
            return self
        rot = scale * np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
        pup = self.pupil
        meta = dict(pup.meta, rotation_deg=pup.meta.get("rotation_deg", 0.0) + np.rad2deg(ang),
                    scale=pup.meta.get("scale", 1.0) * scale)
        new_pupil = PupilModel(pup.xy.value @ rot.T, pup.transmission,
                               step=None if pup.step is None else pup.step * scale,
                               name=pup.name, meta=meta)
        km = KernelModel(new_pupil, self._uv @ rot.T, self.redundancy, self.blm,
                         self._kernel, rank=self._rank, rtol=self._rtol, meta=self.meta)
        return km

    def for_wavelengths(self, wavelengths, pixscale, *, on_nyquist="drop", source=None):
        """Return a model usable at all *wavelengths* for images of *pixscale*.

        uv points beyond the Nyquist limit at any channel are found; with
        ``on_nyquist='drop'`` they are removed (one common model for every
        channel, so that kernel phases stay comparable across wavelength) with a
        `~kpifs.KpifsWarning` saying how many and at which channels; with
        ``'raise'`` a `~kpifs.KpifsError` is raised; with ``'own'`` each channel
        keeps the uv points it samples: the model's kernel is nested
        (`~kpifs.model.sampling.nested_kernel`, counts in ``meta['nested_counts']``).

        Examples
        --------
        >>> import astropy.units as u
        >>> from kpifs import KernelModel, make_pupil
        >>> km = KernelModel.from_pupil(make_pupil("subaru"))
        >>> km.for_wavelengths([1.6] * u.um, 16.2 * u.mas) is km
        True
        """
        if on_nyquist not in ("drop", "raise", "own"):
            raise KpifsError(f"on_nyquist must be 'drop', 'raise' or 'own', got {on_nyquist!r}")
        wl = np.atleast_1d(to_quantity(wavelengths, u.um, name="wavelengths"))
        usable = nyquist_usable(self.uv, wl, pixscale)
        bad = ~usable.all(axis=1)
        if not bad.any():
            return self
        where = f"{source}: " if source else ""
        lost = ", ".join(f"{w:.3f} ({n} of {self.n_uv})" for w, n in
                         zip(wl.value[bad], (~usable[bad]).sum(axis=1)))
        msg = (f"{where}uv points beyond the Nyquist limit of {u.Quantity(pixscale, u.mas):.2f} "
               f"pixels at {bad.sum()} channel(s), wavelengths in um (uv points lost): {lost}")
        if on_nyquist == "raise":
            raise KpifsError(msg + "; use on_nyquist='drop' (--nyquist drop) to remove them")
        if on_nyquist == "own" and usable.sum(axis=1).min() >= 2:
            model, counts = nested_kernel(self, usable)
            if counts.min() > 0:
                log.info("%seach channel its own uv points: %s kernel phases", where,
                         counts.tolist())
                return model
        keep = usable.all(axis=0)
        sub = self.subset(keep) if keep.sum() >= 2 else None
        if sub is None or sub.n_kp == 0:
            # refused here, before any work: a product without kernel phases is no product
            worst = int(np.argmin(usable.sum(axis=1)))
            raise KpifsError(
                f"{where}no kernel phase left: at channel {worst + 1} ({wl[worst]:.3f}) "
                f"{int((~usable[worst]).sum())} of {self.n_uv} uv points are beyond the "
                f"sampling limit of {u.Quantity(pixscale, u.mas):.2f} pixels and the "
                f"{int(keep.sum())} uv points usable at every channel give no kernel phase")
        warnings.warn(msg + f"; dropping {(~keep).sum()} uv points for all channels",
                      KpifsWarning, stacklevel=2)
        return sub

    # --- Fourier matrices -------------------------------------------------
    def dft_matrix(self, wavelength, pixscale, shape):
        """Real-stacked DFT matrix for a window of *shape* pixels centred on the origin.

        Returns an array of shape ``(2 nuv, ny*nx)`` whose first ``nuv`` rows are
        ``cos`` and last ``nuv`` rows ``-sin`` of ``2 pi (u x + v y) / lam``, so
        that ``M @ image.ravel()`` stacks ``Re V`` and ``Im V`` with
        ``V(u, v) = sum I(x, y) exp(-2 pi i (u x + v y) / lam)``. Pixel ``(ny//2,
        nx//2)`` of the window is the origin. This is the dense reference of
        `kpifs.model.fourier` (extraction uses a faster path when there is one);
        matrices are kept in its bounded module-level cache, keyed by the uv
        points, wavelength, pixel scale and shape, so models rebuilt per file
        share them.
        """
        wl = float(to_quantity(wavelength, u.m, name="wavelength").value)
        p = float(to_quantity(pixscale, u.mas, name="pixel scale").value) * MAS
        return fourier_operator(self._uv, wl, p, shape, method="dense").matrix

    def signature(self, offset, wavelengths):
        """First-order kernel-phase signature of a companion at *offset*.

        ``K sin(-2 pi (alpha u + beta v) / lam)`` per wavelength, so that a
        companion of contrast ``c`` gives kernel phases ``~ c * signature``.

        Parameters
        ----------
        offset : `~astropy.units.Quantity`, shape (2,)
            ``(alpha, beta)``: companion offset from the star along image x and y.
        wavelengths : `~astropy.units.Quantity`, shape (nwave,)

        Returns
        -------
        ndarray, shape (nwave, nkp)
        """
        a, b = to_quantity(offset, u.mas, name="offset").value * MAS
        wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
        theta = 2 * np.pi * (a * self._uv[:, 0] + b * self._uv[:, 1])[None, :] / wl[:, None]
        return np.sin(-theta) @ self.kernel.T

    def binary_kernel_phases(self, offset, contrast, wavelengths):
        """Exact kernel phases of a binary: ``K arg(1 + c exp(-2 pi i (alpha u + beta v)/lam))``.

        *contrast* is a scalar or one value per wavelength. Returns (nwave, nkp).
        """
        a, b = to_quantity(offset, u.mas, name="offset").value * MAS
        wl = np.atleast_1d(to_quantity(wavelengths, u.m, name="wavelengths").value)
        c = np.broadcast_to(np.asarray(contrast, float), wl.shape)
        theta = 2 * np.pi * (a * self._uv[:, 0] + b * self._uv[:, 1])[None, :] / wl[:, None]
        phi = np.angle(1 + c[:, None] * np.exp(-1j * theta))
        return phi @ self.kernel.T

    # --- FITS -------------------------------------------------------------
    @classmethod
    def from_hdulist(cls, hdul, *, source="<memory>"):
        """Build the model from the KPFITS model extensions of an open file."""
        return cls.from_parts(read_model_parts(hdul, source=source), source=source)

    @classmethod
    def from_parts(cls, parts, *, source="<memory>"):
        """Build the model from the arrays of `kpifs.io.kpfits.read_model_parts`.

        The kernel is kept as stored (rows of any norm: kernel phases, errors
        and covariances of the same file share its units). Without a BLM-MAT
        the baseline-mapping matrix is rebuilt from the aperture for the file's
        own uv points, in their order and half plane; without a grid step
        (``STEP``) the closest pair of sub-apertures gives it. A kernel that is
        not orthogonal to ``BLM / RED`` gets a `~kpifs.KpifsWarning`.

        Examples
        --------
        >>> import astropy.units as u
        >>> from kpifs import KernelModel, make_pupil
        >>> from kpifs.io.kpfits import model_hdulist, read_model_parts
        >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
        >>> parts = read_model_parts(model_hdulist(km))
        >>> parts["blm"] = None                        # as in files without BLM-MAT
        >>> bool(abs(KernelModel.from_parts(parts).blm - km.blm).max() < 1e-12)
        True
        """
        meta = {"source": str(source)}
        meta_pupil = ({} if parts.get("diameter") is None
                      else {"diameter_m": float(parts["diameter"])})
        pup = PupilModel(parts["xy"], parts["transmission"], step=parts["step"],
                         name=parts["name"], meta=meta_pupil)
        uv = np.asarray(parts["uv"], float)
        xy = pup.xy.value
        d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        if pup.step is None:      # other tools' files: the grid step is the closest pair
            pup.step = float(np.min(d[d > 0])) * u.m
            meta["step_inferred"] = True
        blm = parts["blm"]
        if blm is None:  # rebuild A from the aperture (files of other tools may omit it)
            blm, missing = _blm_for_uv(xy, pup.transmission, uv, 1e-3 * np.min(d[d > 0]))
            if missing.size:
                raise KpifsError(f"{source}: no BLM-MAT and no pair of sub-apertures makes "
                                 f"{missing.size} of the {len(uv)} uv points (first: "
                                 f"{uv[missing[0]].round(4).tolist()} m)")
            meta["blm_rebuilt"] = "from the aperture"
        elif parts.get("blm_rebuilt"):
            meta["blm_rebuilt"] = "reference column"
        km = cls(pup, uv, parts["redundancy"], blm, parts["kernel"], rank=parts["rank"],
                 meta=meta)
        resid = km.kernel_residual()
        if resid > 1e-6:
            warnings.warn(f"{source}: KER-MAT is not orthogonal to BLM-MAT / RED (relative "
                          f"residual {resid:.1e}): the kernel and the baseline model disagree "
                          f"(integer redundancies of a grey model?)", KpifsWarning,
                          stacklevel=2)
        return km

    def kernel_residual(self):
        """``max |K R^-1 A| / (||K|| ||R^-1 A||)``: 0 for a kernel of this model.

        Examples
        --------
        >>> from kpifs import KernelModel, make_pupil
        >>> KernelModel.from_pupil(make_pupil("subaru")).kernel_residual() < 1e-12
        True
        """
        tfm = self.tfm
        scale = np.linalg.norm(self.kernel, 2) * np.linalg.norm(tfm, 2)
        return float(np.abs(self.kernel @ tfm).max() / scale) if scale > 0 else 0.0

    _io_format = "kpfits-model"
    read, write = io_methods("KernelModel")


def _read_model(path):
    return KernelModel.from_parts(read_model_file(path), source=path)


def _write_model(model, path, *, overwrite=False):
    return write_hdulist(model_hdulist(model), path, overwrite=overwrite)


register(KernelModel, "kpfits-model", reader=_read_model, writer=_write_model)


def load_kernel_model(pupil="subaru", *, pupil_scale=None, **pupil_options):
    """Return a `KernelModel` for a telescope name, a pupil image FITS or a model FITS.

    A FITS file holding a ``KER-MAT`` extension is read as a kernel model;
    any other FITS file as a pupil image (pixel size from ``PUPSCALE`` or
    *pupil_scale*); anything else is passed to `~kpifs.model.pupil.make_pupil`.

    Examples
    --------
    >>> from kpifs.model.kernel import load_kernel_model
    >>> load_kernel_model("subaru")
    <KernelModel 'subaru': ... kernel phases>
    """
    if isinstance(pupil, KernelModel):
        return pupil
    if isinstance(pupil, PupilModel):
        return KernelModel.from_pupil(pupil)
    key = str(pupil)
    if key.lower().endswith((".fits", ".fit", ".fits.gz")) and has_kernel_model(key):
        return KernelModel.read(key)
    return KernelModel.from_pupil(make_pupil(pupil, pupil_scale=pupil_scale, **pupil_options))
