"""Sphinx configuration of the API reference (``python -m sphinx -W -b html docs/api OUT``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import evdown_torch  # noqa: E402

project = "evdown_torch"
author = "the evdown_torch authors"
copyright = "the evdown_torch authors"  # noqa: A001
release = evdown_torch.__version__
version = release

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.viewcode"]

# Google-style docstrings, as Tonic and snntorch write them.
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# "Attributes:" sections as :ivar: fields, so that NamedTuple and dataclass fields that autodoc
# documents too are not described twice.
napoleon_use_ivar = True

autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
# Optional readers and plotting libraries need not be installed to build the reference.
autodoc_mock_imports = ["matplotlib", "h5py", "aedat", "faery"]

# Cross-references to torch, NumPy and Tonic types are not resolved (no intersphinx: the
# build runs offline); a broken reference inside this package still shows in the text.
nitpicky = False

html_theme = "alabaster"
html_title = f"evdown_torch {release} API reference"
exclude_patterns = ["_build"]
