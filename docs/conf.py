"""Sphinx configuration of the stochlap_torch documentation.

Build (what CI runs; the ``docs`` extra installs the tools)::

    python -m sphinx -W --keep-going -n -b html docs docs/_build/html
"""

from __future__ import annotations

import importlib
import inspect
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))  # the checkout's package, not an installed copy

from sphinx.ext import intersphinx  # noqa: E402

import stochlap_torch  # noqa: E402

project = "stochlap_torch"
author = "stochlap_torch contributors"
copyright = "stochlap_torch contributors, MIT licence"
release = stochlap_torch.__version__
version = release

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.intersphinx",
    "sphinx.ext.viewcode",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "_inventories", "auto_examples/*.ipynb", "auto_examples/*.py"]
templates_path: list[str] = []

html_theme = "furo"
html_title = f"stochlap_torch {release}"
html_static_path: list[str] = []

# -- MyST -------------------------------------------------------------------------------------
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3

# -- autodoc + napoleon -----------------------------------------------------------------------
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_default_options = {"members": True, "show-inheritance": True}
# (the subpackage pages add undoc-members: their public constants have no docstrings)
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
napoleon_attr_annotations = False
napoleon_use_ivar = True  # the fields are documented by autodoc (undoc-members) once
autodoc_inherit_docstrings = False  # forward() would show torch.nn.Module.forward's text

# -- intersphinx ------------------------------------------------------------------------------
# The build must pass offline (CI reaches PyPI only), so each project's inventory is read from
# a small local file in _inventories/ (written by _inventories/make_inventories.py: only the
# names these docs reference, with their pages on the projects' sites); a build with network
# access tries the project's own objects.inv first and falls back to the local one.
_INVENTORIES = DOCS / "_inventories"
_SITES = {
    "python": "https://docs.python.org/3/",
    "torch": "https://docs.pytorch.org/docs/stable/",
    "numpy": "https://numpy.org/doc/stable/",
    "scipy": "https://docs.scipy.org/doc/scipy/",
    "torch_geometric": "https://pytorch-geometric.readthedocs.io/en/latest/",
    "trimesh": "https://trimesh.org/",
}
_ONLINE = False  # set True to prefer the live inventories (needs network access)
_LOCAL = {name: str(_INVENTORIES / f"{name}.inv") for name in _SITES}
intersphinx_mapping = {
    name: (url, (None, _LOCAL[name]) if _ONLINE else _LOCAL[name]) for name, url in _SITES.items()
}
intersphinx_timeout = 10

# -- nitpicky ---------------------------------------------------------------------------------
nitpicky = True
# Names that are no Python objects: the shapes and kinds written in docstrings' type fields.
nitpick_ignore_regex = [
    # The robust structure's internal parts, named in the field types of StructureLevel.
    ("py:class", r"stochlap_torch\.robust\.pyramid\.Interpolation"),
    ("py:class", r"stochlap_torch\.robust\.heat\.LevelSemigroup"),
    ("py:class", r"stochlap_torch\.robust\.pyramid\.StateReader"),
    ("py:class", r"optional"),
    ("py:class", r"array-like|array_like|path-like|file-like"),
]

# -- sphinx-gallery ---------------------------------------------------------------------------
# Only the cheap examples (``plot_*.py``, seconds on the bundled mesh) run at build time; the
# others take minutes on the shared meshes and are shown as code with their committed outputs
# (figures in docs/figures, tables in the reports), listed by COMMITTED_OUTPUTS below.
sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": str(DOCS / "auto_examples"),
    "filename_pattern": r"/plot_",
    "ignore_pattern": r"(report_blocks|segmentation_data|__init__)\.py$",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "matplotlib_animations": False,
    "image_scrapers": ("matplotlib",),
    "show_memory": False,
    "min_reported_time": 60,
    "write_computation_times": False,
}

#: Example script -> what it writes into the repository, shown under its gallery page.
COMMITTED_OUTPUTS = {
    "paper_figures": [
        "figures/fig01_sparsity.png",
        "figures/fig03_sphere_multiscale.png",
        "figures/fig04_sphere_displacement.png",
        "figures/fig05_spectral_vs_stochastic.png",
        "figures/fig10_saliency_gallery.png",
        "figures/fig11_laplacians.png",
        "figures/fig12_gargoyle_interest.png",
        "figures/fig13_camel_interest.png",
        "figures/fig14_cow_interest.png",
        "figures/readme_multiscale_bunny.png",
        "figures/readme_interest_armadillo.png",
        "spot_saliency.png",
    ],
    "resolution_consistency": [":doc:`/RESULTS_EVALUATION` (resolution consistency tables)"],
    "saliency_analysis": [":doc:`/RESULTS_EVALUATION` (valence, curvature, extremity tables)"],
    "train_segmentation": [":doc:`/guide/training` (the segmentation table)"],
    "local_convexity": [":doc:`/guide/variants` (the coarse convexity scores)"],
}


def finish_script_pages(app) -> None:
    """Give each gallery page of a script that is not run its title (the scripts' docstrings
    open with a sentence, not the title sphinx-gallery's pages and references expect) and a
    "Committed output" section."""
    gallery = Path(app.srcdir) / "auto_examples"
    for script, outputs in COMMITTED_OUTPUTS.items():
        page = gallery / f"{script}.rst"
        if not page.exists():
            continue
        text = page.read_text()
        label = f".. _sphx_glr_auto_examples_{script}.py:\n"
        title = f"examples/{script}.py"
        text = text.replace(label, f"{label}\n{title}\n{'=' * len(title)}\n", 1)
        lines = ["", "Committed output", "----------------", ""]
        lines.append(
            "This script takes minutes on the shared meshes, so the build does not run it; "
            "this is what its last run wrote into the repository."
        )
        lines.append("")
        for output in outputs:
            if output.endswith(".png"):
                lines += [f".. image:: /{output}", f"   :alt: {Path(output).stem}", ""]
            else:
                lines += [f"* {output}", ""]
        head, sep, tail = text.partition("\n.. _sphx_glr_download")
        page.write_text(head + "\n".join(lines) + "\n" + sep + tail)


# -- one documented name per object ----------------------------------------------------------
# The package re-exports its public names at the root (``sl.Mesh``), where they are documented;
# the subpackage pages document the rest of each subpackage's ``__all__``. A docstring that
# names an object by another of its import paths (``stochlap_torch.mesh.Mesh``) is resolved to
# the documented name of that same object.
_current_module: list[str] = [""]


def _note_module(app, what, name, obj, options, lines) -> None:
    if what == "module":
        _current_module[0] = name


def skip_root_exports(app, what, name, obj, skip, options):
    """In a subpackage page, skip what the package root already documents."""
    module = _current_module[0]
    if what != "module" or module in ("", "stochlap_torch"):
        return None
    if name in stochlap_torch.__all__ and getattr(stochlap_torch, name) is obj:
        return True
    return None


def _resolve(path: str):
    """The object a dotted path names (a module, or an attribute of one), or None."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            value = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                value = getattr(value, part)
        except AttributeError:
            return None
        return value
    return None


def _contexts(node) -> list[str]:
    """The modules a relative name in this reference may be relative to, innermost first: the
    module the docstring's object is defined in and its parents, then the documented module."""
    contexts = []
    source = str(node.source or "")
    if "docstring of " in source:
        dotted = source.split("docstring of ", 1)[1].split(":", 1)[0]
        parts = dotted.split(".")
        contexts += [".".join(parts[:cut]) for cut in range(len(parts), 0, -1)]
    if node.get("py:module"):
        contexts.append(node["py:module"])
    return [context for context in contexts if context.startswith("stochlap_torch")]


def _documented_name(domain, target, last: str) -> str | None:
    """The name, ending in ``last``, under which ``target`` (an object) is documented, or None."""
    for name, entry in domain.objects.items():
        if entry.aliased or entry.objtype == "module" or not name.startswith("stochlap_torch"):
            continue
        # the same object under the same last name (ints and strings are shared objects)
        if name.rpartition(".")[2] == last and _resolve(name) is target:
            return name
    return None


#: Bare names in attributes' string annotations, and the classes they stand for.
_ANNOTATION_NAMES = {"Tensor": "torch.Tensor", "Path": "pathlib.Path"}


def resolve_aliases(app, env, node, contnode):
    """Resolve a reference to an object or module of the package that the API reference
    documents under another name.

    ``stochlap_torch.mesh.Mesh``, ``Mesh`` or ``.container.Mesh`` (relative to the docstring's
    module) name the object documented as ``stochlap_torch.Mesh``; a module that has no page
    of its own (``stochlap_torch.robust.heat``) links to the page of the nearest package
    above it that has one. A name that resolves to no object stays unresolved (an error).
    """
    if node.get("refdomain") != "py":
        return None
    if node["reftarget"] in _ANNOTATION_NAMES:
        # an attribute's string annotation (``from torch import Tensor``) that autodoc could
        # not evaluate: the class it names, resolved by its project's inventory
        node = node.deepcopy()
        node["reftarget"] = _ANNOTATION_NAMES[node["reftarget"]]
        return intersphinx.missing_reference(app, env, node, contnode)
    target_name = node["reftarget"].lstrip(".~")
    domain = env.get_domain("py")
    candidates = [target_name]
    candidates += [f"{context}.{target_name}" for context in _contexts(node)]
    candidates.append(f"stochlap_torch.{target_name}")  # the root's re-exports
    for candidate in candidates:
        if not candidate.startswith("stochlap_torch"):
            continue
        target = _resolve(candidate)
        if target is None:
            continue
        if inspect.ismodule(target):
            name = target.__name__
            while name and name not in domain.modules:
                name = name.rpartition(".")[0]
            if not name:
                return None
            return domain.resolve_xref(
                env, node["refdoc"], app.builder, "mod", name, node, contnode
            )
        name = _documented_name(domain, target, candidate.rpartition(".")[2])
        if name is not None:
            return domain.resolve_xref(
                env, node["refdoc"], app.builder, node["reftype"], name, node, contnode
            )
    return None


def check_every_public_name(app, env) -> None:
    """Warn (an error under -W) for a public name the API reference does not document."""
    documented = set(env.get_domain("py").objects)
    missing = []
    modules = ["stochlap_torch", *(f"stochlap_torch.{name}" for name in PUBLIC_SUBPACKAGES)]
    for module_name in modules:
        module = importlib.import_module(module_name)
        for name in module.__all__:
            if name.startswith("__"):
                continue
            if f"{module_name}.{name}" in documented:
                continue
            if name in stochlap_torch.__all__ and f"stochlap_torch.{name}" in documented:
                continue
            missing.append(f"{module_name}.{name}")
    if missing:
        from sphinx.util import logging

        logging.getLogger(__name__).warning(
            "public names missing from the API reference: %s", ", ".join(missing)
        )


#: The subpackages whose ``__all__`` the API reference documents (docs/api/).
PUBLIC_SUBPACKAGES = (
    "nn",
    "mesh",
    "params",
    "diffusion",
    "robust",
    "features",
    "saliency_maps",
    "interest",
    "learning",
    "operators",
    "baselines",
    "evaluation",
    "viz",
    "sparse",
)


def public_bases(app, name, obj, options, bases) -> None:
    """Show a class's public bases: a private one (a layers' shared ``forward``) is an
    implementation detail, replaced by its own public bases."""
    while any(base.__name__.startswith("_") for base in bases):
        bases[:] = [
            public
            for base in bases
            for public in (base.__bases__ if base.__name__.startswith("_") else (base,))
        ]


def setup(app):
    app.connect("autodoc-process-bases", public_bases)
    app.connect("builder-inited", finish_script_pages, priority=900)
    app.connect("autodoc-process-docstring", _note_module)
    app.connect("autodoc-skip-member", skip_root_exports)
    app.connect("missing-reference", resolve_aliases)
    app.connect("env-check-consistency", check_every_public_name)
