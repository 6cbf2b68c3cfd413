"""The documentation's promises: links that lead somewhere, a layout that matches the package,
and text for users (no dates outside CHANGELOG.md, no work diary)."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "CHANGELOG.md",
        *sorted((ROOT / "docs").rglob("*.md"))]


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to -."""
    text = re.sub(r"[`*]", "", heading.strip()).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return {_slug(h) for h in re.findall(r"^#+ (.*)$", text, re.M)}


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_link_leads_somewhere(doc: Path) -> None:
    """Every relative link of the page names a file of the repository, and its #anchor a
    heading of that file."""
    text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
    bad = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        if not path.exists():
            bad.append(f"{target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in _anchors(path):
            bad.append(f"{target}: no heading with that anchor")
    assert not bad, f"{doc.relative_to(ROOT)}: " + "; ".join(bad)


def test_layout_tree_matches_the_package() -> None:
    """docs/development.md's tree names every package and top-level module of mkf_ros (and
    every module of core/ and stream/, where the design lives), and nothing that is not there."""
    text = (ROOT / "docs" / "development.md").read_text()
    block = re.search(r"## Layout\n+```\n(.*?)```", text, re.S)
    assert block, "docs/development.md has no layout tree under ## Layout"
    tree = block.group(1)
    pkg = ROOT / "mkf_ros"
    named = set(re.findall(r"mkf_ros/([\w.]+)", tree))
    for name in named - {"_kernels"}:  # _kernels: made by the install / ./run setup
        assert (pkg / name).exists(), f"the layout names mkf_ros/{name}, which does not exist"
    top = {p.name for p in pkg.iterdir()
           if (p.suffix == ".py" and p.name != "__init__.py")
           or (p.is_dir() and (p / "__init__.py").exists())}
    assert top <= named, f"the layout misses {sorted(top - named)}"
    words = set(re.findall(r"[\w]+\.py", tree))
    for sub in ("core", "stream"):
        mods = {p.name for p in (pkg / sub).glob("*.py") if p.name != "__init__.py"}
        assert mods <= words, f"the layout misses mkf_ros/{sub}/{sorted(mods - words)}"


#: A calendar date (2026-11-27, 2026-11); ISO timestamps with a time (2024-01-01T00:00:00Z, a
#: default of the synthetic bags) are data, not dates of work.
DATE = re.compile(r"\b(19|20)\d\d-[01]\d(-[0-3]\d)?\b(?![-T\d])")
#: Numbered or referred-to work sessions; "session" in its technical senses (a pytest fixture
#: scope, a POSIX session) is not this.
DIARY = re.compile(r"\b(session \d+|this session|previous session|work session)", re.I)


def test_no_dates_or_work_diary_outside_the_changelog() -> None:
    """Docs and code state the current figure and the command that reproduces it; the history
    (dates, who did what when) is CHANGELOG.md's, and work sessions are no one's."""
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True,
                           check=True).stdout.split()
    bad = []
    for name in files:
        if name == "test/test_docs.py":  # (the patterns themselves)
            continue
        path = ROOT / name
        if path.suffix not in (".py", ".md", ".txt", ".yaml", ".toml", ".cfg", ".ini", ".xml",
                               "") or not path.is_file():
            continue
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if DIARY.search(line) or (name != "CHANGELOG.md" and DATE.search(line)):
                bad.append(f"{name}:{i}: {line.strip()[:80]}")
    assert not bad, "\n".join(bad[:30]) + (f"\n… {len(bad)} in all" if len(bad) > 30 else "")
