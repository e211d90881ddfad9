"""The front page stays a front page: at most 120 lines, the two set-up commands within its first 30,
and every file it links to present (the rest of what it used to hold lives in docs/GUIDE.md)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEMO = "python3 -m venv .venv && .venv/bin/pip install -q -e . && .venv/bin/crowd-demo"
TESTS = "python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && .venv/bin/python -m pytest -q"


def test_the_readme_is_short_and_starts_with_how_to_run_it():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 120, len(lines)
    head = [line.strip() for line in lines[:30]]
    assert DEMO in head and TESTS in head


def test_every_file_the_readme_and_the_guide_link_to_exists():
    for page in (ROOT / "README.md", ROOT / "docs" / "GUIDE.md"):
        for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", page.read_text()):
            if "://" not in target:
                assert (page.parent / target).exists(), (page.name, target)


def test_the_ci_runs_the_readme_test_command():
    assert TESTS in (ROOT / ".ci" / "run").read_text()
