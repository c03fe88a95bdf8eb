# Sphinx configuration for kpifs: sphinx-astropy (v3 theme), automodapi, numpydoc,
# and a gallery of examples executed by the build itself.
import datetime
import os

from sphinx_astropy.conf.v3 import *  # noqa: F401,F403

import kpifs

project = "kpifs"
author = "The kpifs developers"
copyright = f"{datetime.date.today().year}, {author}"
version = release = kpifs.__version__

extensions += ["sphinx_gallery.gen_gallery"]  # noqa: F405
exclude_patterns = ["_build", "**.ipynb_checkpoints", "gallery/*.ipynb", "gallery/*.py",
                    "gallery/*.md5", "gallery/*.json", "gallery/*.zip"]

# The build runs with no network: no intersphinx inventories. References to
# other packages' objects are therefore not resolvable and are ignored; every
# kpifs reference must resolve.
intersphinx_mapping = {}
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(astropy|numpy|scipy|matplotlib|photutils|dask|tqdm)(\..*)?"),
    (r"py:.*", r"(np|u)\..*"),
    (r"py:.*", r"(ndarray|Quantity|QTable|Table|Header|HDUList|Generator|WCS|array-like|"
               r"array_like|optional|callable|dict|list|tuple|str|int|float|bool|None|"
               r"function|sequence|path-like|Path|Figure|Axes)"),
    (r"py:obj", r".*"),
]
numpydoc_xref_param_type = False
suppress_warnings = ["config.cache"]

os.environ.setdefault("MPLBACKEND", "agg")
sphinx_gallery_conf = {
    "examples_dirs": "../examples",
    "gallery_dirs": "gallery",
    "filename_pattern": r"plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
}
html_title = f"kpifs {version}"
html_theme_options = {"github_url": "https://github.com/kpifs/kpifs"}
automodapi_inheritance_diagram = False
