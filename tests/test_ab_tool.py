"""tools/ab.py: a benchmark run at two commits in turn, and the ratio of the figures they print."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "ab.py"


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout.strip()


def commit_bench(repo: Path, value: float) -> str:
    (repo / "bench.py").write_text(f'print("DEM: {value} us per particle-step")\n')
    git(repo, "add", "bench.py")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", f"bench {value}")
    return git(repo, "rev-parse", "HEAD")


def ab(repo: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(TOOL), *args, "--cpu", "-1", "--", sys.executable, "bench.py"]
    return subprocess.run(cmd, cwd=repo, capture_output=True, text=True)


@pytest.fixture
def repo(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    git(repo, "init", "-q")
    return repo


def test_two_commits_give_the_ratio_of_their_figures_and_leave_no_worktree(repo):
    old = commit_bench(repo, 2.0)
    new = commit_bench(repo, 0.5)
    done = ab(repo, old, "--new", new, "--rounds", "2")
    assert done.returncode == 0, done.stderr
    assert "round 2: old 2  new 0.5  new/old 0.250" in done.stdout
    assert "new/old: 0.250 (per round 0.250, 0.250)" in done.stdout
    assert git(repo, "worktree", "list").count("\n") == 0  # only the repository's own tree is left


def test_the_working_tree_is_the_default_new_side(repo):
    old = commit_bench(repo, 2.0)
    (repo / "bench.py").write_text('print("DEM: 3.0 us per particle-step")\n')  # not committed
    done = ab(repo, old, "--rounds", "1")
    assert done.returncode == 0, done.stderr
    assert "new/old: 1.500" in done.stdout


def test_a_figure_missing_from_the_output_is_named(repo):
    old = commit_bench(repo, 2.0)
    done = ab(repo, old, "--rounds", "1", "--metric", r"GAS: ([0-9.]+) ms")
    assert done.returncode != 0
    assert "no match of --metric 'GAS: ([0-9.]+) ms'" in done.stderr
    done = ab(repo, "no-such-commit", "--rounds", "1")
    assert done.returncode != 0 and "ab: git worktree add" in done.stderr
