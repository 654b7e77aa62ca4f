"""Sphinx configuration of the torchrl_recon site: the Markdown guides and the API reference.

``make docs`` builds it with ``-W -n`` (warnings and broken references fail the build). Nothing
here touches the network: there is no intersphinx (its inventories are downloaded), so names of
torch, TorchRL, tensordict and the other libraries are left unlinked (``nitpick_ignore_regex``).

The API reference is written when a build starts into ``docs/api/`` (ignored by git): one page per
package listing the names of its ``__all__`` (``API_PACKAGES``), then, one section each, the
names its modules make public (their ``__all__``) that the package does not export itself
(``API_MODULES``), and one page per name made by autosummary from its docstring. Each object is
documented once, under the package that exports it (or else its module; a name that two
packages export, under its home package: ``API_REEXPORTS``); a reference to it by
its defining module (``:class:`~torchrl_recon.planners.cem.CEMPlanner```) is resolved to that
page.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import inspect
import pkgutil
import sys
from pathlib import Path

from docutils import nodes
from sphinx import addnodes
from sphinx.ext import autosummary, viewcode
from sphinx.pycode import ModuleAnalyzer
from sphinx.transforms.post_transforms import SphinxPostTransform
from sphinx.util import inspect as sphinx_inspect
from sphinx.util import logging

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

import torchrl_recon  # noqa: E402

logger = logging.getLogger("torchrl_recon.docs")

project = "torchrl_recon"
author = "torchrl_recon contributors"
copyright = "torchrl_recon contributors"
release = version = torchrl_recon.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "myst_parser",
]

root_doc = "index"
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
# docs/results holds run outputs (JSON, plots, archives), not pages: the guides' figures are
# copied from it as images, links to its files as downloads, links to its folders shown as
# repository paths (FolderLinks).
exclude_patterns = ["_build", "results", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]

html_theme = "furo"
html_title = f"torchrl_recon {release}"
html_static_path = ["_static"]
html_css_files = ["custom.css"]

# The guides are GitHub-flavoured Markdown: headings get GitHub's anchors, so that
# ``planning.md#mpcpolicy`` resolves both on GitHub and here.
myst_heading_anchors = 6
myst_enable_extensions = ["dollarmath"]

napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
# ``Args:`` entries may name several parameters (``low, high: action bounds``): a plain field
# list shows them as written (``:param low, high:`` would read ``low`` as a type).
napoleon_use_param = False
napoleon_use_keyword = False
# An ``Attributes:`` entry keeps its docstring's words; the type is in the class signature.
napoleon_attr_annotations = False

autosummary_generate = True
# A summary line is a docstring's first sentence: not one cut at "(paper eq." or "Fig.".
autosummary.WELL_KNOWN_ABBREVIATIONS = (
    *autosummary.WELL_KNOWN_ABBREVIATIONS,
    *("eq.", "Eq.", "Fig.", "Sec.", "cf."),
)
autosummary_imported_members = False
autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_inherit_docstrings = False  # an override without a docstring is not documented again
autodoc_default_options = {"show-inheritance": True}
autodoc_preserve_defaults = True

# No inventories offline: references to these libraries' objects (type hints, base classes,
# ``:class:`torchrl.envs.GymEnv```) stay plain text instead of failing the build.
nitpick_ignore_regex = [
    ("py:.*", r"(torch|torchrl|tensordict|gymnasium|gym|numpy|np|hydra|omegaconf|scipy)(\..*)?"),
    ("py:.*", r"(matplotlib|pybullet|wandb|yaml|filelock|tqdm|submitit|pytest)(\..*)?"),
    ("py:.*", r"(pathlib|os|collections|typing|types|dataclasses|enum|json|math|io|abc)(\..*)?"),
    ("py:.*", r"(concurrent|contextlib|functools|random|subprocess|threading|tarfile)(\..*)?"),
    ("py:class", r"(Tensor|TensorDict|TensorDictBase|NestedKey|Path|Any|Callable|Sequence)"),
    ("py:class", r"(DictConfig|ListConfig|EnvBase|Logger|Figure|Axes|Module|Generator)"),
    ("py:class", r"(Iterable|Iterator|Mapping|Generator|Literal|Self|TypeVar|NamedTuple)"),
    ("py:class", r"(int|float|str|bool|bytes|dict|list|tuple|object|type|None|slice|complex)"),
    ("py:class", r"(Exception|ValueError|TypeError|RuntimeError|KeyError|Warning)"),
    ("py:class", r"(UserWarning|FileNotFoundError|OSError|NotImplementedError)"),
]

# The packages of the API reference, in the order of the sidebar: each one's page lists the
# names of its ``__all__``.
API_PACKAGES = (
    "torchrl_recon.envs",
    "torchrl_recon.data",
    "torchrl_recon.collectors",
    "torchrl_recon.modules",
    "torchrl_recon.estimators",
    "torchrl_recon.objectives",
    "torchrl_recon.fitting",
    "torchrl_recon.trainers",
    "torchrl_recon.planners",
    "torchrl_recon.transforms",
    "torchrl_recon.policies",
    "torchrl_recon.evaluation",
    "torchrl_recon.experiments",
    "torchrl_recon.reports",
    "torchrl_recon.errors",
)

# Names a package exports for existing imports that another package of the reference exports
# too (their home): documented once, under the home package.
API_REEXPORTS = {"torchrl_recon.modules": "torchrl_recon.estimators"}

# Modules whose public names (their ``__all__``) their package does not export: each has a
# section on its package's page, in this order.
API_MODULES = {
    "torchrl_recon.trainers": ("torchrl_recon.trainers.configs",),
    "torchrl_recon.planners": tuple(
        f"torchrl_recon.planners.{module}"
        for module in ("base", "sampling", "cem", "elite_memory", "noise", "registry", "bounds")
        + ("beta", "planning_model", "executors", "cpu_threads", "torchrl_models", "model_env")
    ),
}

# The site's navigation, by caption, in the order of the sidebar. docs/index.md links every
# guide for GitHub; the toctrees are added to it here (SITE_TOCTREES) so that GitHub does not
# show them as code.
NAVIGATION = {
    "Environments": [
        "envs/industrial_benchmark",
        "envs/drone",
        "envs/minitaur",
        "custom_env",
    ],
    "Guides": [
        "modules",
        "training",
        "planning",
        "online",
        "torchrl_trainer",
        "torchrl_world_models",
        "experiments",
        "clusters",
        "testing",
    ],
    "Results": ["standard_tasks", "uncertainty_estimators", "benchmarks", "reproduction"],
    "API reference": [f"api/{pkg.rsplit('.', 1)[-1]}" for pkg in API_PACKAGES],
}
SITE_TOCTREES = "".join(
    f"\n\n```{{toctree}}\n:hidden:\n:caption: {caption}\n\n" + "\n".join(pages) + "\n```\n"
    for caption, pages in NAVIGATION.items()
)


def public_names(package: str) -> list[str]:
    """The names ``package`` exports (its ``__all__``), less those documented under their home
    package (``API_REEXPORTS``)."""
    own = importlib.import_module(package)
    home = API_REEXPORTS.get(package)
    if home is None:
        return list(own.__all__)
    home = importlib.import_module(home)
    at_home = {id(getattr(home, name)) for name in home.__all__}
    return [name for name in own.__all__ if id(getattr(own, name)) not in at_home]


def module_names(module: str) -> list[str]:
    """The names of ``module``'s ``__all__`` that its package does not export (the same object)."""
    package = importlib.import_module(module.rsplit(".", 1)[0])
    own = importlib.import_module(module)
    exported = {id(getattr(package, name)) for name in package.__all__}
    return [name for name in own.__all__ if id(getattr(own, name)) not in exported]


def api_names() -> list[str]:
    """The full name of every object the API reference documents, in the order of its pages."""
    names = []
    for pkg in API_PACKAGES:
        names += [f"{pkg}.{name}" for name in public_names(pkg)]
        for module in API_MODULES.get(pkg, ()):
            names += [f"{module}.{name}" for name in module_names(module)]
    return names


def summary_table(module: str, names: list[str]) -> list[str]:
    """A page's table of ``names`` of ``module``, each with a page of its own."""
    page = [f".. currentmodule:: {module}", "", ".. autosummary::", "   :toctree: generated"]
    return page + ["   :nosignatures:", ""] + [f"   {name}" for name in names] + [""]


def write_if_changed(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` unless it already holds it (keeps incremental builds cheap)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def write_api_pages() -> None:
    """One page per package in ``docs/api/``: its docstring and a table of its ``__all__``, then
    a section per module of ``API_MODULES``: its docstring and a table of its other names."""
    api = DOCS / "api"
    for pkg in API_PACKAGES:
        page = [pkg, "=" * len(pkg), "", f".. automodule:: {pkg}", "   :no-members:", ""]
        page += summary_table(pkg, public_names(pkg))
        for module in API_MODULES.get(pkg, ()):
            page += [module, "-" * len(module), "", f".. automodule:: {module}", "   :no-members:"]
            page += [""] + summary_table(module, module_names(module))
        write_if_changed(api / f"{pkg.rsplit('.', 1)[-1]}.rst", "\n".join(page).rstrip() + "\n")
    # a page of a name (or package) no longer exported would fail the build
    stale = [p for p in api.glob("generated/*.rst") if p.stem not in _api_names()]
    packages = {pkg.rsplit(".", 1)[-1] for pkg in API_PACKAGES}
    stale += [p for p in api.glob("*.rst") if p.stem not in packages]
    for page in stale:
        page.unlink()


def _public_objects() -> dict[int, str]:
    """``id(object) -> public path`` for every object the API reference documents."""
    found = {}
    for path in api_names():
        module, name = path.rsplit(".", 1)
        found.setdefault(id(getattr(importlib.import_module(module), name)), path)
    return found


def _submodules(package: str) -> list[str]:
    module = importlib.import_module(package)
    names = [package]
    if hasattr(module, "__path__"):
        names += [m.name for m in pkgutil.iter_modules(module.__path__, package + ".")]
    return names


def defining_attr_doc(fullname: str) -> list[str]:
    """The docstring of a module-level constant ``pkg.NAME`` written where it is assigned.

    autodoc reads an attribute's docstring from the module it documents it in (the package's
    ``__init__``); a re-exported constant's docstring is in the submodule that assigns it.
    """
    pkg, name = fullname.rsplit(".", 1)
    value = getattr(importlib.import_module(pkg), name)
    for modname in _submodules(pkg):
        module = importlib.import_module(modname)
        if getattr(module, name, None) is not value:
            continue
        try:
            docs = ModuleAnalyzer.for_module(modname).find_attr_docs()
        except Exception:  # noqa: BLE001  (a module without source: no docstring there)
            continue
        if ("", name) in docs:
            return list(docs[("", name)])
    return []


@functools.cache
def _api_names() -> frozenset[str]:
    return frozenset(api_names())


def process_docstring(app, what, name, obj, options, lines) -> None:
    """Fill in a re-exported constant's docstring; warn when a public name has none."""
    if name not in _api_names():
        return
    if what in ("data", "attribute"):
        own = defining_attr_doc(name)
        type_doc = inspect.getdoc(type(obj)) or ""
        if own or "\n".join(lines).strip() == type_doc.strip():
            lines[:] = own  # not the docstring of the value's type (``dict``, ``tuple``)
    if not any(line.strip() for line in lines):
        logger.warning("public name %s has no docstring", name, type="docstring")


def dataclass_factories(app, what, name, obj, options, signature, return_annotation):
    """Show a dataclass field's ``default_factory`` as a call (``= dict()``): Python renders it
    ``<factory>``, which no signature parser reads (the signature falls apart at its commas)."""
    if not signature or "<factory>" not in signature or not dataclasses.is_dataclass(obj):
        return None
    for f in dataclasses.fields(obj):
        if f.init and f.default_factory is not dataclasses.MISSING:
            call = getattr(f.default_factory, "__name__", "")
            call = f"{call}()" if call.isidentifier() else "..."
            signature = signature.replace("<factory>", call, 1)
    return signature, return_annotation


def init_signatures(app, what, name, obj, options, signature, return_annotation):
    """A class whose base takes ``(*args, **kwargs)`` in ``__new__`` or in its metaclass's
    ``__call__`` (tensordict's TensorDictModuleBase, TorchRL's EnvBase, Trainer, samplers) shows
    its own ``__init__``'s parameters, as its docstring's ``Args:`` describe them."""
    init = getattr(obj, "__init__", None)
    if what != "class" or signature != "(*args, **kwargs)" or not _is_library(init):
        return None
    aliases = app.config.autodoc_type_aliases
    own = sphinx_inspect.signature(init, bound_method=True, type_aliases=aliases)
    short = app.config.autodoc_typehints_format == "short"
    text = sphinx_inspect.stringify_signature(
        own, show_return_annotation=False, unqualified_typehints=short
    )
    return text, None


def _is_library(obj) -> bool:
    return (getattr(obj, "__module__", None) or "").split(".")[0] == "torchrl_recon"


def skip_foreign_member(app, what, name, obj, skip, options):
    """Skip methods a class inherits from torch, TorchRL or tensordict (their docs are theirs);
    keep those it inherits from the library's own bases and mixins."""
    func = getattr(obj, "fget", None) or getattr(obj, "func", None) or obj
    if (inspect.isroutine(func) or isinstance(obj, property)) and not _is_library(func):
        return True
    return None


def public_bases(app, name, obj, options, bases) -> None:
    """Show a class's public bases: a private base of the library (a mixin) is replaced by its
    own bases, whose members the class's page documents anyway."""
    public = app.env.temp_data.setdefault("public_objects", _public_objects())

    def expand(cls) -> list:
        if inspect.isclass(cls) and _is_library(cls) and id(cls) not in public:
            return [b for base in cls.__bases__ for b in expand(base)]
        return [cls]

    shown = []
    for base in bases:
        for cls in expand(base):
            if cls not in shown:
                shown.append(cls)
    bases[:] = [cls for cls in shown if cls is not object] or [object]


def _lookup(path: str):
    """The object ``path`` (``pkg.module.Name.attr``) names, or None."""
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return obj
    return None


def _scopes(node) -> list[str]:
    """Where a short name in a docstring is looked up: the page's module and class, then the
    module that defines the documented object (``torchrl_recon.planners.cem`` for CEMPlanner)."""
    module, cls = node.get("py:module") or "", node.get("py:class") or ""
    scopes = [f"{module}.{cls}" if cls else module, module]
    documented = _lookup(f"{module}.{cls}") if cls else None
    if documented is None and "/generated/" in node.get("refdoc", ""):
        documented = _lookup(node["refdoc"].rsplit("/", 1)[-1])
    home = getattr(documented, "__module__", None)
    if home and home.startswith("torchrl_recon"):
        scopes.append(home)
    return [scope for scope in scopes if scope]


def resolve_by_object(app, env, node, contnode):
    """Resolve a reference to a public object by another path (its defining module,
    ``torchrl_recon.planners.cem.CEMPlanner``, or a name imported where the docstring is) to
    its page under the package that exports it."""
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"].lstrip("~.")
    paths = [target] if target.startswith("torchrl_recon.") else []
    paths += [f"{scope}.{target}" for scope in _scopes(node)]
    public_objects = app.env.temp_data.setdefault("public_objects", _public_objects())
    if "." not in target:  # a short name that one public name has (``RecipeError``)
        same = [n for n in _api_names() if n.rsplit(".", 1)[1] == target]
        paths += same if len(same) == 1 else []
    for path in paths:
        obj = _lookup(path)
        if obj is None:
            continue
        public = public_objects.get(id(obj))
        if public is None and not inspect.ismodule(obj) and "." in path:
            # a member of a public class: Class.member under the class's public path
            owner = public_objects.get(id(_lookup(path.rsplit(".", 1)[0])))
            public = f"{owner}.{path.rsplit('.', 1)[1]}" if owner else None
        if public is None or public == target:
            continue
        new = node.deepcopy()
        new["reftarget"] = public
        new["refspecific"] = False
        found = env.get_domain("py").resolve_xref(
            env, node["refdoc"], app.builder, node["reftype"], public, new, contnode
        )
        if found is not None:
            return found
    return None


def viewcode_backlink_ids(app, doctree, docname) -> None:
    """Give each object the id that the ``[docs]`` link of its source page points at.

    viewcode keeps one documenting module per source module (the first it meets) and links every
    object of that source back to ``that module.name``. A module whose names are documented partly
    under its package (``planners.base.PlannerBase`` as ``planners.PlannerBase``) and partly
    under itself (``planners.base.PlanFlags``) would link some of them to no anchor."""
    modules = getattr(app.env, "_viewcode_modules", {})
    for signode in doctree.findall(addnodes.desc_signature):
        module, fullname = signode.get("module"), signode.get("fullname")
        if not module or not fullname:
            continue
        entry = modules.get(viewcode._get_full_modname(module, fullname) or "")
        anchor = f"{entry[3]}.{fullname}" if entry else None
        if anchor and entry[3] != module and anchor not in signode["ids"]:
            signode["ids"].append(anchor)


class FolderLinks(SphinxPostTransform):
    """A guide's link to a repository folder (``[...](results/control_bands/)``) or to a page
    the site leaves out (``results/README.md``) becomes its path in the repository: GitHub
    opens it, a built site has no page for it.

    Links to files that are not pages (figures, scripts) are myst's downloads, copied into the
    build."""

    default_priority = 5  # before myst's resolver (9) warns that no page matches

    def run(self, **kwargs) -> None:
        for node in list(self.document.findall(addnodes.pending_xref)):
            if node.get("reftype") != "myst" or node.get("refdomain") not in (None, "", "doc"):
                continue
            target = node["reftarget"].split("#", 1)[0]
            if node.get("refdomain") == "doc":
                # a page of the repository that the site leaves out (docs/results/README.md)
                if target in self.env.all_docs:
                    continue
                found = [p for p in DOCS.glob(target + ".*") if p.suffix in source_suffix]
                if not found:
                    continue
                local, shown = found[0], found[0].relative_to(ROOT).as_posix()
            else:
                _, path = self.env.relfn2path(target, node.get("refdoc", self.env.docname))
                local = Path(path).resolve()
                if not target or not local.is_dir():
                    continue
                shown = local.relative_to(ROOT).as_posix() + "/"
            text = node.astext()
            replacement = nodes.inline(classes=["repo-path"])
            if shown.rstrip("/").endswith(text.strip("/")):
                replacement += nodes.literal(shown, shown)
            else:
                replacement += node.children
                replacement += nodes.Text(" (")
                replacement += nodes.literal(shown, shown)
                replacement += nodes.Text(")")
            node.replace_self(replacement)


def add_guides_toctree(app, docname, source) -> None:
    """Append the site's toctrees to docs/index.md (GitHub shows the page without them)."""
    if docname == root_doc:
        source[0] += SITE_TOCTREES


def setup(app) -> None:
    write_api_pages()  # before autosummary (builder-inited) looks for the pages to fill in
    app.connect("source-read", add_guides_toctree)
    app.connect("autodoc-process-docstring", process_docstring)
    app.connect("autodoc-process-signature", dataclass_factories)
    app.connect("autodoc-process-signature", init_signatures)
    app.connect("autodoc-skip-member", skip_foreign_member)
    app.connect("autodoc-process-bases", public_bases)
    app.connect("missing-reference", resolve_by_object)
    app.connect("doctree-resolved", viewcode_backlink_ids)
    app.add_post_transform(FolderLinks)
