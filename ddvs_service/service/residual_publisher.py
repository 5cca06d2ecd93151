"""The registration's residual image for people watching a servo (`servo/residual`), at a reduced rate and only
while someone subscribes.

`ResidualPublisher.offer(header, compute)` publishes `compute()` — the residual over the ROI, warped current −
reference after the photometric model (`registration.residual`), grey levels — as a `sensor_msgs/msg/Image` in
`32FC1` with the frame's header, when a subscriber matches the key (Zenoh matching status, kept up to date by a
matching listener: nobody watching costs one flag test per frame) and at most `rate_hz` times a second. Pixels whose
warped position left the current image are 0.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ddvs_service.protocol import Header, encode_image, image_from_array

DEFAULT_RATE_HZ = 5.0


class ResidualPublisher:
    """Publishes residual images on `publisher` (of the `servo_residual` row: a Zenoh publisher or an
    `endpoints.Publisher`; it stays the caller's to undeclare) at most `rate_hz`."""

    def __init__(self, publisher: Any, rate_hz: float = DEFAULT_RATE_HZ) -> None:
        if not rate_hz > 0:
            raise ValueError(f"residual rate {rate_hz} Hz: expected a rate > 0")
        self._publisher = publisher
        self._period = 1.0 / rate_hz
        self._last = -float("inf")
        self._watched = threading.Event()
        if publisher.matching_status.matching:
            self._watched.set()
        self._listener = publisher.declare_matching_listener(self._on_matching)

    def _on_matching(self, status: Any) -> None:
        if status.matching:
            self._watched.set()
        else:
            self._watched.clear()

    @property
    def watched(self) -> bool:
        """True while at least one subscriber matches the residual key."""
        return self._watched.is_set()

    def offer(self, header: Header, compute: Callable[[], NDArray[np.float32] | None]) -> bool:
        """Publish `compute()` when watched and due; True when an image was published."""
        if not self._watched.is_set():
            return False
        now = time.monotonic()
        if now - self._last < self._period:
            return False
        residual = compute()
        if residual is None:
            return False
        self._last = now
        pixels = np.nan_to_num(residual.astype(np.float32), nan=0.0)
        self._publisher.put(encode_image(image_from_array(pixels, "32FC1", header)))
        return True

    def close(self) -> None:
        """Stop following the matching status (the publisher is the caller's)."""
        self._listener.undeclare()
