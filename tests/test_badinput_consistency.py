"""Issue 37: physically consistent or refused, on cubes, JWST, GPI, inject, simulate, info and
model-check. Each case records the exit status, the message, that the inputs are unchanged
and that no partial output is left; cases that run to the end check the answer against
the simulation's truth."""
import hashlib
import warnings

import numpy as np
import pytest
from astropy.io import fits

from kpifs import KernelPhaseData
from kpifs.cli import main
from kpifs.exceptions import KpifsError, KpifsWarning
from kpifs.io.layouts import write_observation
from kpifs.simulate import simulate_scene


def _hashes(files):
    return {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in files if p.is_file()}


def _edit(src, dst, *, phu=None, sci=None, data=None):
    """A copy of a FITS file with header cards (None deletes) and extensions' data changed."""
    with fits.open(src, memmap=False) as h:
        for hdr, cards in ((h[0].header, phu), (h["SCI"].header if "SCI" in h else None, sci)):
            for k, v in (cards or {}).items():
                if v is None:
                    hdr.remove(k, ignore_missing=True)
                else:
                    hdr[k] = v
        for name, edit in (data or {}).items():
            h[name].data = edit(np.array(h[name].data))
        h.writeto(dst)
    return dst


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    d = tmp_path_factory.mktemp("consistency")
    f = {}
    # NIRISS F480M through CLEARP (kernel phase) and NRM (aperture masking)
    for name, tel, seed in (("clearp", "niriss_clearp", 3), ("nrm", "niriss_nrm", 4)):
        obs = simulate_scene("niriss", n_frames=10, npup=64, seed=seed, telescope=tel)
        files = write_observation(obs, d / name, layout="jwst")
        f[name], f[name + "_cal"] = files["target"][0], files["calibrator"][0]
    f["gr700xd"] = _edit(f["clearp"], d / "gr700xd_calints.fits", phu={"PUPIL": "GR700XD"})
    return f


def _run(corpus, tmp_path, capsys, argv, code):
    """Run the command line; the message, checked: one error line for exit 2, no traceback,
    inputs untouched, no output or temporary left by a refusal."""
    inputs = [p for v in corpus.values() for p in (v if isinstance(v, list) else [v])
              if hasattr(p, "is_file")]
    before = _hashes(inputs)
    out = tmp_path / "out.fits"
    args = [str(a) for a in argv]
    if args[0] in ("extract", "detect", "inject") and "-o" not in args:
        args += ["-o", str(out)]
    assert main(args) == code
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    if code == 2:
        lines = [ln for ln in captured.err.splitlines() if ": error: " in ln]
        assert len(lines) == 1, captured.err
        assert not out.exists()
    assert not list(tmp_path.glob(".out*"))
    assert _hashes(before) == before
    return captured.err + captured.out


CASES = [
    # (name, argv builder, exit status, texts in the message)
    ("3: CLEARP target, NRM calibrator",
     lambda f: ["extract", f["clearp"], "--calibrator", f["nrm_cal"]], 2,
     ["calibrator {nrm_cal}: pupil element NRM, but the target {clearp}: CLEARP"]),
    ("3: NRM target, CLEARP calibrator",
     lambda f: ["extract", f["nrm"], "--calibrator", f["clearp_cal"]], 2,
     ["calibrator {clearp_cal}: pupil element CLEARP, but the target {nrm}: NRM"]),
    ("3: target files through two pupil elements",
     lambda f: ["extract", f["clearp"], f["nrm"], "--calibrator", f["clearp_cal"]], 2,
     ["files through different pupil elements", "{nrm} (PUPIL NRM)"]),
    ("17: unknown NIRISS PUPIL refused",
     lambda f: ["extract", f["gr700xd"], "--calibrator", f["clearp_cal"]], 2,
     ["gr700xd_calints.fits: NIRISS PUPIL 'GR700XD' is no pupil element kpifs models"]),
]


@pytest.mark.parametrize("name, argv, code, texts", CASES, ids=[c[0] for c in CASES])
@pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::ResourceWarning")
def test_refused_or_said(corpus, tmp_path, capsys, name, argv, code, texts):
    message = _run(corpus, tmp_path, capsys, argv(corpus), code)
    for text in texts:
        assert text.format(**{k: v for k, v in corpus.items()}) in message, message


def test_same_setup_through_the_python_api(corpus):
    """The refusal is made where target and calibrator meet: `calibrate` too."""
    from kpifs.calibrate import calibrate
    from kpifs.workflow import ExtractOptions, extract_observation
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)
        t = extract_observation(corpus["clearp"], ExtractOptions())
        c = extract_observation(corpus["nrm_cal"], ExtractOptions(), model=t.kernel_model)
    with pytest.raises(KpifsError, match="pupil element NRM, but the target"):
        calibrate(t, [c])
    # kernel-phase files read back keep the headers: `detect --calibrator` refuses too
    kt = t.write(corpus["clearp"].parent / "t_kp.fits")
    kc = c.write(corpus["clearp"].parent / "c_kp.fits")
    with pytest.raises(KpifsError, match="pupil element NRM"):
        calibrate(KernelPhaseData.read(kt), [KernelPhaseData.read(kc)])
