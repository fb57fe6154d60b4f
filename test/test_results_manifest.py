"""docs/results/ holds only what a named command writes and a page cites (docs/results/MANIFEST.yaml)."""

from __future__ import annotations

import fnmatch
import re
import shlex
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results"
MANIFEST = RESULTS / "MANIFEST.yaml"
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
# a file name a page may write: plain, with a * or with {a,b} alternatives
MENTION = re.compile(r"[\w./*{},<>-]*\.(?:json|png|csv|\{[\w,]+\})")


def entries() -> list[dict]:
    return yaml.safe_load(MANIFEST.read_text())


def results_files() -> list[str]:
    return sorted(p.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("*") if p.is_file() and p != MANIFEST)


def expand_braces(text: str) -> list[str]:
    """``a.{json,png}`` -> ``a.json``, ``a.png`` (nested and repeated groups too)."""
    match = re.search(r"\{([^{}]*)\}", text)
    if match is None:
        return [text]
    return [expanded for choice in match.group(1).split(",")
            for expanded in expand_braces(text[:match.start()] + choice + text[match.end():])]


def mentions(text: str) -> set[str]:
    """Every results path a page names, relative to docs/results/ when it names that folder."""
    found = set()
    for token in MENTION.findall(text):
        for path in expand_braces(token):
            found.add(path.split("results/", 1)[1] if "results/" in path else path)
    return found


def matches(patterns: list[str], name: str) -> bool:
    return any(fnmatch.fnmatchcase(name, p) and p.count("/") == name.count("/") for p in patterns)


def test_the_brace_and_glob_reading_of_a_page():
    assert mentions("`docs/results/fine_timing.{json,png}` and docs/results/route_set/*.json") == {
        "fine_timing.json", "fine_timing.png", "route_set/*.json"}
    assert not matches(["*.json"], "route_set/a.json")  # a * stays within its folder


def test_every_results_file_has_one_producer():
    writes = [pattern for entry in entries() for pattern in entry["writes"]]
    unlisted = [name for name in results_files() if not matches(writes, name)]
    twice = [name for name in results_files() if sum(matches([p], name) for p in writes) > 1]
    assert not unlisted, f"docs/results files no MANIFEST.yaml entry writes: {unlisted}"
    assert not twice, f"docs/results files two MANIFEST.yaml entries write: {twice}"
    stale = [p for p in writes if not any(matches([p], name) for name in results_files())]
    assert not stale, f"MANIFEST.yaml names files docs/results does not hold: {stale}"


@pytest.mark.parametrize("command", [entry["command"] for entry in entries()])
def test_every_producer_exists(command):
    words = shlex.split(command, comments=True)
    if words[0] == "python":
        assert (REPO / words[1]).is_file(), f"{command}: no script {words[1]}"
    else:
        assert words[0] == "deepsync", f"{command}: neither a script nor a deepsync command"
        cli = (REPO / "src" / "deepsync" / "deepsync" / "cli.py").read_text()
        assert f'add_parser("{words[1]}"' in cli, f"{command}: deepsync has no command {words[1]}"


def test_every_results_file_is_cited():
    cited = set().union(*(mentions(page.read_text()) for page in PAGES))
    uncited = [name for name in results_files() if not matches(sorted(cited), name)]
    assert not uncited, f"docs/results files no page of README.md or docs/**/*.md cites: {uncited}"
