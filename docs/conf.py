"""Sphinx configuration of the mshoot documentation (``make docs`` -> out/docs/html)."""
import pathlib
import sys

HERE = pathlib.Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / '_ext'))

project = 'mshoot'
author = 'mshoot developers'
copyright = 'mshoot developers; BSD-3-Clause (package.xml)'  # noqa: A001 (Sphinx's name)

extensions = [
    'myst_parser',
    'sphinx.ext.autodoc',
    'sphinx.ext.napoleon',
    'mshoot_docs',
]
# Intersphinx (links into the Python, NumPy and SciPy documentation) is left out: it fetches
# each project's objects.inv over the network at every build, and neither the development
# machines nor CI have one; without the inventories every build would warn, and -W fails.

source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
root_doc = 'index'
exclude_patterns = ['_build', '_ext', 'README.md']

# MyST: plain Markdown pages work as they are (a page's headings may start at any level;
# '#' is its title). Anchors for [text](page.md#a-heading) links up to level 3.
myst_enable_extensions = ['colon_fence', 'deflist']
myst_heading_anchors = 3
# A page may skip a heading level (# then ###): Markdown allows it; the site need not warn.
# A docstring's type field names a type by its short name ("str or path"); where two classes
# have an attribute of that name (Library.path, ModelCard.path) the link is ambiguous, and the
# site leaves such a type unlinked rather than fail: ref.python is only that ambiguity.
suppress_warnings = ['myst.header', 'ref.python']

# autodoc + napoleon: the numpydoc docstrings of mshoot_core.
autodoc_default_options = {'members': True, 'show-inheritance': True}
autodoc_member_order = 'bysource'
autodoc_typehints = 'description'
autodoc_preserve_defaults = True
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False

html_theme = 'furo'
html_title = 'mshoot'
html_static_path = []
html_show_sourcelink = False
