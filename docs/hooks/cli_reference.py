"""mkdocs hooks: the command-line reference is generated from vvtbench's own parsers at build
time (``vvtbench COMMAND --help`` of every command and sub-command), so it cannot drift from
the code; Sphinx roles left in docstrings (``:func:`x```) render as plain code."""

from __future__ import annotations

import contextlib
import io
import re

MARKER = "<!-- cli-reference -->"
SUBCOMMANDS = re.compile(r"^usage: vvtbench [\w-]+ \[-h\] \{([\w,-]+)\}")
ROLES = r":(?:func|class|mod|meth|attr|data|exc|obj):"
SPHINX_ROLE = re.compile(ROLES + r"(?=<code>)")
SPHINX_ROLE_RAW = re.compile(ROLES + r"`~?([^`<]+)`")


def _help(*args: str) -> str:
    from vvtbench.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([*args, "--help"])
        except SystemExit:
            pass
    text = (out.getvalue() or err.getvalue()).rstrip()
    if not text:
        raise RuntimeError(f"vvtbench {' '.join(args)} --help printed nothing")
    return text


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    from vvtbench.cli import COMMANDS

    parts = []
    for command in COMMANDS:
        text = _help(command)
        parts.append(f"## `vvtbench {command}`\n\n```text\n{text}\n```\n")
        found = SUBCOMMANDS.match(text)
        for sub in found.group(1).split(",") if found else ():
            parts.append(f"### `vvtbench {command} {sub}`\n\n```text\n{_help(command, sub)}\n```\n")
    return markdown.replace(MARKER, "\n".join(parts))


def on_page_content(html: str, page, config, files) -> str:
    return SPHINX_ROLE_RAW.sub(r"\1", SPHINX_ROLE.sub("", html))
