"""`python -m scripts.docsgen [--check]`: write every generated page of the documentation site (`make docs`).

With `--check`, write nothing and exit 1 naming each page that differs from what the code gives now.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from scripts.docsgen import api_reference, cli_reference, config_reference, protocol_reference

DOCS = Path(__file__).resolve().parents[2] / "docs"


def generated_pages(docs: Path = DOCS) -> dict[Path, str]:
    """Every generated page: path under `docs` → its text."""
    pages = {
        docs / "reference" / "cli.md": cli_reference.render(),
        docs / "reference" / "configuration.md": config_reference.render(),
        docs / "reference" / "protocol.md": protocol_reference.render(),
    }
    for name, modules in api_reference.pages().items():
        pages[docs / "reference" / "api" / f"{name}.md"] = api_reference.render(name, modules)
    return pages


def stale_pages(docs: Path = DOCS) -> list[Path]:
    """The generated pages whose committed text differs from what the code gives now (missing ones included)."""
    return [p for p, text in generated_pages(docs).items() if not p.exists() or p.read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m scripts.docsgen", description=__doc__)
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 if a page is out of date")
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_pages()
        for path in stale:
            print(f"out of date: {path.relative_to(DOCS.parent)} (run `make docs`)", file=sys.stderr)
        return 1 if stale else 0
    for path, text in generated_pages().items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path.relative_to(DOCS.parent)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
