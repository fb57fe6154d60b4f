"""Every page link resolves, and every ``docs/...`` page the code, configs and tests name exists.

Pages move (``docs/design/`` holds the how-it-works pages): a link or a docstring left pointing at
the old place sends a reader nowhere, and nothing else would notice.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
# [text](target) with a relative target; the target may carry a #fragment
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
# docs/... pages named in prose, code and configs, relative to the repository's root
NAMED_PAGE = re.compile(r"\bdocs/[\w/.-]+\.md\b")
# where code, configs, scripts and tests name pages
NAMING = ("src", "test", "benchmarks", "config", "scripts")
SUFFIXES = {".py", ".md", ".yaml", ".yml", ".sh", ".xml", ".txt", ".cfg", ".toml"}


def slug(heading: str) -> str:
    """A heading's anchor as GitHub writes it: lower case, punctuation dropped, spaces as dashes."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    inside_code = False
    found = set()
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            inside_code = not inside_code
        elif not inside_code and line.startswith("#"):
            found.add(slug(line.lstrip("#")))
    return found


def relative_links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # code links nothing
    text = re.sub(r"`[^`\n]*`", "", text)
    return [target for target in LINK.findall(text) if not re.match(r"[a-z]+:", target)]


def test_slug_reads_headings_as_github_does():
    assert slug("Bias maps (`fusion/bias_map.py`, `deepsync survey-map`)") == \
        "bias-maps-fusionbias_mappy-deepsync-survey-map"
    assert slug("4. Nodes, topics, frames, parameters") == "4-nodes-topics-frames-parameters"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_every_relative_link_resolves(page):
    broken = []
    for target in relative_links(page):
        path, _, fragment = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists():
            broken.append(f"{target} (no {resolved.relative_to(REPO) if resolved.is_relative_to(REPO) else resolved})")
        elif fragment and resolved.suffix == ".md" and fragment not in anchors(resolved):
            broken.append(f"{target} (no heading #{fragment} in {resolved.relative_to(REPO)})")
    assert not broken, f"{page.relative_to(REPO)} links to what is not there: {broken}"


def test_every_named_docs_page_exists():
    files = [REPO / "README.md"] + [path for folder in NAMING for path in (REPO / folder).rglob("*")
                                    if path.suffix in SUFFIXES and path.is_file()]
    missing = sorted({f"{path.relative_to(REPO)}: {name}" for path in files
                      for name in NAMED_PAGE.findall(path.read_text(errors="replace"))
                      if not (REPO / name).is_file()})
    assert not missing, f"pages named that do not exist: {missing}"
