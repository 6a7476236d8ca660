"""The README is the entry and ``docs/`` the manual (issue 40): every relative link in README.md and
docs/*.md points to a file that exists (and, for ``page.md#anchor``, to a heading of that page), the
README stays within 250 lines, and every page of ``docs/`` is linked from the README and links back."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = sorted((ROOT / "docs").glob("*.md"))
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def links(path: Path) -> list[str]:
    """The link targets of a Markdown file, fenced code left out."""
    return LINK.findall(FENCE.sub("", path.read_text()))


def anchors(path: Path) -> set[str]:
    """GitHub's anchors for the headings of a Markdown file: lower case, punctuation dropped, spaces
    as hyphens."""
    text = FENCE.sub("", path.read_text())
    heads = re.findall(r"^#+\s+(.*?)\s*$", text, re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in heads}


@pytest.mark.parametrize("path", [README, *PAGES], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_resolve(path):
    broken = []
    for target in links(path):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto:
            continue
        name, _, anchor = target.partition("#")
        dest = (path.parent / name).resolve() if name else path
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            broken.append(target)
    assert not broken, f"{path.name}: links to nothing: {broken}"


def test_readme_is_the_entry():
    assert len(README.read_text().splitlines()) <= 250
    linked = {(README.parent / t.partition("#")[0]).resolve() for t in links(README)}
    assert PAGES and not [p.name for p in PAGES if p.resolve() not in linked], "a docs page the README does not list"
    for page in PAGES:
        assert README.resolve() in {(page.parent / t.partition("#")[0]).resolve() for t in links(page)}, page.name
