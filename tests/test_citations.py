"""Every .md or .py file that the README, docs, source, tests or benchmarks cite exists in the
repository: no citation points outside it."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CITED = re.compile(r"(?<![\w/.:-])((?:\.{1,2}/)?[\w.-]+(?:/[\w.-]+)*\.(?:md|py))\b")


def _sources():
    yield ROOT / "README.md"
    for folder, pattern in (("docs", "*.md"), ("src", "*.py"), ("tests", "*.py")):
        yield from (p for p in sorted((ROOT / folder).rglob(pattern)) if p != Path(__file__))
    yield from sorted((ROOT / "benchmarks").rglob("*.py"))
    yield from sorted((ROOT / "benchmarks").rglob("*.md"))


def _benchmark_output(cited: str) -> bool:
    """A results file that a benchmark script writes (it exists once the benchmark has run,
    which some need a GPU or outside data for)."""
    name = Path(cited).name
    if not name.endswith(".md") or (cited != name and not cited.startswith("benchmarks/")):
        return False
    scripts = (ROOT / "benchmarks").glob("*.py")
    return any(f'"{name}"' in p.read_text(encoding="utf-8") for p in scripts)


def _exists(cited: str, source: Path) -> bool:
    if _benchmark_output(cited):
        return True
    if "/" not in cited:  # a bare file name: somewhere in the repository
        return any(ROOT.rglob(cited))
    return (ROOT / cited).exists() or (source.parent / cited).resolve().exists()


def test_every_cited_file_exists():
    missing = []
    for source in _sources():
        text = source.read_text(encoding="utf-8")
        for match in CITED.finditer(text):
            cited = match.group(1)
            if not _exists(cited, source):
                line = text.count("\n", 0, match.start()) + 1
                missing.append(f"{source.relative_to(ROOT)}:{line}: {cited}")
    assert not missing, "cited files the repository lacks:\n" + "\n".join(missing)


def test_the_scan_sees_citations():
    # the pattern finds the kinds of citation the files use (so the test above can fail)
    text = "see `docs/method.md`, DESIGN.md and ../shared/x.py"
    found = [m.group(1) for m in CITED.finditer(text)]
    assert found == ["docs/method.md", "DESIGN.md", "../shared/x.py"]
    assert not _exists("DESIGN.md", ROOT / "README.md")
