"""Options defined once (issue 38, item 3), beyond `test_one_driver`: the instrument names
come from one registry and are checked in one place for `kpifs extract`, `kpifs batch` and
the Python driver; the driver's functions take the option objects, never an option spelled
again as a keyword of their own."""
import dataclasses
import inspect
import warnings

import numpy as np
import pytest

from kpifs import workflow
from kpifs.cli import main
from kpifs.exceptions import KpifsError
from kpifs.io.instruments import INSTRUMENTS
from kpifs.workflow import DetectOptions, ExtractOptions

#: Parameters of the driver's functions that are the *data's* instrument (the cube's, after
#: reading), not the --instrument option.
DATA_NOT_OPTION = {("kernel_model_for", "instrument"), ("default_pupil", "instrument")}


def test_driver_functions_take_the_option_objects():
    """No public function of `kpifs.workflow` takes a keyword named like an option: every
    option reaches them inside `ExtractOptions`/`DetectOptions` (one default, one meaning)."""
    fields = ({f.name for f in dataclasses.fields(ExtractOptions)}
              | {f.name for f in dataclasses.fields(DetectOptions)})
    seen = set()
    for name in workflow.__all__:
        obj = getattr(workflow, name)
        if not inspect.isfunction(obj):
            continue
        seen.add(name)
        spelled = {p for p in inspect.signature(obj).parameters if p in fields}
        assert {(name, p) for p in spelled} <= DATA_NOT_OPTION, (name, spelled)
    assert {"reduce_observation", "extract_observation", "detect_observation",
            "process_observation", "calibrate_observation"} <= seen


def _ignore(fn, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args)


def test_instrument_names_checked_alike(tmp_path, capsys):
    """An unknown --instrument: the same message from `kpifs extract`, `kpifs batch` and
    `ExtractOptions`, naming every registered instrument; each registered name (and auto)
    is an option value all three take."""
    cube = tmp_path / "c.fits"
    from astropy.io import fits
    fits.writeto(cube, np.ones((2, 16, 16), np.float32))
    (tmp_path / "m.csv").write_text(f"name,target,calibrator\na,{cube},\n")
    with pytest.raises(KpifsError) as exc:
        ExtractOptions(instrument="osiris")
    message = str(exc.value)
    assert message.startswith("unknown instrument 'osiris'")
    assert all(name in message for name in ("auto", *INSTRUMENTS))
    assert main(["extract", str(cube), "--instrument", "osiris", "-o",
                 str(tmp_path / "kp.fits")]) == 2
    assert message in capsys.readouterr().err
    assert _ignore(main, ["batch", str(tmp_path / "m.csv"), "--instrument", "osiris",
                          "-o", str(tmp_path / "out"), "-q"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()                # refused before any work
    for name in ("auto", *INSTRUMENTS):
        assert ExtractOptions(instrument=name).instrument == name
        assert dataclasses.replace(ExtractOptions(), instrument=name).instrument == name
