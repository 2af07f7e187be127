"""Sphinx configuration of the API reference (``python -m sphinx -W -b html docs/api OUT``)."""

import os
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

# Cross-references to torch, NumPy, Tonic and the standard library are not resolved (no
# intersphinx: the build runs offline). CI builds with -n (nitpicky): every reference to this
# package's own names must resolve; these third-party names (as type hints spell them) are the
# only ones let through.
nitpick_ignore_regex = [
    (r"py:.*", r"(torch|numpy|tonic|pathlib|collections\.abc|contextlib|fractions|os|typing)"
               r"(\..*)?"),
    (r"py:class", r"Tensor|Path|Generator|Fraction"),
]

html_theme = "alabaster"
html_title = f"evdown_torch {release} API reference"
exclude_patterns = ["_build"]


# ----------------------------------------------------------------------------- own references
# The reference documents many names where users import them (``evdown_torch.data.open_source``,
# ``evdown_torch.transforms.Streaming.session``) while docstrings name them where they are
# defined, or relative to the module or class whose docstring they are in. A reference to one
# of the package's own objects that Sphinx does not find resolves to the entry documenting
# that same object (or, for a method, the same name on a documented base class).


def _import(dotted):
    """``(object, module name)`` of a dotted name ``package.module.Class.attr``, or None.

    The longest importable prefix is the module. (A package attribute that shadows its
    submodule, as ``evdown_torch.transforms.calibrate`` the function does the module, is
    :func:`_attribute`'s.)
    """
    import importlib

    parts = dotted.split(".") if dotted else []
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except (ImportError, ValueError):
            continue
        try:
            for part in parts[cut:]:
                obj = getattr(obj, part)
        except AttributeError:
            return None
        return obj, ".".join(parts[:cut])
    return None


def _attribute(dotted):
    """The object ``dotted`` names as attributes from its package down, or None."""
    found = _import(dotted.split(".")[0])
    if found is None:
        return None
    obj = found[0]
    for part in dotted.split(".")[1:]:
        obj = getattr(obj, part, None)
        if obj is None:
            return None
    return obj


def _objects(dotted):
    """The objects a dotted name may mean, by module path or by attribute path (their ids)."""
    found = _import(dotted)
    return {id(o) for o in (None if found is None else found[0], _attribute(dotted))
            if o is not None}


def _scopes(node):
    """``(module, class)`` pairs a bare name in ``node`` is looked up in, innermost first."""
    scopes = [(node.get("py:module") or "", node.get("py:class"))]
    while node is not None:  # the object whose docstring holds the reference, where defined
        source = getattr(node, "source", None)
        if source and "docstring of " in source:
            described = source.rsplit("docstring of ", 1)[1]
            found = _import(described)
            if found is not None:
                module = found[1]
                rest = described[len(module) + 1:].split(".") if described != module else []
                owner = _import(f"{module}.{rest[0]}") if rest else None
                cls = rest[0] if owner is not None and isinstance(owner[0], type) else None
                scopes.insert(0, (module, cls))
            break
        node = node.parent
    return [(m, c) for m, c in scopes if m.startswith("evdown_torch")]


def _same_object(app, env, node, contnode):
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"].lstrip("~.")
    candidates = [target] if target.startswith("evdown_torch.") else []
    for module, cls in _scopes(node):
        candidates += [f"{module}.{cls}.{target}"] if cls else []
        candidates.append(f"{module}.{target}")
    domain = env.get_domain("py")
    last = target.rsplit(".", 1)[-1]
    documented = [(name, entry) for name, entry in domain.objects.items()
                  if name.rsplit(".", 1)[-1] == last]
    for name in candidates:
        wanted = _objects(name)
        if not wanted:
            continue
        owner = _import(name.rsplit(".", 1)[0])
        bases = owner[0].__mro__ if owner and isinstance(owner[0], type) else ()
        for other, entry in documented:
            other_owner = _import(other.rsplit(".", 1)[0])
            same = bool(wanted & _objects(other))
            inherited = other_owner is not None and other_owner[0] in bases
            if same or inherited:
                if os.environ.get("EVDOWN_DOCS_DEBUG"):
                    print(f"resolved {node['reftarget']} -> {other}")
                return domain.resolve_xref(env, node["refdoc"], app.builder, entry.objtype,
                                           other, node, contnode)
    return None


def _public_bases(app, name, obj, options, bases):
    """Show a class's bases as the reference documents them: private ones by their own bases."""
    def private(base):
        if base.__name__.startswith("_"):
            return True
        module = base.__module__
        if not module.startswith("evdown_torch") or "._" not in f".{module}":
            return False
        parent = _import(module.split("._")[0])
        return parent is None or getattr(parent[0], base.__name__, None) is not base

    changed = True
    while changed:
        changed = False
        for i, base in enumerate(bases):
            if isinstance(base, type) and private(base):
                bases[i:i + 1] = [b for b in base.__bases__ if b is not object] or [object]
                changed = True
                break


def setup(app):
    app.connect("missing-reference", _same_object)
    app.connect("autodoc-process-bases", _public_bases)
