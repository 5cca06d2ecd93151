"""The optional full benchmark datasets (the Oxford affine sequences and the EF dataset), found through the
`DDVS_DATASETS` environment variable only: the folder that holds `oxford/` and `ef/` (layout in
docs/guide/installation.md). Nothing the README's commands run needs them; benchmarks and tests that do skip
without them."""

from __future__ import annotations

import os
from pathlib import Path

MISSING = ("needs the full datasets: set DDVS_DATASETS to the folder holding oxford/ and ef/ "
           "(docs/guide/installation.md, 'Optional datasets')")


def datasets_dir() -> Path | None:
    """The folder named by `DDVS_DATASETS`, or None when the variable is unset or empty.

    Raises NotADirectoryError when it is set to something that is not a folder (a typo should not read as "absent")."""
    value = os.environ.get("DDVS_DATASETS", "")
    if not value:
        return None
    path = Path(value)
    if not path.is_dir():
        raise NotADirectoryError(f"DDVS_DATASETS={value!r} is not a folder; expected the folder of oxford/ and ef/")
    return path


def require_datasets() -> Path:
    """The datasets folder, or SystemExit with the one line saying what is missing (for benchmark scripts)."""
    path = datasets_dir()
    if path is None:
        raise SystemExit(f"skipped: {MISSING}")
    return path
