"""The containers that travel between the stages: kernel-phase data and detection results.

- `KernelPhaseData`: kernel phases of a cube, with the kernel model, the
  extraction window and (once calibrated) their covariance; read and written
  in the KPFITS1 layout (`kpifs.io.kpfits`) with ``KernelPhaseData.read`` /
  ``.write``.
- `DetectionGrid`: the grid of companion offsets a search covers.
- `DetectionResult`: what a search found (maps, limits, candidates), read and
  written as kpifs detection products (`kpifs.io.products`) with
  ``DetectionResult.read`` / ``.write``.

Both ``read``/``write`` pairs go through astropy's unified I/O registry
(formats ``'kpfits'`` and ``'kpifs-detection'``).
"""
from dataclasses import dataclass, field

import numpy as np
from astropy import units as u
from astropy.io import fits

from ._registry import io_methods, register
from ._utils import to_quantity
from .exceptions import KpifsError
from .io.kpfits import is_kpfits, read_kpfits_parts, write_kpfits
from .io.oifits import is_oifits
from .io.oifits_combine import read_oifits
from .io.oifits_write import write_oifits
from .io.products import (detection_header_meta, is_detection, read_detection_parts,
                          write_detection)
from .io.wavelengths import check_wavelengths
from .model.kernel import KernelModel
from .model.pupil import PupilModel
from .model.window import ExtractionWindow
from .report import DetectionReport

__all__ = ["KernelPhaseData", "DetectionGrid", "DetectionResult"]


class KernelPhaseData:
    """Kernel phases of a cube, with everything needed to interpret them.

    Parameters
    ----------
    kp : ndarray, shape (nframe, nwave, nkp)
        Kernel phases (rad).
    wavelengths : `~astropy.units.Quantity`, shape (nwave,)
    pixscale : `~astropy.units.Quantity`
        Pixel scale of the images the phases come from.
    kernel_model : `~kpifs.model.kernel.KernelModel`
        The model whose kernel produced *kp*.
    window : `~kpifs.model.window.ExtractionWindow`, optional
        The extraction window (its attenuation matters for contrasts).
    phases, amplitudes : ndarray, shape (nframe, nwave, nuv), optional
        Raw Fourier phases (rad) and normalised amplitudes, for diagnostics.
    centres : `~astropy.table.QTable` or callable, optional
        Star centres used, one row per (frame, wavelength); a callable
        returning the table is called on first access (extraction passes one:
        `astropy.table` is slow to import and the command line never reads
        the table).
    covariance : ndarray, shape (nwave, nkp, nkp), optional
        Covariance of one frame's kernel phases, per channel (the same for
        every frame). Given per frame, shape (nframe, nwave, nkp, nkp) as other
        tools' KPFITS files hold it, their mean is kept (exact for a
        calibrated, single-frame file) and their diagonals become *kp_err*.
    kp_err : ndarray, shape (nframe, nwave, nkp), optional
        Per-frame 1-sigma errors of *kp* (rad), when known (KP-SIGM of other
        tools' files); written back as KP-SIGM.
    joint_covariance : ndarray, shape (nwave*nkp, nwave*nkp), optional
        The same across channels (spectral cross-talk included).
    covariance_rows : ndarray, shape (nrow, nwave, nkp), optional
        Rows ``R`` with ``R^T R`` the covariance across all channels (see
        `~kpifs.calibration.calibrate.calibrate`): a compact, always-available form of the
        cross-channel covariance used to draw realistic noise.
    fit_covariance_rows : ndarray, shape (nrow, nwave, nkp), optional
        Rows of the error model that characterises candidates (more modes
        than the search's, see `~kpifs.calibration.calibrate.calibrate`'s *fit_modes*);
        stored as KP-FITROWS.
    block_rows : ndarray, shape (nblock, nwave, nkp), optional
        Centred time-block means of the stars behind calibrated data, scaled
        so that random sign combinations are noise of the calibrated mean
        (`~kpifs.calibration.calibrate.block_rows`): the empirical null of detection;
        stored as KP-BLKROWS.
    header : `~astropy.io.fits.Header`, optional
        Header of the input cube (kept in products).
    detpa : array-like, shape (nframe,), optional
        Detector position angle of each frame (deg): the position angle, East
        of North, of the detector +y axis (NaN where unknown).
    bandwidth : `~astropy.units.Quantity`, optional
        Channel widths.
    meta : dict, optional
        Provenance.

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
    >>> km = KernelModel.from_pupil(make_pupil("subaru"))
    >>> kpd = KernelPhaseData(np.zeros((2, 3, km.n_kp)), [1.52, 1.6, 1.68] * u.um,
    ...                       10.42 * u.mas, km)
    >>> kpd.shape == (2, 3, km.n_kp)
    True
    """

    _io_format = "kpfits"
    read, write = io_methods("KernelPhaseData")

    @property
    def centres(self):
        """Star centres used (`~astropy.table.QTable`, one row per (frame, wavelength)), or
        None."""
        if callable(self._centres):
            self._centres = self._centres()
        return self._centres

    @centres.setter
    def centres(self, value):
        self._centres = value

    def __init__(self, kp, wavelengths, pixscale, kernel_model, *, window=None, phases=None,
                 amplitudes=None, centres=None, covariance=None, joint_covariance=None,
                 covariance_rows=None, header=None, detpa=None, bandwidth=None, meta=None,
                 kp_err=None, fit_covariance_rows=None, block_rows=None):
        kp = np.asarray(kp, float)
        if kp.ndim == 2:
            kp = kp[None]
        self.kp = kp
        self.wavelengths = check_wavelengths(to_quantity(wavelengths, u.um, name="wavelengths"))
        self.pixscale = to_quantity(pixscale, u.mas, name="pixel scale")
        if not isinstance(kernel_model, KernelModel):
            raise KpifsError(f"expected a KernelModel, got {type(kernel_model).__name__}")
        self.kernel_model = kernel_model
        nw, nk = len(self.wavelengths), kernel_model.n_kp
        if kp.ndim != 3 or kp.shape[1] != nw or kp.shape[2] != nk:
            raise KpifsError(f"kernel phases have shape {kp.shape}, expected (nframe, {nw}, "
                             f"{nk})")
        if window is not None and not isinstance(window, ExtractionWindow):
            raise KpifsError(f"window must be an ExtractionWindow, got {window!r}")
        self.window = window
        self.phases = phases
        self.amplitudes = amplitudes
        self.centres = centres
        if kp_err is not None:
            kp_err = np.asarray(kp_err, float)
        if covariance is not None:
            covariance = np.asarray(covariance, float)
            if covariance.ndim == 4:   # one per frame (nframe, nwave, nkp, nkp)
                if covariance.shape[0] not in (1, kp.shape[0]):
                    raise KpifsError(f"covariance has shape {covariance.shape}, expected "
                                     f"({kp.shape[0]} or 1, {nw}, {nk}, {nk})")
                if kp_err is None and covariance.shape[0] > 1:
                    kp_err = np.sqrt(np.diagonal(covariance, axis1=-2, axis2=-1))
                covariance = covariance.mean(axis=0)
            if covariance.shape != (nw, nk, nk):
                raise KpifsError(f"covariance has shape {covariance.shape}, expected "
                                 f"({nw}, {nk}, {nk})")
        if joint_covariance is not None:
            joint_covariance = np.asarray(joint_covariance, float)
            if joint_covariance.shape != (nw * nk, nw * nk):
                raise KpifsError(f"joint covariance has shape {joint_covariance.shape}, "
                                 f"expected ({nw * nk}, {nw * nk})")
        rows_in = [covariance_rows, fit_covariance_rows, block_rows]
        for j, r in enumerate(rows_in):
            if r is None:
                continue
            rows_in[j] = r = np.asarray(r, float)
            if r.ndim != 3 or r.shape[1:] != kp.shape[1:]:
                raise KpifsError(f"covariance rows have shape {r.shape}, expected "
                                 f"(nrow, {nw}, {nk})")
        covariance_rows, fit_covariance_rows, block_rows = rows_in
        if kp_err is not None and kp_err.shape != kp.shape:
            raise KpifsError(f"kernel-phase errors have shape {kp_err.shape}, expected "
                             f"{kp.shape}")
        self.covariance = covariance
        self.kp_err = kp_err
        self.joint_covariance = joint_covariance
        self.covariance_rows = covariance_rows
        self.fit_covariance_rows = fit_covariance_rows
        self.block_rows = block_rows
        self.header = fits.Header() if header is None else header.copy()
        if detpa is not None:
            detpa = np.atleast_1d(np.asarray(u.Quantity(detpa, u.deg).value, float))
            if detpa.shape != (kp.shape[0],):
                raise KpifsError(f"{detpa.size} detector position angle(s) for {kp.shape[0]} "
                                 f"frame(s)")
        self.detpa = detpa
        self.bandwidth = bandwidth
        self.meta = dict(meta or {})
        # time blocks of a rotating sequence (kpifs.rotation)
        self.rotation = None
        # spectral-differential nuisance profiles along the channels (issue 39,
        # `kpifs.calibration.spectral_diff`): {'profiles': (q, m), 'basis', 'order'}
        self.spectral = None

    @property
    def shape(self):
        return self.kp.shape

    @property
    def n_frame(self):
        return self.kp.shape[0]

    @property
    def n_wave(self):
        return self.kp.shape[1]

    @property
    def n_kp(self):
        return self.kp.shape[2]

    @property
    def channel_n_kp(self):
        """Kernel phases each channel measures, shape (nwave,): the first ones of the
        kernel (`~kpifs.model.sampling.nested_kernel`; all of them unless channels sample
        different uv points)."""
        n = self.meta.get("channel_n_kp")
        return np.full(self.n_wave, self.n_kp) if n is None else np.asarray(n, int)

    @property
    def name(self):
        """The data's name for messages (its source file)."""
        return self.meta.get("source", "<kernel-phase data>")

    def select_channels(self, keep):
        """The same data restricted to some channels (a boolean mask or indices).

        Everything per channel follows: kernel phases, covariances and their
        rows, errors, raw phases, the time blocks; the meta records the channels
        kept (``meta['channels']``, 1-based numbers of the original channels).

        Examples
        --------
        >>> import numpy as np, astropy.units as u
        >>> from kpifs import KernelModel, KernelPhaseData, make_pupil
        >>> km = KernelModel.from_pupil(make_pupil("subaru", step=1 * u.m))
        >>> kpd = KernelPhaseData(np.zeros((1, 3, km.n_kp)), [1.52, 1.6, 1.68] * u.um,
        ...                       10.42 * u.mas, km)
        >>> sub = kpd.select_channels([0, 2])
        >>> sub.wavelengths, sub.meta["channels"]
        (<Quantity [1.52, 1.68] um>, [1, 3])
        """
        idx = np.arange(self.n_wave)[np.asarray(keep)] if np.asarray(keep).dtype == bool \
            else np.asarray(keep, int).ravel()
        if idx.size == 0 or idx.min() < -self.n_wave or idx.max() >= self.n_wave:
            raise KpifsError(f"{self.name}: channels {keep!r} do not select among "
                             f"{self.n_wave} channel(s)")
        idx = np.unique(idx % self.n_wave)

        def per_channel(a, axis):
            return None if a is None else np.take(np.asarray(a), idx, axis=axis)

        jcov = None
        if self.joint_covariance is not None:
            q, p = self.n_wave, self.n_kp
            jcov = self.joint_covariance.reshape(q, p, q, p)[idx][:, :, idx]
            jcov = jcov.reshape(idx.size * p, idx.size * p)
        meta = dict(self.meta)
        numbers = list(self.meta.get("channels") or range(1, self.n_wave + 1))
        meta["channels"] = [int(numbers[i]) for i in idx]
        if self.meta.get("channel_n_kp") is not None:
            meta["channel_n_kp"] = [int(self.channel_n_kp[i]) for i in idx]
        bw = self.bandwidth
        if bw is not None and np.ndim(bw) > 0:
            bw = bw[idx]
        out = KernelPhaseData(
            self.kp[:, idx], self.wavelengths[idx], self.pixscale, self.kernel_model,
            window=self.window, phases=per_channel(self.phases, 1),
            amplitudes=per_channel(self.amplitudes, 1), covariance=per_channel(self.covariance, 0),
            joint_covariance=jcov, covariance_rows=per_channel(self.covariance_rows, 1),
            fit_covariance_rows=per_channel(self.fit_covariance_rows, 1),
            block_rows=per_channel(self.block_rows, 1), kp_err=per_channel(self.kp_err, 1),
            header=self.header, detpa=self.detpa, bandwidth=bw, meta=meta)
        if self.rotation is not None:
            r = self.rotation
            out.rotation = type(r)(r.angles, r.frames, r.data[:, idx], r.noise[:, idx],
                                   r.n_target_noise, r.calibrated, r.search)
        if self.spectral is not None:
            out.spectral = dict(self.spectral, profiles=self.spectral["profiles"][idx])
        return out

    def __repr__(self):
        return (f"<KernelPhaseData: {self.n_frame} frame(s) x {self.n_wave} channel(s) x "
                f"{self.n_kp} kernel phases, {self.wavelengths.min():.3f}-"
                f"{self.wavelengths.max():.3f}, {self.pixscale:.2f}>")


def _read_kpd(path, *, detpa=None):
    parts = read_kpfits_parts(path, detpa=detpa)
    model = parts.pop("model")
    km = KernelModel.from_parts(model, source=path)
    window = ExtractionWindow.from_header(parts["header"])
    rotation = parts.pop("rotation", None)
    spectral = parts.pop("spectral", None)
    out = KernelPhaseData(parts.pop("kp"), parts.pop("wavelengths"), parts.pop("pixscale"),
                          km, window=window, **parts)
    out.rotation = rotation
    out.spectral = spectral
    return out


def _read_files(kpd):
    """The files *kpd* was read from (``meta['read_from']``), which no writer replaces."""
    return [str(p) for p in kpd.meta.get("read_from") or ()]


def _guarded(writer):
    """*writer* with the files the data were read from among its inputs: ``read(p)``
    then ``write(p, overwrite=True)`` is refused as the command line refuses it."""
    def write(kpd, path, *, inputs=(), **kwargs):
        return writer(kpd, path, inputs=list(inputs) + _read_files(kpd), **kwargs)
    write.__doc__ = writer.__doc__
    return write


def _read_kpd_file(path, *, detpa=None):
    out = _read_kpd(path, detpa=detpa)
    out.meta["read_from"] = [str(path)]
    return out


register(KernelPhaseData, "kpfits", reader=_read_kpd_file, writer=_guarded(write_kpfits),
         identifier=is_kpfits)


def _read_oifits(path, *, insname=None, correlations="baselines", binning="auto"):
    """Closure phases of OIFITS file(s) of one target (`kpifs.io.oifits`,
    `kpifs.io.oifits_combine`): one frame, the sky frame."""
    parts = read_oifits(path, insname=insname, correlations=correlations, binning=binning)
    m = parts.pop("model")
    pupil = PupilModel(m["xy"], step=m["step"], name=m["name"],
                       meta={"closure_phases": True})
    km = KernelModel(pupil, m["uv"], np.ones(len(m["uv"])), m["blm"], m["kernel"],
                     rank=m["rank"], meta={"source": str(path), "closure_phases": True})
    out = KernelPhaseData(parts.pop("kp"), parts.pop("wavelengths") * u.m,
                          parts.pop("pixscale") * u.mas, km,
                          bandwidth=parts.pop("bandwidth") * u.m, **parts)
    paths = [path] if isinstance(path, (str, bytes)) or not hasattr(path, "__iter__") \
        else list(path)
    out.meta["read_from"] = [str(p) for p in paths]
    return out


register(KernelPhaseData, "oifits", reader=_read_oifits, writer=_guarded(write_oifits),
         identifier=is_oifits)


class DetectionGrid:
    """A rectangular grid of companion offsets in mas, on the detector or on the sky.

    Parameters
    ----------
    x, y : `~astropy.units.Quantity`
        Grid coordinates (1-D, uniformly spaced): along image x and y
        (``frame='detector'``), or dRA (East positive) and dDec
        (``frame='sky'``; dRA decreasing along the map's columns, East left).
    min_sep, max_sep : `~astropy.units.Quantity`, optional
        Positions closer or farther than these are not searched.
    frame : {'detector', 'sky'}
        What the coordinates are.

    Examples
    --------
    >>> import astropy.units as u
    >>> from kpifs.data import DetectionGrid
    >>> g = DetectionGrid.from_separation(200 * u.mas, 10 * u.mas, min_sep=30 * u.mas)
    >>> g.shape, int(g.valid.sum())
    ((41, 41), 1232)
    """

    def __init__(self, x, y, *, min_sep=None, max_sep=None, frame="detector"):
        if frame not in ("detector", "sky"):
            raise KpifsError(f"grid frame must be 'detector' or 'sky', got {frame!r}")
        self.frame = frame
        self.x = np.atleast_1d(to_quantity(x, u.mas, name="grid x")).value.astype(float)
        self.y = np.atleast_1d(to_quantity(y, u.mas, name="grid y")).value.astype(float)
        if self.x.size < 2 or self.y.size < 2:
            raise KpifsError("a detection grid needs at least 2 points along each axis")
        self.min_sep = 0.0 if min_sep is None else to_quantity(min_sep, u.mas).value
        self.max_sep = np.inf if max_sep is None else to_quantity(max_sep, u.mas).value
        self.X, self.Y = np.meshgrid(self.x, self.y)
        self.sep = np.hypot(self.X, self.Y)
        self.valid = (self.sep >= self.min_sep) & (self.sep <= self.max_sep) & (self.sep > 0)
        if not self.valid.any():
            raise KpifsError("the detection grid has no valid position")

    @classmethod
    def from_separation(cls, max_sep, step, *, min_sep=None, frame="detector"):
        """A square grid of half-width *max_sep* and spacing *step*, searched out to *max_sep*.

        On the sky (*frame* ``'sky'``) the first axis is dRA from East to West,
        so that a map shows East to the left.

        Examples
        --------
        >>> import astropy.units as u
        >>> from kpifs.data import DetectionGrid
        >>> DetectionGrid.from_separation(50 * u.mas, 10 * u.mas).shape
        (11, 11)
        """
        max_sep = to_quantity(max_sep, u.mas, name="maximum separation").value
        step = to_quantity(step, u.mas, name="grid step").value
        if not (step > 0 and max_sep > step):
            raise KpifsError(f"grid step ({step} mas) must be > 0 and smaller than the maximum "
                             f"separation ({max_sep} mas)")
        n = int(np.floor(max_sep / step))
        c = np.arange(-n, n + 1) * step
        x = -c if frame == "sky" else c
        return cls(x * u.mas, c * u.mas, min_sep=min_sep, max_sep=max_sep * u.mas, frame=frame)

    @property
    def shape(self):
        return self.X.shape

    @property
    def step(self):
        return float(self.x[1] - self.x[0]), float(self.y[1] - self.y[0])

    def wcs(self, *, star=None):
        """The map's WCS.

        On the detector: linear, from map pixels to offsets (mas) along image x
        and y. On the sky: celestial (gnomonic), offsets from the star, whose
        coordinates are *star* (a `~astropy.coordinates.SkyCoord`) or, when
        unknown, (0, 0) (then only the offsets mean anything).

        Examples
        --------
        >>> import astropy.units as u
        >>> from kpifs.data import DetectionGrid
        >>> w = DetectionGrid.from_separation(50 * u.mas, 10 * u.mas, frame="sky").wcs()
        >>> list(w.wcs.ctype), round(float(w.wcs.cdelt[0] * 3.6e6), 6)
        (['RA---TAN', 'DEC--TAN'], -10.0)
        """
        from astropy.wcs import WCS   # deferred: astropy.wcs is only needed for products
        w = WCS(naxis=2)
        if self.frame == "sky":
            # reference pixel: where the offsets are zero (1-based, may fall between pixels)
            w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
            w.wcs.cunit = ["deg", "deg"]
            w.wcs.crpix = [1 - self.x[0] / (self.x[1] - self.x[0]),
                           1 - self.y[0] / (self.y[1] - self.y[0])]
            w.wcs.cdelt = [(self.x[1] - self.x[0]) / 3.6e6, (self.y[1] - self.y[0]) / 3.6e6]
            w.wcs.crval = ([0.0, 0.0] if star is None
                           else [star.icrs.ra.deg, star.icrs.dec.deg])
            return w
        w.wcs.ctype = ["OFFSET-X", "OFFSET-Y"]
        w.wcs.cunit = ["mas", "mas"]
        w.wcs.crpix = [1, 1]
        w.wcs.crval = [self.x[0], self.y[0]]
        w.wcs.cdelt = [self.x[1] - self.x[0], self.y[1] - self.y[0]]
        return w

    def key(self):
        """A hashable description of the grid (for caches)."""
        return (self.x.tobytes(), self.y.tobytes(), self.min_sep, self.max_sep, self.frame)


@dataclass
class DetectionResult:
    """Everything a search found: maps (ny, nx) on `grid`, tables and provenance.

    Read and written as kpifs detection products: ``DetectionResult.read(path)``,
    ``result.write(path, inputs=..., overwrite=...)``. *header* is the header of
    the data searched (kept in the products).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> res = _example_result()
    >>> res.statistic.shape == res.grid.shape, res.limit is res.limits["B"]
    (True, True)
    """

    grid: DetectionGrid
    test: str
    pfa: float
    pd: float
    statistic: np.ndarray
    pfa_local: np.ndarray
    pfa_global: np.ndarray
    contrast: np.ndarray
    contrast_err: np.ndarray
    limits: dict
    curves: object
    candidates: object
    threshold: float
    wavelengths: u.Quantity
    energy: dict = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
    header: fits.Header = field(default_factory=fits.Header)
    #: The map the search stopped on: the statistic of the residual once the candidates
    #: are subtracted, at the noise scale they were judged with (the SEARCH extension;
    #: None in products written before it).
    search_map: np.ndarray = None
    #: The typed report of the search (`kpifs.report.DetectionReport`) that made
    #: it; *meta* is generated from it. Read from a product, it is made from the
    #: cards (fields no card holds are None).
    report: object = None

    _io_format = "kpifs-detection"
    read, write = io_methods("DetectionResult")

    def __post_init__(self):
        if self.report is not None and not self.meta:
            self.meta = self.report.as_meta()

    @property
    def limit(self):
        """The detection-limit map of the chosen test (None for a test without limits)."""
        return self.limits.get(self.test)


def _read_detection(path):
    parts = read_detection_parts(path)
    hdr, images, tables = parts["header"], parts["images"], parts["tables"]
    stat = images["DETECTION"]
    ny, nx = stat.shape
    g = parts["grid_header"]            # the maps' WCS
    if str(g.get("CTYPE1", "")).startswith("RA--"):
        # celestial: offsets from the star, which sits at the reference pixel
        frame = "sky"
        x = 3.6e6 * g["CDELT1"] * (np.arange(nx) + 1 - g["CRPIX1"])
        y = 3.6e6 * g["CDELT2"] * (np.arange(ny) + 1 - g["CRPIX2"])
    else:
        frame = "detector"
        x = g["CRVAL1"] + g["CDELT1"] * (np.arange(nx) + 1 - g["CRPIX1"])
        y = g["CRVAL2"] + g["CDELT2"] * (np.arange(ny) + 1 - g["CRPIX2"])
    grid = DetectionGrid(x * u.mas, y * u.mas, min_sep=hdr["GRIDMIN"] * u.mas,
                         max_sep=(hdr["GRIDMAX"] if hdr["GRIDMAX"] >= 0 else np.inf) * u.mas,
                         frame=frame)
    wl, energy, meta = detection_header_meta(hdr, path)
    # the typed report again, from the cards `_report_cards` wrote from it
    return DetectionResult(grid=grid, test=hdr["TEST"], pfa=hdr["PFA"], pd=hdr["PD"],
                           statistic=stat, pfa_local=images["PFA_LOCAL"],
                           pfa_global=images["PFA"], contrast=images["CONTRAST"],
                           contrast_err=images["CONTRAST_ERR"], limits=parts["limits"],
                           curves=tables["CURVES"], candidates=tables["CANDIDATES"],
                           threshold=hdr["THRESH"], wavelengths=wl, energy=energy, meta=meta,
                           header=hdr, search_map=images.get("SEARCH"),
                           report=DetectionReport.from_meta(meta))


register(DetectionResult, "kpifs-detection", reader=_read_detection, writer=write_detection,
         identifier=is_detection)
