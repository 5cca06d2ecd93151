"""Where the shared image datasets are (`../shared/datasets` beside the repository; see its README).

Lookup order: the `DDVS_DATASETS` environment variable, then `shared/datasets` next to the repository checkout,
then `/work/shared/datasets`. Used for default textures of the simulated targets, by tests and by benchmarks.
"""

from __future__ import annotations

import os
from pathlib import Path

_REPO = Path(__file__).resolve().parents[1]
_CANDIDATES = (_REPO.parent / "shared" / "datasets", Path("/work/shared/datasets"))


def datasets_dir() -> Path:
    """The datasets folder; raises FileNotFoundError naming every place looked at when none exists."""
    env = os.environ.get("DDVS_DATASETS")
    candidates = ((Path(env),) if env else ()) + _CANDIDATES
    for path in candidates:
        if path.is_dir():
            return path
    raise FileNotFoundError(
        f"no datasets folder: looked at {', '.join(map(str, candidates))}; set DDVS_DATASETS to the folder that holds "
        "oxford/ and ef/"
    )


def dataset_image(relative: str) -> Path:
    """Path of an image of the datasets folder, e.g. `dataset_image("oxford/boat/img1.png")` (must exist)."""
    path = datasets_dir() / relative
    if not path.is_file():
        raise FileNotFoundError(f"dataset image {path} is missing; expected a file there (see the datasets README)")
    return path
