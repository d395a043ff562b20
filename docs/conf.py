"""Sphinx configuration of the evnoise documentation (build: ``.ci/docs``, or the README's command)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import evnoise

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # sphinx-gallery's examples import nothing from here, conf helpers only

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("NUMBA_NUM_THREADS", "2")

project = "evnoise"
author = "evnoise developers"
copyright = "2026, evnoise developers"
release = evnoise.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
    "sphinxarg.ext",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
smartquotes = False  # keep "--option" as typed in CLI help and prose (no en dashes)
exclude_patterns = ["_build", "examples/README.rst", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*.zip", "auto_examples/*.md5", "auto_examples/*.codeobj.json"]
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# --- API reference -----------------------------------------------------------------------------
templates_path = ["_templates"]
autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": True, "inherited-members": False, "show-inheritance": True}
autodoc_typehints = "none"  # numpydoc's Parameters sections carry the types and units
autodoc_member_order = "bysource"
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks = set()

# The build is offline (no intersphinx): references to external types (numpy, Python builtins,
# torch, h5py, tonic, v2e, ...) and to evnoise's internal modules, which are not part of the
# documented public surface, are not resolved but must not fail `-n -W`.
nitpick_ignore_regex = [
    (r"py:.*", r"(numpy|np|torch|h5py|tonic|v2ecore|v2e|scipy|PIL|dask|distributed|pathlib|os|typing|collections|concurrent|matplotlib|argparse|io|enum|dataclasses|faery)(\..*)?"),
    (r"py:.*", r"(int|float|str|bool|bytes|dict|list|tuple|set|object|callable|None|type|Path|Iterator|Iterable|Sequence|Mapping|array_like|ndarray|array|path|optional|TextIO|BinaryIO|Exception|ValueError|TypeError|OSError|KeyboardInterrupt|RuntimeError|ImportError|NotImplementedError|PathLike|Generator)"),
    # evnoise's internal modules and their members (being reorganised; the public names are documented)
    (r"py:.*", r"(evnoise\.)?_.*|.*\._[a-z].*"),
    (r"py:mod", r"evnoise\..*"),
    (r"py:.*", r"evnoise\.(model|rates|background|mismatch|simulate|stream|io|readers|radiometry|separation|motion|params|events|errors|testing|cli|presets|data|models|examples)(\.[A-Za-z_.]+)?"),
    # members of the documented subpackages' internal modules (evnoise.reconstruct.train.train, ...)
    (r"py:.*", r"evnoise\.(plugins|calibration|generators|reconstruct)\.[a-z_0-9]+\.[A-Za-z_.]+"),
    (r"py:.*", r"[A-Z][A-Z0-9_]+"),  # module constants named bare in docstrings (GZIP_LEVEL, COUNT_MODES, ...)
    (r"py:.*", r"[A-Z][A-Za-z0-9]+(\.[A-Za-z_]+)?"),  # bare class names in docstrings (MotionFrame, QuietFit, MaskParams, ...)
    (r"py:.*", r"[a-z_][a-z_0-9]*"),  # bare function/attribute names of the same module
]

# --- CLI: sphinx-argparse reads evnoise.cli.build_parser() ---------------------------------------

# --- gallery ------------------------------------------------------------------------------------
sphinx_gallery_conf = {
    "examples_dirs": "examples",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "ignore_pattern": r"__init__\.py|_common\.py",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "min_reported_time": 0,
    "show_memory": False,
    "matplotlib_animations": False,
    "image_scrapers": ("matplotlib",),
    "abort_on_example_error": False,
    "only_warn_on_example_error": False,
    "reference_url": {"evnoise": None},
    "plot_gallery": "True",
    "write_computation_times": True,
}

# --- HTML ---------------------------------------------------------------------------------------
html_theme = "alabaster"
html_title = f"evnoise {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]
html_theme_options = {
    "description": "The photon noise of event cameras, modelled exactly and put to work.",
    "page_width": "1180px",
    "sidebar_width": "240px",
    "fixed_sidebar": False,
    "show_relbars": True,
}
html_sidebars = {"**": ["about.html", "navigation.html", "relations.html", "searchbox.html"]}
html_show_sourcelink = False
html_copy_source = False


# --- the API name lists are written from the package's own __all__ at build time ---------------
def _write_name_lists() -> None:
    from api_lists import write_lists  # docs/api_lists.py

    write_lists(HERE / "api")


_write_name_lists()
