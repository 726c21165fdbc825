"""The documentation site builds with `mkdocs build --strict` (a broken link, a missing page or
a docstring mkdocstrings cannot render fails it), and no page speaks of how the product was
built (sessions, issue numbers) instead of what it is."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HISTORY = re.compile(r"\b(sessions?)\b|\bissues? #?\d+|\b(first|second|third|fourth|fifth|"
                     r"sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|thirteenth|"
                     r"fourteenth|fifteenth|sixteenth|seventeenth|eighteenth|nineteenth|"
                     r"twentieth|twenty-\w+)[ -]session", re.IGNORECASE)
ALLOWED = re.compile(r"new[-_]session|start_new_session|test session")


def _pages() -> list[Path]:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    for extra in ("benchmarks/RESULTS.md", "CHANGELOG.md", "leaderboard/README.md"):
        if (ROOT / extra).is_file():
            pages.append(ROOT / extra)
    return pages


def test_the_history_check_can_fail():
    for text in ("in the twentieth session", "issue 17", "Sessions", "issue #3",
                 "the fifth-session figure"):
        assert HISTORY.search(text), text
    assert not HISTORY.search(ALLOWED.sub("", "bwrap --new-session"))


def history_lines(pages: list[Path], root: Path = ROOT) -> list[str]:
    """`file:line: text` of every line that speaks of how the product was built."""
    found = []
    for page in pages:
        for number, line in enumerate(page.read_text().splitlines(), 1):
            if HISTORY.search(ALLOWED.sub("", line)):
                found.append(f"{page.relative_to(root)}:{number}: {line.strip()}")
    return found


def test_no_page_speaks_of_how_the_product_was_built():
    found = history_lines(_pages())
    assert not found, "\n".join(found)


def test_the_history_check_lists_file_and_line(tmp_path):
    page = tmp_path / "docs" / "probe.md"
    page.parent.mkdir()
    page.write_text("fine\nmeasured in the ninth session\nbwrap --new-session\n")
    assert history_lines([page], tmp_path) == ["docs/probe.md:2: measured in the ninth session"]


LIST_ITEM = re.compile(r"^(?:[*+-]|\d+\.) ")


def glued_lists(pages: list[Path], root: Path = ROOT) -> list[str]:
    """`file:line: text` of every list that starts right under a paragraph line: the site's
    Markdown (unlike GitHub's) reads it as more of that paragraph, asterisks and all."""
    found = []
    for page in pages:
        previous, fenced = "", False
        for number, line in enumerate(page.read_text().splitlines(), 1):
            if line.lstrip().startswith("```"):
                fenced = not fenced
            elif (not fenced and LIST_ITEM.match(line) and previous.strip()
                  and not LIST_ITEM.match(previous) and not previous.startswith((" ", "|", "#",
                                                                                   ">"))):
                found.append(f"{page.relative_to(root)}:{number}: {line.strip()}")
            previous = "" if fenced else line
    return found


def test_every_list_on_the_site_is_set_apart_from_its_paragraph():
    found = glued_lists(sorted((ROOT / "docs").rglob("*.md")))
    assert not found, "\n".join(found)


def test_the_list_check_can_fail(tmp_path):
    page = tmp_path / "docs" / "probe.md"
    page.parent.mkdir()
    page.write_text("What it shows:\n* one\n* two\n\nApart:\n\n1. three\n  more\n"
                    "```\ncode:\n- not a list\n```\n")
    assert glued_lists([page], tmp_path) == ["docs/probe.md:2: * one"]


def test_the_results_columns_of_provenance_are_documented():
    text = (ROOT / "docs" / "results.md").read_text()
    for column in ("`estimate_sha256`", "`observation_sha256`", "`sandbox`"):
        assert column in text, column


@pytest.mark.skipif(not (ROOT / "mkdocs.yml").is_file(), reason="no site configuration")
def test_the_site_builds_strictly(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d",
                           str(tmp_path / "site")], cwd=ROOT, capture_output=True, text=True,
                          env=env, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    cli = (tmp_path / "site" / "reference" / "cli" / "index.html").read_text()
    from vvtbench.cli import COMMANDS

    for command in COMMANDS:
        assert f"vvtbench {command}" in cli, command
    for sub in ("build", "verify", "freeze"):
        assert f"vvtbench release {sub}" in cli, sub
    api = (tmp_path / "site" / "reference" / "api" / "index.html").read_text()
    assert "InverseProblem" in api and "solve_sealed" in api
    assert ":func:" not in api and ":class:" not in api
