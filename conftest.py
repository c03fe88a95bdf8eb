# Root conftest: settings shared by the tests and the docstring examples.
import os
import tempfile

import pytest

os.environ.setdefault("MPLBACKEND", "agg")


def pytest_configure(config):
    import matplotlib
    matplotlib.use("agg")


@pytest.fixture(autouse=True)
def _temporary_files_in_tmp_path(tmp_path, monkeypatch):
    """Whatever a test or a docstring example makes with `tempfile` (and the commands it
    runs in a subprocess, through TMPDIR) lands in its own ``tmp_path``, which pytest
    manages: no run leaves folders in the system's temporary directory."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("TMPDIR", str(tmp_path))
