#!/usr/bin/env python3
"""Lint: febed's user-facing text states what is true now, without development history.

Usage:
    python tools/check_language.py [PATH ...]

With no PATH it scans, relative to the repository root (the parent of `tools/`): README.md, docs/, demos/,
febed/, tests/ and benchmarks/. A PATH may be a file or a folder. Folders are walked for text files ending in
.md, .py, .toml, .txt or .rst; folders named out, __pycache__, _build, site, .git and .venv are skipped.
Each hit is printed as `file:line: matched text  [rule]`; the exit status is 1 if there is any hit, else 0
(2 for a PATH that does not exist).

Rules applied to every line of every scanned file (case-insensitive but for the file names):
    - `session N`, `sessions N`          a development session ("measured in session 8")
    - `issue N`, `issue #N`              an issue-tracker number
    - `quiet machine`                    the conditions of one benchmark run
    - `the lead` (not `the lead-in`)     a person in the development process
    - `../shared/`, `DESIGN.md`,         documents outside the repository, which a clone does not contain
      `STYLE.md` (so `shared/DESIGN.md`)

One rule is applied to prose only: a lowercase `s` followed by one or two digits used as a tag (`s5`,
"rows marked s12"). Prose is, in .py files, the comments and the string literals with a space in them (not
the code nor one-word literals such as "s0", where `s0`, `s1` are ordinary names) and, in other files, every
line outside fenced code blocks; in both, inline code (text between backticks) and f-string fields (`{...}`
inside a string literal) are removed first. A tag must not follow a letter, digit, `_`, `.`, `/`, `^` or `-`
(so `s.s0`, `m/s2`, `x_s1` do not count) nor a number and a space (`3 s2`: a unit). Upper-case `S0`, `S1`
(symbols in formulas) do not count.
"""

from __future__ import annotations

import io
import re
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TARGETS = ("README.md", "docs", "demos", "febed", "tests", "benchmarks")
EXTENSIONS = {".md", ".py", ".toml", ".txt", ".rst"}
SKIP_DIRS = {"out", "__pycache__", "_build", "site", ".git", ".venv", ".pytest_cache", ".ruff_cache"}

LINE_RULES = [
    (re.compile(r"\bsessions? ?#?[0-9]+", re.IGNORECASE), "development session"),
    (re.compile(r"\bissues? ?#?[0-9]+", re.IGNORECASE), "issue number"),
    (re.compile(r"\bquiet machine\b", re.IGNORECASE), "run conditions"),
    (re.compile(r"\bthe lead\b(?!-)", re.IGNORECASE), "development role"),
    (re.compile(r"\.\./shared/"), "document outside the repository"),
    (re.compile(r"\b(?:DESIGN|STYLE)\.md\b"), "document outside the repository"),
]
TAG_RULE = (re.compile(r"(?<![\w./^\-])(?<![0-9] )s[0-9]{1,2}(?!\w)"), "session tag")

_CODE_SPAN = re.compile(r"(`+)(?:(?!\1).)+?\1")
_FIELD = re.compile(r"\{[^{}\n]*\}")
_FENCE = re.compile(r"^\s*(```|~~~)")


def _strip_code(text: str) -> str:
    """Blank inline code spans, keeping the columns."""
    return _CODE_SPAN.sub(lambda m: " " * len(m.group(0)), text)


def _python_prose(source: str) -> dict[int, str] | None:
    """Comments and string literals of a Python source, by line number; None if it does not tokenize."""
    prose: dict[int, list[str]] = {}
    try:
        tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    except (tokenize.TokenError, SyntaxError, IndentationError):
        return None
    for tok in tokens:
        if tok.type == tokenize.COMMENT:
            prose.setdefault(tok.start[0], []).append(tok.string)
        elif tok.type == tokenize.STRING:
            text = tok.string
            if not any(c.isspace() for c in text):
                continue  # a one-word literal ("s0", a key or a name) is code, not prose
            prefix = text[: len(text) - len(text.lstrip("rbuRBUfF"))]
            if "f" in prefix.lower():
                text = _FIELD.sub(" ", text)
            for k, line in enumerate(text.split("\n")):
                prose.setdefault(tok.start[0] + k, []).append(line)
    return {n: _strip_code(" ".join(parts)) for n, parts in prose.items()}


def _text_prose(lines: list[str]) -> dict[int, str]:
    """Lines of a text file outside fenced code blocks, inline code removed, by line number."""
    prose: dict[int, str] = {}
    fence = None
    for n, line in enumerate(lines, start=1):
        m = _FENCE.match(line)
        if m:
            fence = None if fence == m.group(1) else (fence or m.group(1))
            continue
        if fence is None:
            prose[n] = _strip_code(line)
    return prose


def check_file(path: Path) -> list[tuple[int, str, str]]:
    """Hits in one file as (line number, matched text, rule)."""
    try:
        source = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError):
        return []
    lines = source.splitlines()
    hits = []
    for n, line in enumerate(lines, start=1):
        for pattern, rule in LINE_RULES:
            hits.extend((n, m.group(0), rule) for m in pattern.finditer(line))
    prose = _python_prose(source) if path.suffix == ".py" else None
    if prose is None:
        prose = _text_prose(lines)
    pattern, rule = TAG_RULE
    for n, text in prose.items():
        hits.extend((n, m.group(0), rule) for m in pattern.finditer(text))
    return sorted(set(hits))


def iter_files(target: Path):
    """Text files under a target (itself if it is a file), sorted, skipping output and cache folders."""
    if target.is_file():
        yield target
        return
    for path in sorted(target.rglob("*")):
        rel = path.relative_to(target).parts
        if path.is_file() and path.suffix in EXTENSIONS and not any(p in SKIP_DIRS for p in rel[:-1]):
            yield path


def main(argv: list[str] | None = None) -> int:
    """Scan the given paths (or the default targets) and report; returns the exit status."""
    args = sys.argv[1:] if argv is None else argv
    if any(a in ("-h", "--help") for a in args):
        print(__doc__)
        return 0
    if args:
        targets = [Path(a) for a in args]
        missing = [str(t) for t in targets if not t.exists()]
        if missing:
            print(f"check_language: no such file or folder: {', '.join(missing)}", file=sys.stderr)
            return 2
    else:
        targets = [ROOT / t for t in DEFAULT_TARGETS if (ROOT / t).exists()]
    count = 0
    for target in targets:
        for path in iter_files(target):
            for n, text, rule in check_file(path):
                try:
                    shown = path.resolve().relative_to(Path.cwd())
                except ValueError:
                    shown = path
                print(f"{shown}:{n}: {text}  [{rule}]")
                count += 1
    if count:
        print(
            f"check_language: {count} line(s) of development-history language (see tools/check_language.py)",
            file=sys.stderr,
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
