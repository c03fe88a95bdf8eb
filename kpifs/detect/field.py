"""The field a search covers, and what limits it (issue 35: say what was searched).

Three things bound the separations a kernel-phase search can reach:

- the pupil model: its uv points lie on a lattice of step ``s`` (the grid step), so
  a companion's signature repeats every ``lambda / s`` and positions beyond
  ``lambda_min / (2 s)`` alias onto nearer ones (`~kpifs.detect.default_grid`
  stops at 0.95 of that);
- the extraction window: light beyond its radius is cut;
- the images: the cut-out read around the star (``KPCROP`` for GPI cubes, else
  the window's size).

A finer model reaches farther but has more kernel phases, whose covariance
needs more frames: `search_field` says which bound applied and what model step
would reach the next one, so that a coarse default is never silent.
"""
import numpy as np
from astropy import units as u

from ..kernel import MAS

__all__ = ["search_field", "field_sentence"]

#: Fraction of the aliasing limit ``lambda_min / (2 s)`` the default grid reaches.
ALIAS_MARGIN = 0.95


def search_field(kpd, grid):
    """Separations searched and the bounds of the field, in mas.

    Returns a dict: ``inner`` and ``outer`` (the grid's), ``alias`` (``0.95
    lambda_min / (2 s)``, None without a grid step), ``window`` (its radius),
    ``image`` (half the side of the image read), ``limit`` (which of
    ``'model'``, ``'window'``, ``'image'`` or ``'grid'`` (a maximum separation
    given) stopped the search), ``step`` (m) and, when the model stopped it
    short of a wider bound, ``step_for`` (the step that reaches that bound) and
    ``reach`` (that bound, mas).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import ExtractionWindow, KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.detect import default_grid
    >>> from kpifs.detect.field import search_field
    >>> km = KernelModel.from_pupil(make_pupil("gpi"))
    >>> kpd = KernelPhaseData(np.zeros((1, 1, km.n_kp)), [1.4946] * u.um, 14.161 * u.mas,
    ...                       km, window=ExtractionWindow(64, 25.6))
    >>> f = search_field(kpd, default_grid(kpd))
    >>> f["limit"], round(f["alias"]), round(f["window"]), round(f["step_for"], 2)
    ('model', 183, 363, 0.4)
    """
    lam = float(np.min(kpd.wavelengths.to_value(u.m)))
    sep = grid.sep[grid.valid] if grid.valid.any() else grid.sep
    out = {"inner": float(np.min(sep)), "outer": float(np.max(sep)), "alias": None,
           "window": None, "image": None, "step": None}
    step = kpd.kernel_model.pupil.step if kpd.kernel_model.pupil is not None else None
    if step is not None and step.to_value(u.m) > 0:
        out["step"] = float(step.to_value(u.m))
        out["alias"] = ALIAS_MARGIN * lam / (2 * out["step"]) / MAS
    ps = kpd.pixscale.to_value(u.mas) if kpd.pixscale is not None else None
    if kpd.window is not None and ps:
        out["window"] = float(kpd.window.radius * ps)
        side = kpd.header.get("KPCROP", kpd.window.size) if kpd.header is not None else \
            kpd.window.size
        out["image"] = float(side) / 2 * ps
    bounds = {k: out[k] for k in ("alias", "window", "image") if out[k] is not None}
    near = {k: v for k, v in bounds.items() if v <= out["outer"] * 1.02 + 1e-9}
    if "alias" in near:
        out["limit"] = "model"
    elif "window" in near:
        out["limit"] = "window"
    elif "image" in near:
        out["limit"] = "image"
    else:
        out["limit"] = "grid"
    if out["limit"] == "model":
        wider = [v for k, v in bounds.items() if k != "alias" and v > out["outer"] * 1.05]
        if wider:
            out["reach"] = float(min(wider))
            out["step_for"] = ALIAS_MARGIN * lam / (2 * out["reach"] * MAS)
    return out


def field_sentence(field):
    """One line saying what was searched and why it stops there.

    Examples
    --------
    >>> from kpifs.detect.field import field_sentence
    >>> field_sentence({"inner": 22.0, "outer": 183.0, "alias": 183.0, "window": 362.5,
    ...                 "image": 453.2, "limit": "model", "step": 0.8, "step_for": 0.4,
    ...                 "reach": 362.5})   # doctest: +NORMALIZE_WHITESPACE
    'field searched 22-183 mas: the 0.80 m grid of the pupil model aliases beyond it;
    the window reaches 362 mas and the images 453 mas; --step 0.40m reaches 362 mas,
    with about 4x the kernel phases (the covariance needs several times more frames
    than kernel phases)'
    """
    head = f"field searched {field['inner']:.0f}-{field['outer']:.0f} mas"
    far = []
    if field.get("window") is not None:
        far.append(f"the window reaches {field['window']:.0f} mas")
    if field.get("image") is not None:
        far.append(f"the images {field['image']:.0f} mas")
    why = {"model": f"the {field.get('step') or 0:.2f} m grid of the pupil model aliases "
                    f"beyond it",
           "window": "the extraction window's radius (--window-radius, --window-size)",
           "image": "the edge of the images read",
           "grid": "the maximum separation asked for (--max-sep)"}[field["limit"]]
    text = f"{head}: {why}"
    if field["limit"] == "model" and far:
        text += "; " + " and ".join(far)
    if field.get("step_for"):
        ratio = (field["step"] / field["step_for"]) ** 2
        text += (f"; --step {field['step_for']:.2f}m reaches {field['reach']:.0f} mas, with "
                 f"about {ratio:.0f}x the kernel phases (the covariance needs several times "
                 f"more frames than kernel phases)")
    return text
