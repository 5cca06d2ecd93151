"""Generators of the documentation site's reference pages (`make docs`; docs/guide/development.md).

Each module renders one part of the reference from the code itself — the CLI from its argparse parsers, the
configuration from its pydantic schema, the protocol from its key table and JSON schemas, the Python API from the
docstrings — as Markdown under `docs/reference/`. `python -m scripts.docsgen` writes them all; `make docs` (and so
`make test`) runs it before the strict build of the site.
"""
