"""Read febed's docstrings as the plain text they are written in, before Napoleon and reStructuredText see them.

febed's docstrings are Google style (Args/Returns/... sections, read by `sphinx.ext.napoleon`) with plain-text
formulas and layouts: `|u - v|` for a norm, and indented blocks (formulas, file layouts, TOML examples,
command lines) after a line of prose. In reStructuredText `|x|` is a substitution and an indented block is a
block quote that must follow a blank line, so those docstrings would render wrongly or fail the build.
This hook, run before Napoleon, makes each indented block outside a Google section a literal block (shown
as written) and escapes `|` outside inline code. Lists (`* item`, `1. item`) and Google sections are left
to reStructuredText and Napoleon.
"""

from __future__ import annotations

import re

SECTION = re.compile(
    r"^(Args|Arguments|Parameters|Keyword Args|Keyword Arguments|Other Parameters|Returns?|Yields?|Raises|"
    r"Attributes|Examples?|Notes?|Warnings?|Warns|See Also|Todo|References|Methods):\s*$"
)
BULLET = re.compile(r"^([*+-]|\d+\.|#\.)\s+")
CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip(" "))


def _escape_bars(line: str) -> str:
    """Escape `|` outside inline code spans."""
    out, pos = [], 0
    for m in CODE_SPAN.finditer(line):
        out.append(line[pos : m.start()].replace("|", r"\|"))
        out.append(m.group(0))
        pos = m.end()
    out.append(line[pos:].replace("|", r"\|"))
    return "".join(out)


def plain_text_blocks(lines: list[str]) -> list[str]:
    """The docstring lines with indented blocks turned into literal blocks and `|` escaped."""
    out: list[str] = []
    context = 0  # indentation of the current paragraph or list item's text
    in_section = False
    in_list = False  # the last top-level line began a list item
    i = 0
    n = len(lines)
    while i < n:
        line = lines[i]
        if not line.strip():
            out.append(line)
            i += 1
            continue
        ind = _indent(line)
        if ind == 0:
            in_section = bool(SECTION.match(line))
            m = BULLET.match(line)
            if m and not in_section and out and out[-1].strip() and not in_list:
                out.append("")  # a list right below a paragraph line starts a list, not a continuation
            in_list = bool(m)
            context = m.end() if m else 0
            out.append(line if in_section else _escape_bars(line))
            i += 1
            continue
        if in_section:
            out.append(_escape_bars(line))
            i += 1
            continue
        if ind <= context:
            m = BULLET.match(line[ind:])
            context = ind + m.end() if m else ind
            out.append(_escape_bars(line))
            i += 1
            continue
        # An indented block below prose: every following line that is blank or indented deeper than `context`.
        j = i
        while j < n and (not lines[j].strip() or _indent(lines[j]) > context):
            j += 1
        while j > i and not lines[j - 1].strip():
            j -= 1
        pad = " " * context
        prose = [x for x in out if x.strip()]
        if not (prose and prose[-1].rstrip().endswith("::")):  # already a literal block in reST
            if out and out[-1].strip():
                out.append("")
            out.extend([pad + "::", ""])
        elif out and out[-1].strip():
            out.append("")
        out.extend(lines[i:j])
        out.append("")
        i = j
    return out


def process_docstring(app, what, name, obj, options, lines: list[str]) -> None:
    """`autodoc-process-docstring` handler: rewrite `lines` in place."""
    lines[:] = plain_text_blocks(lines)


def setup(app):
    """Connect before Napoleon (priority 500), which then reads the Google sections."""
    app.connect("autodoc-process-docstring", process_docstring, priority=400)
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}
