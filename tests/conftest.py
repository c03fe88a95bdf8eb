import os
from pathlib import Path

import numpy as np
import pytest
import astropy.units as u

os.environ.setdefault("MPLBACKEND", "agg")

REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


@pytest.fixture(scope="session")
def real_data():
    """Folder of real third-party data; the test is skipped when it is absent."""
    if not REAL_DATA.is_dir():
        pytest.skip(f"real data folder {REAL_DATA} is absent (only in the development "
                    f"workspace)")
    return REAL_DATA


@pytest.fixture(scope="session")
def subaru_model():
    from kpifs import KernelModel, make_pupil
    return KernelModel.from_pupil(make_pupil("subaru"))


@pytest.fixture(scope="session")
def paper_wavelengths():
    return [1.52, 1.60, 1.68] * u.um


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
