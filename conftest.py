# Root conftest: settings shared by the tests and the docstring examples.
import os

os.environ.setdefault("MPLBACKEND", "agg")


def pytest_configure(config):
    import matplotlib
    matplotlib.use("agg")
