"""The package's furniture agrees with itself: version, citation, changelog, licence, py.typed."""

import re
import sys
from pathlib import Path

import evdown_torch

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_the_version_is_semantic_and_cited_and_in_the_changelog():
    version = evdown_torch.__version__
    assert re.fullmatch(r"\d+\.\d+\.\d+", version), version
    citation = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert re.search(rf'^version: "{re.escape(version)}"$', citation, re.M)
    changelog = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    headings = re.findall(r"^## \[([^\]]+)\]", changelog, re.M)
    assert headings[0] == "Unreleased" and version in headings, headings
    assert "vMAJOR.MINOR.PATCH" in changelog


def test_the_citation_names_the_paper_and_its_four_authors():
    citation = (ROOT / "CITATION.cff").read_text(encoding="utf-8")
    assert "Event Data Downscaling for Embedded Computer Vision" in citation
    families = re.findall(r"family-names: (\S+)", citation)
    assert families == ["Gruel", "Martinet", "Serrano-Gotarredona", "Linares-Barranco"]


def test_the_licence_file_matches_pyproject_and_py_typed_ships():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert project["project"]["license"] in ({"text": "MIT"}, "MIT")
    assert (ROOT / "LICENSE").read_text(encoding="utf-8").startswith("MIT License")
    assert (Path(evdown_torch.__file__).parent / "py.typed").is_file()
    package_data = project["tool"]["setuptools"]["package-data"]["evdown_torch"]
    assert "py.typed" in package_data
