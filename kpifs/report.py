"""The typed report of a search: what `kpifs.detect.detect` decided and with what.

`DetectionReport` holds named fields (the null's `NullReport`, the limits'
`LimitsReport`); ``DetectionResult.meta``, which products, printouts and older
code read, is generated from them (`DetectionReport.as_meta`), and a product read
back gets them again from its cards (`DetectionReport.from_meta` of what
`kpifs.io.products.detection_header_meta` reads). It sits below the data
containers and the products (the search in `kpifs.detect` fills it).
"""
from dataclasses import dataclass, field

__all__ = ["NullReport", "LimitsReport", "DetectionReport"]


@dataclass
class NullReport:
    """How the search's threshold was calibrated (`kpifs.detect.null.search_null`).

    *method* names the nulls combined ('gaussian', 'empirical' or both joined
    by '+'), *threshold* is the one applied, *thresholds* each null's by name;
    *n_blocks* and *block_energy* describe the empirical null's time blocks,
    *empirical_draws* its number of sign patterns.

    Examples
    --------
    >>> from kpifs.report import NullReport
    >>> NullReport("gaussian", 12.5, {"gaussian": 12.5}).as_meta()["threshold_gaussian"]
    12.5
    """

    method: str
    threshold: float
    thresholds: dict
    n_blocks: int = None
    block_energy: float = None
    empirical_draws: int = None

    @classmethod
    def from_meta(cls, meta):
        """The report from a ``meta['null']`` dict (`as_meta`'s, or a product's)."""
        thresholds = {k[len("threshold_"):]: v for k, v in meta.items()
                      if k.startswith("threshold_")}
        return cls(meta["method"], meta["threshold"], thresholds, meta.get("n_blocks"),
                   meta.get("block_energy"), meta.get("empirical_draws"))

    def as_meta(self):
        """The ``meta['null']`` dict."""
        return {"method": self.method, "threshold": self.threshold,
                **{f"threshold_{k}": v for k, v in self.thresholds.items()},
                "n_blocks": self.n_blocks, "block_energy": self.block_energy,
                "empirical_draws": self.empirical_draws}


@dataclass
class LimitsReport:
    """What the limits were computed with: the noise scales (the common one and the
    subspace test's), the error model, the null's spread and map floor, the
    calibrators and source, the spectrum shape, the energy's non-centrality, the
    null's channels ('covariance rows' or 'independent') and the PA bins.

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> lim = _example_result().report.limits
    >>> lim.null_channels, lim.spectrum
    ('independent', [1.0, 1.0])
    """

    noise_scale_common: float
    noise_scale_subspace: float
    error_model: object
    energy_spread: float
    map_noise_low: float
    calibrators: list
    source: str
    spectrum: list
    lambda_energy: float
    null_channels: str
    pa_bins: list = None
    pa_bins_search: list = None


@dataclass
class DetectionReport:
    """What a search decided, and with what (`kpifs.detect.detect`).

    Examples
    --------
    >>> from kpifs.detect.pipeline import _example_result
    >>> report = _example_result().report
    >>> report.test, report.null.method, report.limits.null_channels
    ('B', 'gaussian', 'independent')
    >>> report.as_meta()["null"]["threshold"] == report.null.threshold
    True
    """

    test: str
    map_test: str
    pfa: float
    pd: float
    n_draws: int
    seed: object
    frame: str
    chi2_red: float
    noise_scale: float
    null: NullReport
    static: dict = None
    blocks: dict = None
    aliased: list = field(default_factory=list)
    channels: list = field(default_factory=list)
    excluded_channels: list = field(default_factory=list)
    field_searched: dict = None
    limits: LimitsReport = None

    @classmethod
    def from_meta(cls, meta):
        """The report from a ``DetectionResult.meta`` dict: `as_meta`'s, or what a
        product's cards give (`kpifs.io.products.detection_header_meta`; fields no card
        holds are None).

        Examples
        --------
        >>> from kpifs.detect.pipeline import _example_result
        >>> from kpifs.report import DetectionReport
        >>> report = _example_result().report
        >>> DetectionReport.from_meta(report.as_meta()) == report
        True
        """
        lim = None
        if "null_channels" in meta:
            lim = LimitsReport(
                meta.get("noise_scale_common"), meta.get("noise_scale_S"),
                meta.get("error_model"), meta.get("energy_spread"), meta.get("map_noise_low"),
                list(meta.get("calibrators") or []), meta.get("source"),
                list(meta.get("spectrum") or []), meta.get("lambda_energy"),
                meta["null_channels"], meta.get("pa_bins"), meta.get("pa_bins_search"))
        null = NullReport.from_meta(meta["null"]) if meta.get("null") else None
        return cls(meta["test"], meta.get("map_test", meta["test"]), meta["pfa"], meta["pd"],
                   meta.get("n_draws"), meta.get("seed"), meta.get("frame"),
                   meta.get("chi2_red"), meta.get("noise_scale"), null,
                   static=meta.get("static"), blocks=meta.get("blocks"),
                   aliased=list(meta.get("aliased") or []),
                   channels=list(meta.get("channels") or []),
                   excluded_channels=list(meta.get("excluded_channels") or []),
                   field_searched=meta.get("field"), limits=lim)

    def as_meta(self):
        """The ``DetectionResult.meta`` dict (the keys products and printouts read)."""
        meta = {"test": self.test, "map_test": self.map_test, "pfa": self.pfa, "pd": self.pd,
                "n_draws": self.n_draws, "seed": self.seed, "chi2_red": self.chi2_red,
                "noise_scale": self.noise_scale}
        lim = self.limits
        if lim is not None:
            meta.update({"noise_scale_common": lim.noise_scale_common,
                         "noise_scale_S": lim.noise_scale_subspace,
                         "error_model": lim.error_model, "energy_spread": lim.energy_spread,
                         "map_noise_low": lim.map_noise_low, "calibrators": lim.calibrators,
                         "source": lim.source, "spectrum": lim.spectrum,
                         "lambda_energy": lim.lambda_energy,
                         "null_channels": lim.null_channels})
        meta.update({"null": self.null.as_meta(), "frame": self.frame})
        if lim is not None:
            meta.update({"pa_bins": lim.pa_bins, "pa_bins_search": lim.pa_bins_search})
        meta.update({"blocks": self.blocks, "static": self.static, "aliased": self.aliased,
                     "channels": self.channels, "excluded_channels": self.excluded_channels,
                     "field": self.field_searched})
        return meta
