"""mkdocs hook: the command-line reference is generated from vvtbench's own parsers at build
time (``vvtbench COMMAND --help`` of every command), so it cannot drift from the code."""

from __future__ import annotations

import contextlib
import io

MARKER = "<!-- cli-reference -->"


def _help(command: str) -> str:
    from vvtbench.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([command, "--help"])
        except SystemExit:
            pass
    return (out.getvalue() or err.getvalue()).rstrip()


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    from vvtbench.cli import COMMANDS

    parts = []
    for command in COMMANDS:
        text = _help(command)
        if not text:
            raise RuntimeError(f"vvtbench {command} --help printed nothing")
        parts.append(f"## `vvtbench {command}`\n\n```text\n{text}\n```\n")
    return markdown.replace(MARKER, "\n".join(parts))
