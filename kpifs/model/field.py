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

MAS = np.pi / 180 / 3600 / 1000


__all__ = ["search_field", "field_sentence", "ALIAS_MARGIN"]

#: Fraction of the aliasing limit ``lambda_min / (2 s)`` the default grid reaches.
ALIAS_MARGIN = 0.95


def search_field(kpd, grid):
    """Separations searched and the bounds of the field, in mas.

    Returns a dict: ``inner`` and ``outer`` (the grid's), ``alias`` (``0.95
    lambda_min / (2 s)``, None without a grid step), ``window`` (its radius),
    ``image`` (half the side of the image read), ``limit`` (what stopped the
    search: ``'model'``, ``'window'``, ``'model+window'``, ``'image'`` or
    ``'grid'``, a maximum separation given), ``step`` (m), ``n_kp`` and
    ``n_frames`` (the target's, when known) and, when a wider bound exists,
    ``reach`` (the next bound, mas) and ``step_for`` (the grid step whose
    aliasing limit reaches it, m).

    Examples
    --------
    >>> import numpy as np, astropy.units as u
    >>> from kpifs import ExtractionWindow, KernelModel, KernelPhaseData, make_pupil
    >>> from kpifs.detect import default_grid
    >>> from kpifs.model.field import search_field
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
           "window": None, "image": None, "step": None, "n_kp": int(kpd.n_kp),
           "n_frames": kpd.meta.get("n_target_frames")}
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
    at = [k for k in ("alias", "window", "image")
          if out[k] is not None and out[k] <= out["outer"] * 1.02 + 1e-9]
    out["limit"] = ("model+window" if at[:2] == ["alias", "window"] else
                    "model" if "alias" in at else at[0] if at else "grid")
    wider = [out[k] for k in ("window", "image")
             if out[k] is not None and out[k] > out["outer"] * 1.05]
    if wider and out["limit"] != "grid":
        out["reach"] = float(min(wider))
        if out["alias"] is not None and out["alias"] < out["reach"]:
            out["step_for"] = ALIAS_MARGIN * lam / (2 * out["reach"] * MAS)
    return out


def field_sentence(field):
    """One line saying what was searched, what stopped it and what would reach farther.

    Examples
    --------
    >>> from kpifs.model.field import field_sentence
    >>> field_sentence({"inner": 22.0, "outer": 183.0, "alias": 183.0, "window": 362.5,
    ...                 "image": 453.2, "limit": "model", "step": 0.8, "step_for": 0.4,
    ...                 "reach": 362.5, "n_kp": 60, "n_frames": 8})
    ... # doctest: +NORMALIZE_WHITESPACE
    'field searched 22-183 mas: beyond, the 0.80 m grid of the pupil model (60 kernel
    phases per channel, 8 frames) aliases; the window reaches 362 mas and the images
    453 mas; --step 0.40m reaches 362 mas, with about 4x the kernel phases (the
    covariance needs several times more frames than kernel phases)'
    >>> field_sentence({"inner": 20.0, "outer": 167.0, "alias": 392.0, "window": 167.0,
    ...                 "image": 208.0, "limit": "window", "step": 0.38, "reach": 208.0})
    ... # doctest: +NORMALIZE_WHITESPACE
    'field searched 20-167 mas: beyond, the extraction window ends (--window-size,
    --window-radius); the images 208 mas; a wider window (--window-size,
    --window-radius) reaches 208 mas'
    """
    head = f"field searched {field['inner']:.0f}-{field['outer']:.0f} mas"
    model = f"the {field.get('step') or 0:.2f} m grid of the pupil model"
    if field.get("n_kp"):
        model += f" ({field['n_kp']} kernel phases per channel"
        model += f", {field['n_frames']} frames)" if field.get("n_frames") else ")"
    why = {"model": f"{model} aliases",
           "model+window": f"{model} aliases and the extraction window ends",
           "window": "the extraction window ends (--window-size, --window-radius)",
           "image": "the images read end",
           "grid": "the maximum separation asked for (--max-sep)"}[field["limit"]]
    text = f"{head}: beyond, {why}"
    far = []
    if field["limit"] == "model" and field.get("window") is not None:
        far.append(f"the window reaches {field['window']:.0f} mas")
    if field.get("image") is not None and field["image"] > field["outer"] * 1.05:
        far.append(f"the images {field['image']:.0f} mas")
    if far:
        text += "; " + " and ".join(far)
    win = field.get("window") is None or field["window"] < field.get("reach", 0) / 1.05
    if field.get("step_for") and field["limit"] != "grid":
        ratio = (field["step"] / field["step_for"]) ** 2 if field.get("step") else None
        more = f", with about {ratio:.0f}x the kernel phases" if ratio else ""
        win = " and a window to match (--window-size)" if win else ""
        text += (f"; --step {field['step_for']:.2f}m{win} reaches {field['reach']:.0f} mas"
                 f"{more} (the covariance needs several times more frames than kernel "
                 f"phases)")
    elif field.get("reach") and field["limit"] != "grid":
        text += (f"; a wider window (--window-size, --window-radius) reaches "
                 f"{field['reach']:.0f} mas")
    return text
