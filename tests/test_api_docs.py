"""The API reference (docs/api): docstrings that Napoleon renders as written, every reference
to the package's own names resolving, and no contract file cited to users."""

from __future__ import annotations

import functools
import importlib
import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _public(module) -> list[str]:
    names = getattr(module, "__all__", None)
    return list(names) if names is not None else [n for n in vars(module) if n[:1] != "_"]


def _attribute_docstrings() -> list[tuple[str, str]]:
    """``(name, docstring)`` of the attributes and properties the reference documents.

    The module data of each ``automodule`` of docs/api, and the attributes (``#:`` or a
    docstring below) and properties of the classes it shows, their evdown_torch bases' too.
    """
    import re

    from sphinx.pycode import ModuleAnalyzer

    def attribute_docs(module_name: str) -> dict[tuple[str, str], list[str]]:
        analyzer = ModuleAnalyzer.for_module(module_name)
        analyzer.analyze()
        return analyzer.attr_docs

    rst = "".join(p.read_text(encoding="utf-8") for p in (ROOT / "docs" / "api").glob("*.rst"))
    found: dict[str, str] = {}
    for name in re.findall(r"^\.\. automodule:: (\S+)", rst, re.M):
        module = importlib.import_module(name)
        for (owner, attribute), lines in attribute_docs(name).items():
            if owner == "" and attribute in _public(module):
                found[f"{name}.{attribute}"] = "\n".join(lines)
        for member in _public(module):
            cls = getattr(module, member, None)
            if not inspect.isclass(cls):
                continue
            for base in cls.__mro__:
                if not base.__module__.startswith("evdown_torch"):
                    continue
                docs = attribute_docs(base.__module__)
                for (owner, attribute), lines in docs.items():
                    if owner == base.__qualname__ and not attribute.startswith("_"):
                        found[f"{base.__module__}.{owner}.{attribute}"] = "\n".join(lines)
                for attribute, value in vars(base).items():
                    if isinstance(value, (property, functools.cached_property)) and (
                            value.__doc__ and not attribute.startswith("_")):
                        found[f"{base.__module__}.{base.__qualname__}.{attribute}"] = (
                            inspect.cleandoc(value.__doc__))
    return sorted(found.items())


def test_napoleon_reads_no_attribute_docstring_as_a_type():
    # An attribute's docstring whose first line is "X: Y" renders as "Type: X" with Y below
    # (Napoleon's inline attribute type): types come from the annotations here.
    from sphinx.ext.napoleon import Config
    from sphinx.ext.napoleon.docstring import GoogleDocstring

    config = Config(napoleon_use_ivar=True)
    documented = _attribute_docstrings()
    assert len(documented) > 30
    misread = [name for name, doc in documented
               if any(line.startswith(":type:") for line in
                      GoogleDocstring(doc, config, what="attribute", name="a").lines())]
    assert misread == []


def test_no_docstring_cites_the_contract_file_by_its_internal_name():
    # Users have docs/semantics.md; the contract's working name is not theirs.
    cited = [str(path.relative_to(ROOT)) for path in (ROOT / "evdown_torch").rglob("*.py")
             if "SEMANTICS.md" in path.read_text(encoding="utf-8")]
    assert cited == []


@pytest.mark.slow
def test_the_api_reference_builds_with_every_own_reference_resolved(tmp_path):
    pytest.importorskip("sphinx")
    done = subprocess.run(
        [sys.executable, "-m", "sphinx", "-n", "-W", "--keep-going", "-q", "-b", "html",
         str(ROOT / "docs" / "api"), str(tmp_path / "html")],
        cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True,
        timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
