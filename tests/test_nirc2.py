"""Keck/NIRC2 imaging (issue 38, item 4): the instrument added as a plug-in, its headers,
its angle convention, and a companion found where it was put on the sky."""
import ast
import inspect
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits

import kpifs
from kpifs.cli import main
from kpifs.exceptions import KpifsError, KpifsWarning, MissingInformation
from kpifs.io import read_cube, write_observation
from kpifs.io.instruments import INSTRUMENTS
from kpifs.io.nirc2 import (NIRC2_FILTERS, nirc2_detpa, nirc2_filter, nirc2_pixscale,
                            nirc2_pupil, read_nirc2, write_nirc2_frames)
from kpifs.io.readers import check_pupil_header, detect_instrument, observing_setup
from kpifs.simulation.simulate import simulate_scene

NARROW = {"INSTRUME": "NIRC2", "CAMNAME": "narrow", "FWINAME": "Kp", "FWONAME": "clear",
          "PMSNAME": "largehex", "ROTMODE": "vertical angle", "PARANG": 30.0,
          "ROTPOSN": 4.0, "INSTANGL": 0.7, "DATE-OBS": "2019-06-01"}


def _header(**cards):
    hdr = fits.Header(NARROW)
    for k, v in cards.items():
        if v is None:
            del hdr[k]
        else:
            hdr[k] = v
    return hdr


def _write(path, data, **cards):
    fits.writeto(path, np.asarray(data, np.float32), _header(**cards))
    return str(path)


def test_the_registry_lists_nirc2(capsys):
    """One registry: the readers' names, the driver's default pupil, the simulator's
    layouts and presets and `kpifs info --instruments` all read it."""
    from kpifs.io.layouts import LAYOUTS
    from kpifs.io.readers import INSTRUMENTS as NAMES
    from kpifs.simulation.simulate import PRESETS
    from kpifs.workflow import DEFAULT_PUPIL
    assert "nirc2" in INSTRUMENTS and list(INSTRUMENTS)[-1] == "generic"   # the fallback
    assert NAMES == ("auto", *INSTRUMENTS)
    assert DEFAULT_PUPIL == {name: inst.pupil for name, inst in INSTRUMENTS.items()}
    assert {k: DEFAULT_PUPIL[k] for k in ("charis", "sphere", "jwst", "gpi", "nirc2",
                                          "generic")} == {
        "charis": "subaru", "sphere": "vlt", "jwst": "jwst", "gpi": "gpi", "nirc2": "keck",
        "generic": "subaru"}
    assert "nirc2" in LAYOUTS and "nirc2" in PRESETS
    assert main(["info", "--instruments"]) == 0
    out = capsys.readouterr().out
    assert "nirc2: Keck/NIRC2" in out and "simulator layout: nirc2" in out
    assert out.count("recognised by:") == len(INSTRUMENTS)


def test_unknown_instrument_layout_and_preset_refused(tmp_path, capsys):
    """Names the parser no longer lists are checked by the registry: exit 2, naming them."""
    path = _write(tmp_path / "n0001.fits", np.ones((16, 16)))
    assert main(["extract", path, "--instrument", "osiris", "-o",
                 str(tmp_path / "kp.fits")]) == 2
    err = capsys.readouterr().err
    assert "unknown instrument 'osiris'" in err and "nirc2" in err
    for opt in (["--layout", "hst"], ["--preset", "hst"]):
        assert main(["simulate", *opt, "-o", str(tmp_path / "sim")]) == 2
        err = capsys.readouterr().err
        assert "hst" in err and "nirc2" in err and "Traceback" not in err


def test_detector_angle_by_rotator_mode_and_date():
    """DETPA = PARANG + ROTPOSN - INSTANGL + NORTH (vertical angle), ROTPOSN - INSTANGL +
    NORTH (position angle), NORTH -0.252 deg before 2015-04-13 and -0.262 after (narrow
    camera), unknown when the rotator is stationary."""
    assert nirc2_detpa(_header())[0] == pytest.approx(30 + 4 - 0.7 - 0.262, abs=1e-12)
    assert nirc2_detpa(_header(**{"DATE-OBS": "2012-03-04"}))[0] == pytest.approx(
        30 + 4 - 0.7 - 0.252, abs=1e-12)
    assert nirc2_detpa(_header(ROTMODE="position angle", ROTPOSN=120.0))[0] == \
        pytest.approx(120 - 0.7 - 0.262, abs=1e-12)
    assert nirc2_detpa(_header(CAMNAME="wide"))[0] == pytest.approx(33.3, abs=1e-12)
    assert np.isnan(nirc2_detpa(_header(ROTMODE="stationary"))[0])
    assert np.isnan(nirc2_detpa(_header(PARANG=None))[0])
    with pytest.raises(KpifsError, match="not angles"):
        nirc2_detpa(_header(PARANG=4000.0))


def test_pixel_scale_filter_and_pupil_from_the_header():
    assert nirc2_pixscale(_header()) == 9.971
    assert nirc2_pixscale(_header(**{"DATE-OBS": "2010-01-01"})) == 9.952
    with pytest.raises(MissingInformation, match="CAMNAME 'wide'.*--pixscale"):
        nirc2_pixscale(_header(CAMNAME="wide"), source="n0001.fits")
    assert nirc2_filter(_header()) == ("Kp", (2.124, 0.351))
    assert nirc2_filter(_header(FWINAME="clear", FWONAME="Ms")) == ("Ms", (4.670, 0.241))
    assert nirc2_filter(_header(FWINAME=None, FWONAME=None, FILTER="Br_gamma + clear")) == \
        ("Br_gamma", NIRC2_FILTERS["brgamma"])
    assert nirc2_pupil(_header()) == nirc2_pupil(_header(PMSNAME="open")) == "keck"
    assert nirc2_pupil(_header(PMSNAME="9holeMsk")) is None
    assert observing_setup(_header()) == {"instrument": "NIRC2", "filter": "Kp",
                                          "camera": "NARROW", "pupil stop": "LARGEHEX"}
    with pytest.warns(KpifsWarning, match="expected 'keck'"):
        check_pupil_header("subaru", _header())


def test_images_and_stacks_read_as_frames(tmp_path):
    """2-D images (one frame per file) and a 3-D stack (several frames of one angle)."""
    rng = np.random.default_rng(3)
    one = [_write(tmp_path / f"n{i}.fits", rng.normal(size=(32, 32)), PARANG=10.0 * i)
           for i in range(2)]
    stack = _write(tmp_path / "stack.fits", rng.normal(size=(3, 32, 32)), PARANG=50.0)
    old = _write(tmp_path / "old.fits", rng.normal(size=(32, 32)), **{"DATE-OBS": "2014-01-01"})
    assert detect_instrument(one[0]) == "nirc2"
    with read_cube(one + [stack]) as cube:
        assert cube.instrument == "nirc2" and cube.shape == (5, 1, 32, 32)
        assert cube.wavelengths.to_value(u.um).tolist() == [2.124]
        np.testing.assert_allclose(cube.detpa.to_value(u.deg),
                                   [3.038, 13.038, 53.038, 53.038, 53.038], atol=1e-9)
        np.testing.assert_array_equal(cube.data[2:5, 0], fits.getdata(stack))
        assert cube.header["KPFILTER"] == "Kp"
    with pytest.raises(KpifsError, match="old.fits: pixel scale 9.952 mas differs"):
        read_cube([one[0], old])                     # either side of the 2015 servicing
    with read_nirc2(one, wavelengths=[2.2] * u.um, pixscale=10 * u.mas) as cube:
        assert cube.wavelengths[0] == 2.2 * u.um and cube.pixscale == 10 * u.mas


def test_unmodelled_pupil_stop_and_unknown_filter(tmp_path):
    mask = _write(tmp_path / "mask.fits", np.ones((16, 16)), PMSNAME="9holeMsk")
    with pytest.warns(KpifsWarning, match="9holeMsk.*--pupil"):
        read_cube(mask).close()
    odd = _write(tmp_path / "odd.fits", np.ones((16, 16)), FWINAME="Z")
    with pytest.raises(MissingInformation, match="odd.fits: NIRC2 filter 'Z'.*--wavelengths"):
        read_cube(odd)
    flat = _write(tmp_path / "flat.fits", np.ones((2, 2, 16, 16)))
    with pytest.raises(KpifsError, match="flat.fits: a NIRC2 file holds an image"):
        read_cube(flat)


def test_simulated_files_carry_the_angles_they_were_written_with(tmp_path):
    paths = write_nirc2_frames(tmp_path, np.ones((3, 8, 8)), 3.776 * u.um, 9.971 * u.mas,
                               detpa=[-20.0, 0.0, 35.5])
    assert fits.getval(paths[0], "FILTER") == "Lp + clear"
    with read_cube(paths) as cube:
        np.testing.assert_allclose(cube.detpa.to_value(u.deg), [-20.0, 0.0, 35.5],
                                   atol=1e-9)
        assert cube.wavelengths[0] == 3.776 * u.um


@pytest.mark.slow
def test_companion_found_where_it_was_put_on_the_sky(tmp_path, capsys):
    """A 10-frame pupil-tracking sequence over 30 deg, companion 2 % at (dRA, dDec) =
    (+120, +90) mas (North-East: East left at DETPA 0) and a calibrator, written as NIRC2
    files (ROTPOSN 4 deg, INSTANGL 0.7 deg: each term's sign shows): `kpifs extract`
    recognises them, and `kpifs detect` finds one companion within 4 mas of where it was
    put (1.4 mas for this seed, 1.5-2.9 mas for seeds 2-4, errors 0.6-0.9 mas per axis),
    its position angle East of North within 1 deg (53.15 deg for 53.13): read with
    ROTPOSN's sign flipped, the same files put it at 45.2 deg."""
    obs = simulate_scene("nirc2", seed=2, npup=64)
    files = write_observation(obs, tmp_path, layout="nirc2")
    kp, det = tmp_path / "kp.fits", tmp_path / "det.fits"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", KpifsWarning)      # 30 deg averaged on the detector
        assert main(["extract", *map(str, files["target"]), "--calibrator",
                     *map(str, files["calibrator"]), "--step", "1m", "-q",
                     "-o", str(kp)]) == 0
        assert main(["detect", str(kp), "--draws", "2000", "-q", "-o", str(det)]) == 0
    from kpifs.data import DetectionResult
    cand = DetectionResult.read(det).candidates
    assert len(cand) == 1
    dra, ddec = obs.params.sky_offset.to_value(u.mas)
    fdra, fddec = cand["fit_dra"][0].to_value(u.mas), cand["fit_ddec"][0].to_value(u.mas)
    assert np.hypot(fdra - dra, fddec - ddec) < 4
    pa = np.degrees(np.arctan2(dra, ddec)) % 360                 # 53.13 deg, East of North
    assert abs((cand["fit_pa_sky"][0].to_value(u.deg) - pa + 180) % 360 - 180) < 1


# --- nothing of an instrument outside its module ---------------------------------------
PACKAGE = Path(kpifs.__file__).parent

#: Where a registered instrument's name is another thing's name, and stays: the pupil
#: library names telescopes' pupils (``'jwst'``, ``'gpi'``; ``'charis'`` and
#: ``'sphere'`` are aliases of ``'subaru'`` and ``'vlt'``); the demo picks the CHARIS
#: scene and layout, and ``kpifs roc --preset`` offers some scenes (their choices of a
#: scene, as a user's ``--preset`` is; the parser imports no instrument module, so
#: that ``kpifs --version`` stays fast, and the names it offers are checked below).
NAMED_ELSEWHERE = {"model/apertures.py": {"charis", "sphere", "gpi", "jwst"},
                   "model/_segmented.py": {"jwst"},
                   "demo.py": {"charis"},
                   "_cli/_parser.py": {"charis", "sphere", "sphere-sam"}}


def _instrument_words():
    """Every name a registered instrument is known by: its name, its ``INSTRUME`` values,
    its simulator layout and the simulator scenes it adds (lower and upper case)."""
    words = set()
    for inst in INSTRUMENTS.values():
        if inst.name == "generic":
            continue
        words |= {inst.name, inst.layout, *inst.instrume, *inst.scenes}
    return {w for word in words if word for w in (word.lower(), word.upper())}


def _code_strings(path):
    """The string constants of a module's code (its docstrings left out)."""
    tree = ast.parse(path.read_text())
    docs = {id(node.body[0].value) for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                 ast.AsyncFunctionDef))
            and node.body and isinstance(node.body[0], ast.Expr)
            and isinstance(node.body[0].value, ast.Constant)}
    return {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and id(node) not in docs}


def test_no_instrument_is_spelled_outside_its_module():
    """Adding an instrument touches its module and one registry line: no other module of
    kpifs spells a registered instrument's name, ``INSTRUME``, layout or scene as a
    string of its code (the simulator's presets, the angles of its simulated sequences,
    its field, the injector's file layout, the KPFITS cards of its products, the default
    pupil: all read through `kpifs.io.instruments.INSTRUMENTS`)."""
    own = {Path(inspect.getsourcefile(i.identify)).resolve() for i in INSTRUMENTS.values()}
    own.add(PACKAGE.joinpath("io", "instruments.py").resolve())
    assert len(own) == len(INSTRUMENTS) + 1
    words = _instrument_words()
    assert {"nirc2", "NIRC2", "charis", "sphere-sam", "niriss", "NIRCAM"} <= words
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.resolve() in own:
            continue
        rel = path.relative_to(PACKAGE).as_posix()
        spelled = (_code_strings(path) & words) - NAMED_ELSEWHERE.get(rel, set())
        if spelled:
            found[rel] = sorted(spelled)
    assert found == {}
    from kpifs._cli._parser import ROC_PRESETS
    from kpifs.simulation.simulate import PRESETS
    assert set(ROC_PRESETS) <= set(PRESETS)


def test_rotating_sequences_start_where_their_instrument_says():
    """``kpifs simulate --rotation`` or ``--hour-angle`` starts a preset's sequence at the
    detector angle (at parallactic angle 0) and site of the instrument that adds the
    preset (`Instrument.sequence`), the others at 0 deg at Maunakea: the values of the
    table the command kept before, and now ``sphere-yjh`` as the other SPHERE scenes
    (that table had left it at 0 deg at Maunakea)."""
    from kpifs._cli.simulate import _sequence
    presets = ("paper", "charis", "sphere", "sphere-sam", "sphere-yjh", "gpi", "niriss",
               "nircam", "nirc2")
    assert {p: _sequence(p) for p in presets} == {
        "paper": (0.0, "maunakea"), "charis": (113.0, "maunakea"),
        "sphere": (33.76, "paranal"), "sphere-sam": (33.76, "paranal"),
        "sphere-yjh": (33.76, "paranal"), "gpi": (-66.5, "pachon"),
        "niriss": (0.0, "maunakea"), "nircam": (0.0, "maunakea"), "nirc2": (0.0, "maunakea")}
