"""Sphinx configuration for the gmjax documentation.

Build (from the repository root, after ``pip install -e ".[docs]"``)::

    sphinx-build -W --keep-going -n -b html docs docs/_build/html

Why Sphinx: gmjax's docstrings are Google style with ``:func:`` / ``:class:`` roles, which autodoc and
napoleon render as they are; ``-n -W`` turns every broken cross-reference into a build failure; and myst-nb
renders the notebooks and the Markdown pages (README-style tables, the benchmark results) without a second
tool. Furo is a maintained, readable theme with a light/dark mode and no JavaScript framework.

The API pages under ``docs/api/`` are generated at build time by :func:`write_api_pages` (one page per
public module; ``docs/api/`` is not committed). Every object is documented once, on the page of the public
module that defines it (an object defined in a private module such as ``gmjax.filters._core`` goes to its
package's page); a reference through a re-export (``gmjax.filters.run`` for ``gmjax.filters.base.run``) is
resolved to that page by :func:`resolve_reexport`.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import sys
import warnings
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

import gmjax  # noqa: E402  (after the path set-up above)

project = "gmjax"
author = "The gmjax authors"
copyright = "the gmjax authors; Apache-2.0"  # noqa: A001  (Sphinx's name)
release = gmjax.__version__
version = ".".join(release.split(".")[:2])

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "myst_nb",
]

source_suffix = {".rst": "restructuredtext", ".md": "myst-nb", ".ipynb": "myst-nb"}
exclude_patterns = ["_build", "jupyter_execute", "**.ipynb_checkpoints"]
root_doc = "index"

# the committed notebooks predate nbformat 4.5 cell ids; nbformat adds them in memory and warns
warnings.filterwarnings("ignore", message="Cell is missing an id field")

# -- notebooks: rendered as committed (without outputs); the test suite executes them, the docs never do
nb_execution_mode = "off"
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
suppress_warnings = [
    # the benchmark result pages (benchmarks/results/*.md) are included whole; their headings start at
    # "#" and skip no level, but each file is its own document, so myst may see several top-level titles
    "myst.header",
]

# -- autodoc / napoleon (Google style)
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True
autodoc_class_signature = "separated"
autodoc_default_options = {"show-inheritance": False}
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_ivar = False  # "Attributes:" as attribute entries (the NamedTuple field aliases are skipped)
# sections of the reducer / filter configs (e.g. AGSFConfig): listed like arguments
napoleon_custom_sections = [("Static fields", "params_style"), ("Traced fields", "params_style")]
napoleon_use_rtype = False
napoleon_preprocess_types = False

# -- nitpicky cross-references: a broken reference to a gmjax object fails the build. The names below
# cannot resolve because no inventory of the third-party projects is fetched (CI has no network but the
# package index), or because they are docstring shorthands, not objects:
nitpicky = True
nitpick_ignore_regex = [
    # third-party and standard-library types in signatures (jax.Array, numpy.ndarray, typing.Callable,
    # optax.GradientTransformation, ...): no intersphinx inventory offline
    (r"py:.*", r"(jax|jaxlib|numpy|np|jnp|optax|typing|collections|types|enum|dataclasses|pathlib|"
               r"concurrent|matplotlib|builtins|os)(\..*)?"),
    # builtins written as types in docstrings and signatures
    (r"py:.*", r"(int|float|bool|str|bytes|tuple|list|dict|set|frozenset|object|callable|None|Any|"
               r"Callable|Sequence|Mapping|Iterable|Iterator|Optional|Union|Literal|NamedTuple|type|"
               r"TypeVar|Path|Array|ArrayLike|PRNGKey|Scalar|Weights|Means|Covs|Mask|Vector|Matrix|"
               r"ndarray|PyTree|pytree)"),
]

# -- HTML
html_theme = "furo"
html_title = f"gmjax {release}"
html_static_path: list[str] = []
html_show_sourcelink = False

# -- the API pages: one per public module, generated at build time ----------------------------------

#: Top-level modules in the order of the API index; packages list their public submodules after them
#: (found by :func:`_discover`). A public top-level module missing here is appended at the end.
API_ORDER = [
    "gmjax",
    "gmjax.mixture",
    "gmjax.gaussian",
    "gmjax.metrics",
    "gmjax.quadrature",
    "gmjax.split",
    "gmjax.inputs",
    "gmjax.reduction",
    "gmjax.filters",
    "gmjax.models",
    "gmjax.scenarios",
    "gmjax.pcrb",
    "gmjax.montecarlo",
    "gmjax.fitting",
    "gmjax.tune",
    "gmjax.studies",
]
#: Not part of the library's API: the command-line entry point (documented by ``gmjax --help``).
API_EXCLUDE = {"gmjax.cli"}


def _discover() -> list[str]:
    """Every public module of gmjax (no ``_``-prefixed part), packages followed by their submodules."""
    found = [m.name for m in pkgutil.walk_packages(gmjax.__path__, "gmjax.")
             if not any(p.startswith("_") for p in m.name.split(".")) and m.name not in API_EXCLUDE]
    top = [m for m in API_ORDER if m == "gmjax" or m in found]
    top += sorted(m for m in found if m.count(".") == 1 and m not in top)
    ordered = []
    for module_name in top:
        ordered.append(module_name)
        if module_name != "gmjax":
            ordered += sorted(m for m in found if m.startswith(module_name + "."))
    return ordered


API_MODULES = _discover()


def _public_home(module_name: str) -> str:
    """The public module whose page documents objects defined in ``module_name``: the module itself, or
    for a private module (``gmjax.filters._core``) the nearest public package above it."""
    parts = module_name.split(".")
    while parts and any(p.startswith("_") for p in parts):
        parts.pop()
    return ".".join(parts)


def _exported_names(module) -> list[str]:
    names = getattr(module, "__all__", None)
    if names is None:
        names = [n for n in vars(module) if not n.startswith("_")]
    return [n for n in names if n != "__version__"]


def _page_members(module_name: str) -> list[str]:
    """Names documented on ``module_name``'s page: the exported functions and classes whose home is this
    page, and exported data defined nowhere deeper in :data:`API_MODULES`."""
    module = importlib.import_module(module_name)
    members = []
    for name in _exported_names(module):
        obj = getattr(module, name)
        if inspect.ismodule(obj):
            continue
        defined_in = getattr(obj, "__module__", None)
        if (inspect.isclass(obj) or inspect.isfunction(obj)) and defined_in:
            if _public_home(defined_in) == module_name:
                members.append(name)
            continue
        deeper = [
            m for m in API_MODULES
            if m.startswith(module_name + ".") and getattr(importlib.import_module(m), name, None) is obj
        ]
        if not deeper:
            members.append(name)
    return members


def write_api_pages(app) -> None:
    """Write ``docs/api/<module>.rst`` for every module of :data:`API_MODULES` and ``docs/api/index.rst``."""
    api = DOCS / "api"
    api.mkdir(exist_ok=True)
    documented: dict[str, str] = {}
    for module_name in API_MODULES:
        members = _page_members(module_name)
        module = importlib.import_module(module_name)
        for name in members:
            documented[f"{module_name}.{name}"] = module_name
        children = [m for m in API_MODULES if m.rsplit(".", 1)[0] == module_name]
        lines = [f"``{module_name}``", "=" * (len(module_name) + 4), "", f".. automodule:: {module_name}"]
        if members:
            lines += [f"   :members: {', '.join(members)}"]
        if children and module_name != "gmjax":
            lines += ["", "Submodules", "----------", "", ".. toctree::", "   :maxdepth: 1", ""]
            lines += [f"   {child}" for child in children]
        del module
        _write_if_changed(api / f"{module_name}.rst", "\n".join(lines) + "\n")
    top = [m for m in API_MODULES if m.count(".") <= 1]
    index = [
        "API reference", "=============", "",
        "One page per public module. Every object is documented once, on the page of the module that",
        "defines it; the packages (``gmjax.filters``, ``gmjax.reduction``, ``gmjax.models``) re-export",
        "their submodules' names, so ``gmjax.filters.build_gsf`` is ``gmjax.filters.gsf.build_gsf`` and",
        "``gmjax.reduction.runnalls`` is the function ``gmjax.reduction.runnalls.runnalls``.", "",
        ".. toctree::", "   :maxdepth: 2", "",
    ] + [f"   {m}" for m in top]
    _write_if_changed(api / "index.rst", "\n".join(index) + "\n")
    app.config._gmjax_documented = documented


def _write_if_changed(path: Path, text: str) -> None:
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def resolve_reexport(app, env, node, contnode):
    """Resolve a ``py`` reference that Sphinx could not: through a re-export (``gmjax.filters.run`` is
    documented as ``gmjax.filters.base.run``) or relative to the referring module's package.

    A reference to a gmjax object that exists but has no page of its own (a private helper such as
    ``gmjax.reduction._clustering.similarity_thresholds``, named in a docstring for readers of the source)
    is rendered as plain code. A name that does not exist at all is left unresolved, and ``-n -W`` fails
    the build on it.
    """
    if node.get("refdomain") != "py":
        return None
    target = node.get("reftarget", "").lstrip("~.")
    module_ctx = node.get("py:module") or ""
    class_ctx = node.get("py:class") or ""
    candidates = [target]
    if not target.startswith("gmjax"):
        # the scopes a relative name may live in: the documented object's own module (a docstring's
        # source reads "...: docstring of gmjax.reduction._clustering.gauss_cluster"; the page may be the
        # package's), then the page's class, module and packages
        owner = (node.source or "").rpartition("docstring of ")[2]
        owner_parts = owner.split(".") if owner.startswith("gmjax") else []
        scopes = [".".join(owner_parts[:i]) for i in range(len(owner_parts), 0, -1)]
        if class_ctx:
            scopes.append(f"{module_ctx}.{class_ctx}")
        parts = module_ctx.split(".") if module_ctx else []
        scopes += [".".join(parts[:i]) for i in range(len(parts), 0, -1)]
        candidates += [f"{scope}.{target}" for scope in dict.fromkeys(scopes)]
    domain = env.get_domain("py")
    for candidate in candidates:
        found, obj = _import_dotted(candidate)
        if not found or not candidate.startswith("gmjax"):
            continue
        for name in _documented_names(candidate, obj, domain):
            kind = domain.objects[name].objtype
            role = {"module": "mod", "class": "class", "function": "func", "data": "data",
                    "method": "meth", "attribute": "attr", "property": "attr"}.get(kind, "obj")
            resolved = domain.resolve_xref(env, node["refdoc"], app.builder, role, name, node, contnode)
            if resolved is not None:
                return resolved
        return contnode  # exists, but has no page: plain code
    return None


def _documented_names(dotted: str, obj, domain) -> list[str]:
    """Names under which ``obj`` (reached as ``dotted``) is documented."""
    names = [dotted]
    if inspect.ismodule(obj):
        names.append(obj.__name__)
    defined_in = getattr(obj, "__module__", None)
    qualname = getattr(obj, "__qualname__", None)
    if isinstance(defined_in, str) and isinstance(qualname, str):
        names += [f"{_public_home(defined_in)}.{qualname}", f"{defined_in}.{qualname}"]
    last = dotted.rsplit(".", 1)[-1]
    for name in domain.objects:  # data (tuples, dicts) carry no __module__: match by identity
        if name.endswith("." + last) and name not in names:
            found, other = _import_dotted(name)
            if found and other is obj:
                names.append(name)
    return [n for n in names if n in domain.objects]


def _import_dotted(dotted: str):
    """``(True, obj)`` for a module or attribute path, else ``(False, None)``. Attributes are tried first,
    as Python code sees them (``gmjax.reduction.runnalls`` is the function the package re-exports), then
    the longest importable module prefix (``gmjax.reduction.eise._newton`` lives in the module)."""
    parts = dotted.split(".")
    for attributes_first in (True, False):
        start = 1 if attributes_first else len(parts)
        for i in range(start, 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue
            try:
                for part in parts[i:]:
                    obj = getattr(obj, part)
            except AttributeError:
                break
            return True, obj
    return False, None


def skip_namedtuple_aliases(app, what, name, obj, skip, options):
    """NamedTuple fields are listed by the class docstring's ``Attributes:`` section; skip the generated
    ``Alias for field number N`` properties so they are not documented twice."""
    doc = getattr(obj, "__doc__", None) or ""
    if what == "class" and doc.startswith("Alias for field number"):
        return True
    return None


def setup(app):
    app.connect("builder-inited", write_api_pages)
    app.connect("missing-reference", resolve_reexport)
    app.connect("autodoc-skip-member", skip_namedtuple_aliases)
