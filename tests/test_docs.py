"""The README is a first page and docs/ a reading path: short, complete, linked, and present-tense.

These read the repository's own Markdown, so they fail when a page is added without a link from
docs/index.md, when a link breaks, or when the README outgrows a first page."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").glob("*.md"))
#: A first page, not a manual: trackpy's README is 1.2 kB, scikit-image's 2.7 kB.
README_LIMIT = 8_000
#: Characters in a row of the benchmark table.
BENCHMARK_ROW_LIMIT = 200
#: Markdown links and images, [text](target) and ![alt](target); the target up to a space or ")".
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
#: History has no place in pages that describe the present.
HISTORY = re.compile(r"\bissue\s*#?\d+|\bformer(ly)?\b", re.IGNORECASE)


def _relative_links(text: str) -> list[str]:
    """Link targets that point into the repository (no scheme, no bare anchor)."""
    targets = (m.group(1) for m in LINK.finditer(text))
    return [t for t in targets if not re.match(r"[a-z][a-z0-9+.-]*:|#", t, re.IGNORECASE)]


def _pages() -> list[Path]:
    return [README, *DOCS]


def test_readme_is_a_first_page():
    size = len(README.read_text(encoding="utf-8"))
    assert size <= README_LIMIT, f"README.md has {size} characters; the limit is {README_LIMIT}"


def test_every_docs_page_is_linked_from_the_index():
    index = ROOT / "docs" / "index.md"
    targets = _relative_links(index.read_text(encoding="utf-8"))
    linked = {(index.parent / t.split("#")[0]).resolve() for t in targets}
    missing = [p.name for p in DOCS if p != index and p.resolve() not in linked]
    assert not missing, f"docs/index.md does not link {missing}"


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_history_in_the_pages(page):
    text = page.read_text(encoding="utf-8")
    found = sorted({m.group(0) for m in HISTORY.finditer(text)})
    assert not found, f"{page.relative_to(ROOT)} speaks of history: {found}"


@pytest.mark.parametrize("page", _pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_to_a_file(page):
    text = page.read_text(encoding="utf-8")
    broken = [t for t in _relative_links(text) if not (page.parent / t.split("#")[0]).exists()]
    assert not broken, f"{page.relative_to(ROOT)} links to missing files: {broken}"


def test_readme_shows_the_demo_and_the_test_command_that_ci_runs():
    readme = README.read_text(encoding="utf-8")
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    command = "pip install '.[test]' && pytest"
    assert command in ci, ".ci/run no longer runs the README's test command"
    assert command in readme
    assert re.search(r"^\s*pip install \. && latentz demo\b", readme, re.MULTILINE)


def test_benchmark_table_rows_stay_short():
    # a row a reader can take in at once; details go in the notes under the table
    rows = (ROOT / "benchmarks" / "README.md").read_text(encoding="utf-8").splitlines()
    long = [row[:60] for row in rows if row.startswith("|") and len(row) > BENCHMARK_ROW_LIMIT]
    assert not long, f"benchmarks/README.md rows over {BENCHMARK_ROW_LIMIT} characters: {long}"


def test_the_checks_can_fail():
    # the patterns see what they guard against, so the tests above are not vacuous
    text = 'see [a](missing.txt), [b](https://x.org/y), [c](#top) and ![d](img/e.png "t")'
    assert _relative_links(text) == ["missing.txt", "img/e.png"]
    assert HISTORY.search("as issue 12 asks") and HISTORY.search("the Former model")
    assert not HISTORY.search("the formula of issues that remain")
