"""Code, tests and tools cite the repository's docs/, not the old design contract outside it
(issue 14, item 6): every cited page exists, and every cited section is a heading of that page."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SOURCES = [
    *sorted((ROOT / "leafgate").rglob("*.py")),
    *sorted((ROOT / "leafgate").rglob("*.yaml")),
    *sorted((ROOT / "tests").rglob("*.py")),
    *sorted((ROOT / "tools").glob("*.py")),
    ROOT / "README.md",
]
CITATION = re.compile(r'docs/([a-z-]+\.md)(?:#([a-z0-9-]+)|, "([^"]+)")?')
OLD_CONTRACT = re.compile(r"\bDESIGN(?:\.md)?\b(?!_)")  # DESIGN_FRAMES is a name, not a citation


def _anchor(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^a-z0-9 -]", "", heading.lower()).replace(" ", "-")


def _headings(page: str) -> set[str]:
    lines = (DOCS / page).read_text(encoding="utf-8").splitlines()
    return {line.lstrip("#").strip() for line in lines if line.startswith("#")}


def test_nothing_cites_the_old_design_contract() -> None:
    found = [
        f"{path.relative_to(ROOT)}:{n}: {line.strip()}"
        for path in SOURCES
        if path.name != Path(__file__).name
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if OLD_CONTRACT.search(line)
    ]
    assert not found, "\n".join(found)


def test_every_cited_page_and_section_exists() -> None:
    missing = []
    for path in SOURCES:
        for match in CITATION.finditer(path.read_text(encoding="utf-8")):
            page, anchor, section = match.groups()
            where = f"{path.relative_to(ROOT)}: {match.group(0)}"
            if not (DOCS / page).is_file():
                missing.append(where)
                continue
            headings = _headings(page)
            if anchor is not None and anchor not in {_anchor(h) for h in headings}:
                missing.append(where)
            if section is not None and section not in headings:
                missing.append(where)
    assert not missing, "\n".join(missing)
