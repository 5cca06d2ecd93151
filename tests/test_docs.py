"""The documentation: the generated references complete (every subcommand, setting with its default and range,
key and message), their figures drawn from the results tables, no commit hash, date, clock time or issue number
outside the results pages, a README that stays short and whose links resolve, and the configuration examples and
tables of the guide and the README true to the schema."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from ddvs.cli import SUBCOMMANDS
from ddvs_service.protocol.keys import TOPICS
from ddvs_service.protocol.schemas import SCHEMA_MODELS
from ddvs_service.service.config import ServiceConfig
from ddvs_service.service.fleet_config import read_file
from scripts.docsgen import cli_reference, protocol_reference
from scripts.docsgen.__main__ import generated_pages
from scripts.docsgen.api_reference import markdown_text
from scripts.docsgen.config_reference import default_value, rows
from scripts.docsgen.config_reference import render as render_configuration
from scripts.docsgen.markdown import ROOT
from scripts.docsgen.results_figures import draw, fleet_scaling, registration_speed

DOCS = ROOT / "docs"
README = ROOT / "README.md"

# What a reader outside the project cannot use: commit hashes (7–40 hex digits with a digit and a letter), dates,
# clock times and the project's own issue numbers.
FORBIDDEN = {
    "commit hash": re.compile(r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"),
    "date": re.compile(r"\b(19|20)\d\d-[01]\d-[0-3]\d\b"),
    "clock time": re.compile(r"\b([01]\d|2[0-3]):[0-5]\d(:[0-5]\d)?(\s*UTC)?\b(?![-–:\d])"),  # HH:MM, not m:ss
    "issue number": re.compile(r"\b[Ii]ssues? #?\d+|(?<![\w&])#\d+\b"),
}


def forbidden_mentions(text: str) -> list[str]:
    """`line: kind 'match'` for every forbidden mention in `text`."""
    return [f"{number}: {kind} {match.group(0)!r}"
            for number, line in enumerate(text.splitlines(), 1)
            for kind, pattern in FORBIDDEN.items()
            for match in pattern.finditer(line)]


def reader_pages() -> list[Path]:
    """README.md, benchmarks/README.md and every page of docs/ except the dated results pages."""
    pages = [README, ROOT / "benchmarks" / "README.md", *sorted(DOCS.rglob("*.md"))]
    return [p for p in pages if DOCS / "results" not in p.parents]


@pytest.mark.parametrize("text, kind", [
    ("before 3c6cf65 no service wrote it", "commit hash"),
    ("measured on 2026-12-03 at load 2", "date"),
    ("seven runs (22:56–23:25 UTC)", "clock time"),
    ("a restart at 14:54 took", "clock time"),
    ("since issue 20 the stop rule", "issue number"),
    ("its changelog, #605", "issue number"),
])
def test_forbidden_mentions_are_found(text: str, kind: str) -> None:
    assert [m for m in forbidden_mentions(text) if kind in m], f"{kind} not found in {text!r}"


@pytest.mark.parametrize("text", [
    "a 200×150 template at 30 Hz, 1e-3 threshold, ratio 1:2, elapsed 3:05",
    "`H[2,2] = 1`, λ = 0.4, rmw_zenoh_cpp ≥ 0.2.4, tcp/127.0.0.1:7447, abcdefab",
    "the decoupled error (16) over 2 cores, load average 1.5",
])
def test_ordinary_text_is_not_flagged(text: str) -> None:
    assert forbidden_mentions(text) == []


def test_no_commit_hash_date_or_issue_number_outside_the_results_pages() -> None:
    found = [f"{p.relative_to(ROOT)}:{m}" for p in reader_pages() for m in forbidden_mentions(p.read_text("utf-8"))]
    assert not found, "move these to a results page (docs/results/) or drop them:\n" + "\n".join(found)


def test_configuration_reference_lists_every_setting_with_its_default_and_range() -> None:
    page = render_configuration()
    table_rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([\w.]+)` \|.*$", page, re.MULTILINE)}
    for name, info, _ in rows(ServiceConfig):
        assert name in table_rows, f"configuration reference has no row for {name}"
        row = table_rows[name]
        default = default_value(info)
        if isinstance(default, (bool, int, float, str)) and not isinstance(default, ServiceConfig):
            assert f"`{json.dumps(default)}`" in row, f"{name}: default {default!r} missing from {row!r}"
        for meta in info.metadata:
            bound = next((getattr(meta, a) for a in ("gt", "ge", "lt", "le") if hasattr(meta, a)), None)
            if bound is not None:
                assert str(bound) in row, f"{name}: bound {bound} missing from {row!r}"


def test_every_generated_page_is_in_the_site_navigation() -> None:
    nav = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    missing = [str(p.relative_to(DOCS)) for p in generated_pages() if str(p.relative_to(DOCS)) not in nav]
    assert not missing, f"generated pages not in mkdocs.yml's nav: {missing}"


def test_readme_is_short_and_its_links_resolve() -> None:
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 250, "README.md is a front page: at most 250 lines, details go to docs/"
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    broken = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not broken, f"README.md links to missing files: {broken}"


def test_configuration_guide_examples_are_valid_configurations(tmp_path: Path) -> None:
    page = (DOCS / "guide" / "configuration.md").read_text(encoding="utf-8")
    examples = re.findall(r"```json\n(.*?)```", page, re.DOTALL)
    assert examples, "the configuration guide has no JSON example"
    for number, example in enumerate(examples):
        path = tmp_path / f"example{number}.json"
        path.write_text(example, encoding="utf-8")
        base, robots, _ = read_file(path)  # raises ValueError naming what is wrong
        base.check()
        if robots:
            for entry in robots:
                settings = {k: v for k, v in entry.items() if k != "robot"}
                base.merged(settings)


@pytest.mark.parametrize("page", [README, DOCS / "guide" / "configuration.md"], ids=["README", "guide"])
def test_configuration_tables_state_the_schemas_defaults(page: Path) -> None:
    """A hand-written table row `| `setting` | `default` | …` gives the schema's one default of that setting."""
    defaults = {name: default_value(info) for name, info, _ in rows(ServiceConfig)}
    checked = 0
    for name, cell in re.findall(r"^\| `([\w.]+)` \| `([^`|]+)` \|", page.read_text(encoding="utf-8"), re.MULTILINE):
        if name not in defaults:
            continue
        default = defaults[name]
        expected = list(default) if isinstance(default, tuple) else default
        try:
            stated = json.loads(cell)
        except json.JSONDecodeError:
            stated = cell  # a bare word: a string setting (`planar`)
        assert stated == expected, f"{page.name}: `{name}` default {cell}, the schema's is {default!r}"
        checked += 1
    assert checked >= 5, f"{page.name}: expected a configuration table"


def test_results_figures_are_drawn_from_the_results_tables(tmp_path: Path) -> None:
    speed = registration_speed()
    assert speed and all(0 < row["ours"] < row["ECC"] < row["numpy"] for row in speed.values()), speed
    fleet = fleet_scaling()
    assert [row["robots"] for row in fleet] == sorted(row["robots"] for row in fleet) and len(fleet) >= 2
    assert all(row["shared_rss_mb"] > 0 and row["separate_p99_ms"] >= row["separate_median_ms"] for row in fleet)
    written = draw(tmp_path)
    assert [p.name for p in written] == ["speed.png", "fleet.png"]
    assert all(p.read_bytes().startswith(b"\x89PNG") for p in written)


def test_cli_reference_documents_every_subcommand_and_option() -> None:
    page = cli_reference.render()
    for name in SUBCOMMANDS:
        assert f"## `ddvs {name}`" in page, f"no section for ddvs {name}"
    serve_options = ["--config", "--state-dir", "--fresh", "--no-warmup", "--warmup-only", "--connect"]
    assert all(f"`{option}" in page for option in serve_options)
    assert "%(" not in page, "help text not expanded as --help prints it"  # e.g. "(default %(default)s)"
    assert "(default 100: from identity" in page  # ddvs register --max-iterations, expanded


def test_protocol_reference_documents_every_key_and_message() -> None:
    page = protocol_reference.render()
    assert all(f"`{topic.suffix}`" in page for topic in TOPICS.values())
    assert all(f"(`schemas/{name}.json`)" in page for name in SCHEMA_MODELS)


def test_api_reference_keeps_angle_brackets_of_docstrings_visible() -> None:
    text = "keys <prefix>/<robot>, `<prefix>/x` and `a\nb <c>` d <e>\n    block <f>"
    assert markdown_text(text) == "keys &lt;prefix>/&lt;robot>, `<prefix>/x` and `a\nb <c>` d &lt;e>\n    block <f>"
