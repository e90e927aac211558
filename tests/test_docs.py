"""The README stays short, and the documentation's links, anchors, file paths and benchmark records exist.

Plain text checks (no fempdl import): README.md has at most 210 lines; every relative Markdown link
in README.md and docs/**/*.md points to an existing file (and, for a ``#fragment`` into a Markdown
page, to one of its headings, as GitHub slugs them); every ``bench-results/<name>.json`` the pages
name is committed; every source path they name (``fempdl/...py``, ``benchmarks/...``, ``tools/...``, ``examples/...``,
``tests/...py``) exists.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"
README_MAX_LINES = 210

LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
INLINE_CODE = re.compile(r"`+[^`]*`+")
HEADING = re.compile(r"^\s{0,3}(#{1,6})\s+(.*?)\s*#*\s*$")
BENCH_JSON = re.compile(r"bench-results/([\w.-]+\.json)")
SOURCE_PATH = re.compile(r"(?<![\w/.-])((?:fempdl|benchmarks|tools|examples|tests)/[\w./-]*\.(?:py|sh|toml))")


def pages() -> list[Path]:
    return [README, *sorted(DOCS.rglob("*.md"))]


def page_ids() -> list[str]:
    return [str(p.relative_to(ROOT)) for p in pages()]


def prose_lines(text: str) -> list[str]:
    """The lines outside fenced code blocks."""
    lines, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: link targets and code marks dropped, lower case, punctuation
    other than '-' and '_' removed, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).replace("`", "").strip().lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    out = set()
    for line in prose_lines(path.read_text(encoding="utf-8")):
        m = HEADING.match(line)
        if m:
            base = slug(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def links(path: Path) -> list[str]:
    found = []
    for line in prose_lines(path.read_text(encoding="utf-8")):
        found += LINK.findall(INLINE_CODE.sub("", line))
    return found


def test_the_readme_is_short():
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines; keep it at most {README_MAX_LINES}, move detail to docs/"


def test_the_readme_links_into_the_docs():
    targets = {(README.parent / t.split("#")[0]).resolve() for t in links(README) if not t.startswith("#")}
    assert (DOCS / "index.md").resolve() in targets, "README.md should link docs/index.md"


@pytest.mark.parametrize("page", pages(), ids=page_ids())
def test_relative_links_point_to_existing_files_and_headings(page):
    broken = []
    for target in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):        # http:, https:, mailto:
            continue
        file_part, _, fragment = target.partition("#")
        dest = (page.parent / file_part).resolve() if file_part else page
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
            broken.append(f"{target}: no heading #{fragment} in {dest.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


@pytest.mark.parametrize("page", pages(), ids=page_ids())
def test_named_benchmark_records_are_committed(page):
    named = set(BENCH_JSON.findall(page.read_text(encoding="utf-8")))
    missing = sorted(n for n in named if not (ROOT / "bench-results" / n).is_file())
    assert not missing, f"{page.relative_to(ROOT)} names bench-results/{missing} (not in bench-results/)"


@pytest.mark.parametrize("page", pages(), ids=page_ids())
def test_named_source_files_exist(page):
    named = set(SOURCE_PATH.findall(page.read_text(encoding="utf-8")))
    missing = sorted(p for p in named if not (ROOT / p).exists())
    assert not missing, f"{page.relative_to(ROOT)} names files that do not exist: {missing}"


def test_every_docs_page_is_reachable_from_the_readme():
    """Each docs page is linked from README.md or from another page, so nothing is left unfindable."""
    linked = set()
    for page in pages():
        for target in links(page):
            file_part = target.partition("#")[0]
            if file_part and not re.match(r"^[a-z][a-z0-9+.-]*:", file_part, re.I):
                linked.add((page.parent / file_part).resolve())
    orphans = [str(p.relative_to(ROOT)) for p in sorted(DOCS.rglob("*.md")) if p.resolve() not in linked]
    assert not orphans, f"docs pages no page links to: {orphans}"
