"""Every tutorial runs as written: the commands its page marks (`<!-- tutorial: … -->`, scripts/docsgen/tutorials.py)
run in order from the repository root, background programs included, and each must succeed."""

from __future__ import annotations

from pathlib import Path

import pytest

from scripts.docsgen.tutorials import run_page, steps

TUTORIALS = Path(__file__).resolve().parents[1] / "docs" / "tutorials"
PAGES = sorted(p for p in TUTORIALS.glob("*.md") if p.name != "index.md")
SLOW = {"servo-a-simulated-camera.md", "compare-the-laws.md"}  # each starts the simulator and the service


def test_there_are_three_tutorials_each_with_commands_to_run() -> None:
    assert len(PAGES) == 3, [p.name for p in PAGES]
    for page in PAGES:
        assert any(step.kind == "run" for step in steps(page)), f"{page.name} marks no command to run"


def test_a_malformed_marker_is_refused(tmp_path: Path) -> None:
    page = tmp_path / "bad.md"
    page.write_text("<!-- tutorial: background -->\n```bash\nsleep 1\n```\n")
    with pytest.raises(ValueError, match="needs a name"):
        steps(page)
    page.write_text("<!-- tutorial: run -->\nno block here\n")
    with pytest.raises(ValueError, match="fenced code block"):
        steps(page)


def test_a_failing_command_fails_the_page(tmp_path: Path) -> None:
    page = tmp_path / "failing.md"
    page.write_text("<!-- tutorial: background waiter -->\n```bash\nsleep 60\n```\n\n"
                    "<!-- tutorial: run -->\n```bash\ntrue\nfalse\necho never\n```\n")
    with pytest.raises(RuntimeError, match="exit status 1"):
        run_page(page, tmp_path / "logs")


@pytest.mark.parametrize("page", [
    pytest.param(p, id=p.stem, marks=[pytest.mark.slow] if p.name in SLOW else []) for p in PAGES
])
def test_tutorial_runs_as_written(page: Path, tmp_path: Path) -> None:
    run_page(page, tmp_path / "logs")
