"""Atomic persistence of the service state in a state directory.

Layout of `state_dir`:
- `reference.png`   the reference image (lossless; 8-bit grey or colour as received, 16-bit kept as 16-bit)
- `config.json`     the active service configuration
- `state.json`      servo state, ROI, registration warm start (G, photometric parameters) and the parallax estimate

Every write goes to a temporary file in the same directory, is flushed and fsync'ed, then renamed over the target
(`os.replace`, atomic on POSIX), and the directory is fsync'ed: a crash leaves either the old or the new file, never a
half-written one.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write `data` to `path` atomically (temporary file + fsync + rename + directory fsync)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


class StateStore:
    """Reads and writes the persisted state of one service instance."""

    def __init__(self, state_dir: str | os.PathLike[str]) -> None:
        self.dir = Path(state_dir)
        self.dir.mkdir(parents=True, exist_ok=True)

    @property
    def reference_path(self) -> Path:
        return self.dir / "reference.png"

    def save_reference(self, image: NDArray[Any]) -> None:
        ok, png = cv2.imencode(".png", np.ascontiguousarray(image))
        if not ok:
            raise OSError(f"could not encode the reference image ({image.shape}, {image.dtype}) as PNG")
        atomic_write_bytes(self.reference_path, png.tobytes())

    def load_reference(self) -> NDArray[Any] | None:
        if not self.reference_path.exists():
            return None
        image = cv2.imread(str(self.reference_path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise OSError(f"the persisted reference {self.reference_path} is not a readable PNG")
        return image

    def clear_reference(self) -> None:
        self.reference_path.unlink(missing_ok=True)

    def save_json(self, name: str, data: dict[str, Any]) -> None:
        atomic_write_bytes(self.dir / name, json.dumps(data, indent=2, sort_keys=True).encode())

    def load_json(self, name: str) -> dict[str, Any] | None:
        path = self.dir / name
        if not path.exists():
            return None
        return json.loads(path.read_text())
