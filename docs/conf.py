# Sphinx configuration for kpifs (sphinx-astropy theme, automodapi, numpydoc).
import datetime

from sphinx_astropy.conf.v2 import *  # noqa: F401,F403

import kpifs

project = "kpifs"
author = "The kpifs developers"
copyright = f"{datetime.date.today().year}, {author}"
version = release = kpifs.__version__
extensions += ["sphinx.ext.mathjax"]  # noqa: F405
exclude_patterns = ["_build"]
