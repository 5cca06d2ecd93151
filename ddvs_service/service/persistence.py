"""Atomic persistence of the service state in a state directory.

Layout of `state_dir`:
- `reference.png`   the reference image (lossless; 8-bit grey or colour as received, 16-bit kept as 16-bit)
- `config.json`     the active service configuration (written at start and on every accepted change; for readers)
- `state.json`      servo state, ROI, reference stamp, the parallax estimate, the camera intrinsics last received,
                    the configuration changes made at run time (what a restart applies again) and the last good
                    estimate `G` (where a restart re-acquires from first)

Every write goes to a temporary file in the same directory, is flushed and fsync'ed, then renamed over the target
(`os.replace`, atomic on POSIX), and the directory is fsync'ed: a crash leaves either the old or the new file, never a
half-written one.

`BackgroundWriter` does those writes on its own thread, so an fsync (tens to hundreds of ms on a busy disk) never
delays a frame or a command reply. Writes are applied in the order they were asked for, except that a newer write
of a file replaces an older one still waiting (the older is skipped; the newer goes to the end of the queue). A
crash (kill -9) loses at most the writes still waiting; every file on disk is a whole old or whole new version.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
import threading
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ddvs_service.logs import fields

log = logging.getLogger("ddvs.persistence")


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


class BackgroundWriter:
    """Writes a `StateStore`'s files on one worker thread; the caller never waits for the disk.

    `put_json`, `put_reference` and `remove_reference` return at once; `flush()` waits until everything asked for so
    far is on disk (or failed: failures are logged, the service keeps running); `close()` flushes and stops the
    thread.
    """

    def __init__(self, store: StateStore) -> None:
        self.store = store
        self._cond = threading.Condition()
        self._pending: OrderedDict[str, Callable[[], None]] = OrderedDict()
        self._busy = False
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="ddvs-persistence", daemon=True)
        self._thread.start()

    def put_json(self, name: str, data: dict[str, Any]) -> None:
        self._submit(name, lambda: self.store.save_json(name, data))

    def put_reference(self, image: NDArray[Any]) -> None:
        """Queue the reference image; `image` must not change afterwards (pass a copy or an immutable view)."""
        self._submit(self.store.reference_path.name, lambda: self.store.save_reference(image))

    def remove_reference(self) -> None:
        self._submit(self.store.reference_path.name, self.store.clear_reference)

    def flush(self, timeout_s: float | None = None) -> bool:
        """Wait until every queued write is done; False if `timeout_s` passed first."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._pending and not self._busy, timeout_s)

    def close(self, timeout_s: float | None = None) -> None:
        """Flush, then stop the worker thread."""
        self.flush(timeout_s)
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self._thread.join(timeout_s)

    def _submit(self, name: str, write: Callable[[], None]) -> None:
        with self._cond:
            self._pending.pop(name, None)
            self._pending[name] = write
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending or self._closing)
                if not self._pending:
                    return
                name, write = self._pending.popitem(last=False)
                self._busy = True
            try:
                write()
            except Exception as exc:
                log.error("could not persist a state file", extra=fields(file=name, dir=str(self.store.dir),
                                                                         error=str(exc)))
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
