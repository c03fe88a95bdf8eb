# Root conftest: settings shared by the tests and the docstring examples.
import os
import tempfile

import pytest

os.environ.setdefault("MPLBACKEND", "agg")


def pytest_configure(config):
    import matplotlib
    matplotlib.use("agg")
    if os.environ.get("PYTEST_XDIST_WORKER"):
        # pytest-xdist runs one worker per core (pyproject's addopts): each worker, and
        # the commands its tests run, keeps to one BLAS thread, so that the workers do
        # not oversubscribe the cores between them
        from threadpoolctl import threadpool_limits
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = "1"
        config._kpifs_blas = threadpool_limits(limits=1)


@pytest.fixture(autouse=True)
def _temporary_files_in_tmp_path(tmp_path, monkeypatch):
    """Whatever a test or a docstring example makes with `tempfile` (and the commands it
    runs in a subprocess, through TMPDIR) lands in its own ``tmp_path``, which pytest
    manages: no run leaves folders in the system's temporary directory."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
