"""Constants and small helpers shared by the KPFITS writer and reader."""
import numpy as np
from astropy.io import fits

#: Largest KP-COV (bytes) written with one copy of the (shared) covariance per
#: frame, so that readers indexing ``KP-COV[i]`` (fouriever) find it for every
#: frame. Larger ones are written once, ``(1, nwave, nkp, nkp)``, with
#: ``COVFRAME = 'FIRST'``: identical copies of a 303 x 303 x 22-channel matrix
#: cost 16 MB per frame, 1.6 GB for 100 frames.
KPCOV_COPY_LIMIT = 64 * 2 ** 20

#: Error-model parameters (``meta['error_model']``) <-> primary header cards.
_ERROR_MODEL_CARDS = {
    "model": ("EMMODEL", "error model: modes (fitted model) or frames"),
    "n_modes": ("EMNMODES", "modes of the frame scatter kept"),
    "dof": ("EMDOF", "degrees of freedom nu = sum (N_s - 1)"),
    "mode_fraction": ("EMFRAC", "modes kept / nu"),
    "residual_method": ("EMRESID", "calibration-residual estimator"),
    "residual_fraction": ("EMRFRAC", "residual share of the modelled variance"),
    "tau_max": ("EMTAUMAX", "largest autocorrelation time (frames)"),
    "tau_mean": ("EMTAU", "mean autocorrelation time (frames)"),
    "inflation": ("EMINFL", "variance / independent-frame variance (mean)"),
    "hartlap": ("EMHARTL", "Hartlap factor applied (frames model)"),
    "pixel_modes": ("EMPIXMOD", "directions beyond the modes given pixel noise"),
    "pixel_scale": ("EMPIXSCL", "pixel noise there x this (calibrated data's)"),
}
# telescope name -> diameter (m), the table fouriever uses when DIAM is absent
_TELESCOPE_DIAMETERS = (("ESO-VLT", 8.2), ("KECK", 10.95))

# cards of an input header that describe its data array and must not be copied
_STRUCTURAL = {"SIMPLE", "BITPIX", "NAXIS", "EXTEND", "BSCALE", "BZERO", "PCOUNT", "GCOUNT",
               "XTENSION", "CHECKSUM", "DATASUM", "END"}


def _clean_header(header):
    out = fits.Header()
    for card in header.cards:
        key = card.keyword
        if key in _STRUCTURAL or key.startswith("NAXIS") or key in ("", "HISTORY", "COMMENT"):
            continue
        try:
            out.append(card)
        except (ValueError, fits.VerifyError):
            pass
    for key in ("HISTORY", "COMMENT"):
        for val in header.get(key, []):
            out.add_history(str(val)) if key == "HISTORY" else out.add_comment(str(val))
    return out


def ascii_text(value):
    """*value* as printable ASCII for a FITS card: other characters (a path's accents)
    written as Python escapes (``dé`` -> ``d\\xe9``)."""
    text = str(value)
    if text.isascii() and text.isprintable():
        return text
    return "".join(ch if ch.isascii() and ch.isprintable() else
                   ch.encode("unicode_escape").decode("ascii") for ch in text)


def card(value, comment):
    """A (value, comment) pair that fits one 80-character card (long paths keep their end)."""
    value = ascii_text(value)
    if len(value) > 66:
        value = "..." + value[-63:]
    return (value, comment) if len(value) + len(comment) < 64 else (value, "")


# --- small helpers ----------------------------------------------------------------
def _column(table_hdu, *names):
    """A column of a table HDU by any of *names* (case-insensitive), or None."""
    low = {n.lower(): n for n in table_hdu.columns.names}
    for n in names:
        if n.lower() in low:
            return np.asarray(table_hdu.data[low[n.lower()]])
    return None


def _number(value):
    """*value* as a finite float, or None (strings such as 'NONE', 'unavailable', NaN)."""
    if isinstance(value, bool):
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def _flag(value):
    """A FITS flag written as a boolean or as a string ('False', 'T', ...)."""
    if isinstance(value, str):
        return value.strip().lower() in ("true", "t", "1", "yes", "y")
    return bool(value)


def _all_nan(data):
    a = np.asarray(data, float)
    return a.size > 0 and not np.any(np.isfinite(a))


def _table_hdu(columns, name, units=None):
    """A binary table HDU of float64 columns ``{name: values}`` with optional *units*.

    The same bytes as ``fits.BinTableHDU(Table(...))``, without importing
    `astropy.table` (a tenth of a second of the command line's start).
    """
    units = units or {}
    cols = [fits.Column(name=key, format="D", array=np.asarray(values, np.float64),
                        unit=units.get(key)) for key, values in columns.items()]
    # data given to the constructor (from_columns) would import astropy.table, to check
    # whether it is a Table; set afterwards, they do not
    hdu = fits.BinTableHDU(name=name)
    hdu.data = fits.FITS_rec.from_columns(fits.ColDefs(cols))
    return hdu


def _label_columns(hdu, comments):
    """Comments of the TTYPEn cards of a table HDU: ``{column: comment}``."""
    for i, name in enumerate(hdu.columns.names, 1):
        if name in comments:
            hdu.header.comments[f"TTYPE{i}"] = comments[name]
    return hdu


# --- kernel models ----------------------------------------------------------------
