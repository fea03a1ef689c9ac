"""A newcomer's map (issue 66, point 5): the README links every page of docs/, every relative link in
the docs resolves inside the repository, no doc names a path outside it, benchmarks/README.md names
every benchmark script, and every module path docs/architecture.md names exists. Pure file reading."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
BENCHMARKS_README = ROOT / "benchmarks" / "README.md"
ARCHITECTURE = ROOT / "docs" / "architecture.md"

FENCE = re.compile(r"^(```|~~~).*?^\1", re.MULTILINE | re.DOTALL)
LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
# paths that leave the repository: the shared design notes beside it, the machine's work tree
OUTSIDE = ("../shared", "shared/DESIGN.md", "shared/PITFALLS.md", "shared/STYLE.md", "/work/")
# the package's folders, named relative to scenegen/ in the architecture table (retrieval/ lives
# under perception/)
FAMILY_ROOTS = {"retrieval": ROOT / "scenegen" / "perception"}


def _relative_links(path: Path) -> list[str]:
    """The relative link targets of a Markdown file, outside code blocks, without #anchors."""
    text = FENCE.sub("", path.read_text())
    targets = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # http(s), mailto and anchors within the page
        targets.append(target.split("#", 1)[0])
    return targets


def _inside(path: Path) -> bool:
    return path.resolve().is_relative_to(ROOT)


def test_the_readme_links_every_page_of_the_docs():
    linked = {(ROOT / target).resolve() for target in _relative_links(README)}
    assert DOCS, "no docs/*.md found"
    missing = [page.relative_to(ROOT).as_posix() for page in DOCS if page.resolve() not in linked]
    assert not missing, f"README.md links none of: {missing}"


@pytest.mark.parametrize(
    "doc", [README, *DOCS, BENCHMARKS_README], ids=lambda p: p.relative_to(ROOT).as_posix()
)
def test_every_relative_link_resolves_inside_the_repository(doc: Path):
    broken = []
    for target in _relative_links(doc):
        resolved = doc.parent / target
        if not resolved.exists() or not _inside(resolved):
            broken.append(target)
    assert not broken, f"{doc.relative_to(ROOT)}: links that do not resolve inside the repository: {broken}"


@pytest.mark.parametrize(
    "doc", [README, *DOCS, BENCHMARKS_README], ids=lambda p: p.relative_to(ROOT).as_posix()
)
def test_no_doc_names_a_path_outside_the_repository(doc: Path):
    text = doc.read_text()
    found = [needle for needle in OUTSIDE if needle in text]
    assert not found, f"{doc.relative_to(ROOT)} names paths outside the repository: {found}"


def test_benchmarks_readme_names_every_benchmark_script():
    text = BENCHMARKS_README.read_text()
    scripts = sorted((ROOT / "benchmarks").glob("*.py"))
    assert scripts, "no benchmarks/*.py found"
    missing = [s.name for s in scripts if not re.search(rf"(?<![\w.]){re.escape(s.name)}\b", text)]
    assert not missing, f"benchmarks/README.md does not name: {missing}"


def test_every_module_path_in_the_architecture_exists():
    text = ARCHITECTURE.read_text()
    named = set(re.findall(r"(?<![\w/.])((?:scenegen|benchmarks|tests)/[\w/.]*\w)", text))
    assert any(p.startswith("scenegen/") and p.endswith(".py") for p in named), "no module path found"
    missing = sorted(p for p in named if not (ROOT / p).exists())
    # family-relative module paths as the table writes them: `propose/repair.py`, `retrieval/frames.py`
    families = {d.name for d in (ROOT / "scenegen").iterdir() if d.is_dir()} | set(FAMILY_ROOTS)
    short = re.findall(rf"(?<![\w/.])((?:{'|'.join(sorted(families))})/[\w/]*\w\.py)\b", text)
    for path in sorted(set(short)):
        family = path.split("/", 1)[0]
        base = FAMILY_ROOTS.get(family, ROOT / "scenegen")
        if not (base / path).exists():
            missing.append(path)
    assert not missing, f"docs/architecture.md names modules that do not exist: {missing}"
