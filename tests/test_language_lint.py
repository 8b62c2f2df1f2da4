"""tools/check_language.py: development-history language fails the lint, plain text and code pass.

The planted phrases are assembled from pieces so that this file itself passes the check.
"""

import subprocess
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "check_language.py"
S = "s"  # joined to digits below: a tag or a variable name
SESSION, ISSUE, QUIET, LEAD = "Sess" + "ion", "iss" + "ue", "quiet " + "machine", "the " + "lead"
SHARED, STYLE = "../" + "shared/", "STYLE" + ".md"


def check(*paths: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(TOOL), *map(str, paths)], capture_output=True, text=True, timeout=60)


CLEAN_PY = f'''"""Settling at 0.5 m/s takes 3 s; g = 9.81 m/s2 (docs/theory.md, drag)."""

{S}0 = {S}1 = 1.0  # slip components
fields = ("{S}0", "{S}1")
total = {S}0 + {S}1 * 2  # leading term; {LEAD}-in of the table
'''
CLEAN_MD = f"""# A page

Rows are per simulated second (3 {S}2 is a unit, not a tag). The leading edge of the bed.

```python
{S}0, {S}1 = 1.0, 2.0
```

Inline code `{S}5` is code, and so is ``{S}6``.
"""


@pytest.mark.parametrize(
    ("name", "text", "found"),
    [
        ("a.md", f"Measured in {SESSION} 8 on a laptop.\n", f"{SESSION} 8"),
        ("b.py", f"x = 1  # reproduced in {SESSION.lower()} 12\n", f"{SESSION.lower()} 12"),
        ("c.py", f'"""See {ISSUE} 5 for the check."""\n', f"{ISSUE} 5"),
        ("d.toml", f"# on a {QUIET}\nkey = 1\n", QUIET),
        ("e.rst", f"Wired by {LEAD}'s script.\n", LEAD),
        ("f.txt", f"See {SHARED} for the design notes.\n", SHARED),
        ("g.py", f'"""The readings ({STYLE} item 7)."""\n', STYLE),
        ("h.md", f"| same, {S}13 (alone) | 11.4 min |\n", f"{S}13"),
        ("i.py", f"# rows marked {S}5 were measured later\n", f"{S}5"),
        ("j.py", f'msg = "the {S}9 window"\n', f"{S}9"),
    ],
)
def test_planted_history_fails(tmp_path, name, text, found):
    (tmp_path / "ok.py").write_text(CLEAN_PY)
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / name).write_text(text)
    res = check(tmp_path)
    assert res.returncode == 1, res.stdout + res.stderr
    lines = res.stdout.splitlines()
    assert len(lines) == 1 and lines[0].startswith(str(tmp_path / "sub" / name) + ":1: " + found), lines


def test_clean_tree_passes(tmp_path):
    (tmp_path / "ok.py").write_text(CLEAN_PY)
    (tmp_path / "ok.md").write_text(CLEAN_MD)
    out = tmp_path / "out"  # output folders are not scanned
    out.mkdir()
    (out / "log.txt").write_text(f"{SESSION} 3\n")
    res = check(tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    assert res.stdout == ""


def test_missing_path_is_an_error(tmp_path):
    res = check(tmp_path / "nowhere")
    assert res.returncode == 2 and "nowhere" in res.stderr
