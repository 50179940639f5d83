"""The documentation stays true to the repository: README.md and docs/*.md link only to files
that exist, and docs/node.md names every parameter the node declares; the pages stay short
(README <= 13 KB, each page of docs/ <= 25 KB) and each page of docs/ opens with a working example."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

# [text](target) or [text](target "title"); an image ![alt](target) matches as well.
LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^ {0,3}(```|~~~)")
EXTERNAL = ("http://", "https://", "mailto:")


def markdown_links(text: str) -> list[tuple[int, str]]:
    """(line number, target) of every inline markdown link outside fenced code blocks and
    inline code spans."""
    links = []
    in_fence = False
    for number, line in enumerate(text.splitlines(), start=1):
        if FENCE.match(line):
            in_fence = not in_fence
            continue
        if in_fence:
            continue
        # drop inline code spans, e.g. `[a](b)` shown as code, keeping `[`x`](y)` links intact
        prose = re.sub(r"`[^`]*`", "code", line)
        links.extend((number, target) for target in LINK.findall(prose))
    return links


def broken_links(path: Path) -> list[str]:
    """One line per relative link of ``path`` whose target does not exist."""
    broken = []
    for number, target in markdown_links(path.read_text(encoding="utf-8")):
        if target.startswith(EXTERNAL) or target.startswith("#"):
            continue
        file_part = target.split("#", 1)[0]
        if not (path.parent / file_part).exists():
            broken.append(f"{path.relative_to(REPO)}:{number}: {target}")
    return broken


def test_the_pages_exist():
    names = {p.name for p in DOCS}
    assert {"README.md", "methods.md", "node.md", "replay.md", "diagnosis.md", "robustness.md",
            "benchmark.md"} <= names


def test_the_pages_are_short_and_open_with_an_example():
    """README.md <= 13 000 bytes, each page directly in docs/ <= 25 000 and a code block (its example)
    within its first 25 lines (the README opens with its quick-start table)."""
    sizes = {p.name: p.stat().st_size for p in DOCS}
    assert sizes["README.md"] <= 13_000, sizes
    assert all(size <= 25_000 for size in sizes.values()), sizes
    late = [p.name for p in DOCS[1:] if not any(FENCE.match(line) for line in p.read_text().splitlines()[:25])]
    assert not late, f"no example in the first 25 lines: {late}"


def test_link_extraction_sees_code_links_and_skips_code_blocks():
    text = "see [`a.py`](../a.py) and [b](b.md#x)\n```\n[c](c.md)\n```\n`[d](d.md)` [e](https://x.org)\n"
    assert [t for _, t in markdown_links(text)] == ["../a.py", "b.md#x", "https://x.org"]


def test_every_relative_link_resolves():
    broken = [line for path in DOCS for line in broken_links(path)]
    assert not broken, "broken links:\n" + "\n".join(broken)


def test_node_page_names_every_parameter():
    from hammer_ros.ros.node import PARAMETERS

    text = (REPO / "docs" / "node.md").read_text(encoding="utf-8")
    missing = [name for name in PARAMETERS if f"`{name}`" not in text]
    assert not missing, f"docs/node.md does not name the node parameters: {', '.join(missing)}"
