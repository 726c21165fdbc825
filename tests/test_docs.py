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
    api = (tmp_path / "site" / "reference" / "api" / "index.html").read_text()
    assert "InverseProblem" in api and "solve_sealed" in api
