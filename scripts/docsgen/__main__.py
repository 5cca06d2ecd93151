"""`python -m scripts.docsgen`: write every generated page and figure of the documentation site (`make docs`)."""

from __future__ import annotations

import sys
from pathlib import Path

from scripts.docsgen import api_reference, cli_reference, config_reference, protocol_reference, results_figures
from scripts.docsgen.markdown import ROOT

DOCS = ROOT / "docs"


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


def main() -> int:
    for path, text in generated_pages().items():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")
        print(f"wrote {path.relative_to(ROOT)}")
    for path in results_figures.draw():
        print(f"wrote {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
