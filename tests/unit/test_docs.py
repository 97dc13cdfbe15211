"""The documentation's own rules: README.md reads in minutes and leads to every page of docs/, and no relative
link in the documentation is broken (its file exists; a #anchor into a markdown file names one of its headings,
by GitHub's rule: lowercase, spaces to '-', punctuation other than '-' and '_' removed)."""
from __future__ import annotations

import re
from pathlib import Path

from tests.helpers import REPO

README_MAX_LINES = 200
SKIPPED_FOLDERS = {"out", "build", "node_modules", "__pycache__"}  # made by runs and builds, not documentation

FENCE = re.compile(r"^\s*(```|~~~)")
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
LINK = re.compile(r"\[[^\]]*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")  # inline links and images
SCHEME = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*:")  # http:, https:, mailto:: not ours to check
HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")


def documentation() -> list[Path]:
    """README.md, ARCHITECTURE.md, every page of docs/ and every folder's README.md."""
    folder_readmes = [p for p in REPO.rglob("README.md")
                      if not any(part.startswith(".") or part in SKIPPED_FOLDERS or part.endswith(".egg-info")
                                 for part in p.relative_to(REPO).parts[:-1])]
    return sorted({REPO / "README.md", REPO / "ARCHITECTURE.md", *(REPO / "docs").glob("*.md"), *folder_readmes})


def prose_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, line) outside fenced code blocks: a link or a heading in a code block is neither."""
    lines, fenced = [], False
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            lines.append((number, line))
    return lines


def unclosed_fence(path: Path) -> int | None:
    """The line of a code block's opening fence that is never closed (it hides the rest of the page), or None."""
    opened = None
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if FENCE.match(line):
            opened = None if opened else number
    return opened


def links(path: Path) -> list[tuple[int, str]]:
    """(line number, target) of every inline link and image, code spans left out."""
    return [(number, m.group(1)) for number, line in prose_lines(path)
            for m in LINK.finditer(CODE_SPAN.sub("", line))]


def anchor(heading: str) -> str:
    """GitHub's anchor of a heading: its text (link targets and code marks dropped) lowercased, punctuation other
    than '-' and '_' removed, each space a '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading's anchor; a repeated one gets -1, -2, … as on GitHub."""
    found, times_seen = set(), {}
    for _, line in prose_lines(path):
        if m := HEADING.match(line):
            base = anchor(m.group(2))
            found.add(f"{base}-{times_seen[base]}" if base in times_seen else base)
            times_seen[base] = times_seen.get(base, 0) + 1
    return found


def broken(path: Path, target: str) -> str | None:
    """Why a relative link does not resolve, or None when it does."""
    file_part, _, fragment = target.partition("#")
    resolved = (path.parent / file_part).resolve() if file_part else path
    if not resolved.exists():
        return "no such file"
    if fragment and resolved.suffix == ".md" and fragment not in anchors(resolved):
        return f"no heading #{fragment} in {resolved.relative_to(REPO)}"
    return None


def test_the_readme_reads_in_minutes():
    lines = len((REPO / "README.md").read_text().splitlines())
    assert lines <= README_MAX_LINES, (f"README.md has {lines} lines (at most {README_MAX_LINES}): move the detail "
                                       "into a page of docs/ and link it")


def test_every_docs_page_is_linked_from_the_readme():
    readme = REPO / "README.md"
    linked = {(REPO / target.partition("#")[0]).resolve() for _, target in links(readme)
              if not SCHEME.match(target) and target.partition("#")[0]}
    unlinked = [str(p.relative_to(REPO)) for p in sorted((REPO / "docs").glob("*.md")) if p.resolve() not in linked]
    assert unlinked == [], f"link these from README.md's list of pages: {unlinked}"


def test_every_code_block_is_closed():
    unclosed = [f"{p.relative_to(REPO)}:{line}" for p in documentation() if (line := unclosed_fence(p))]
    assert unclosed == [], f"close the code block opened at: {unclosed}"


def test_no_relative_link_is_broken():
    failures = [f"{path.relative_to(REPO)}:{number}: ({target}) {why}"
                for path in documentation() for number, target in links(path)
                if not SCHEME.match(target) and (why := broken(path, target))]
    assert failures == [], "broken links:\n" + "\n".join(failures)
