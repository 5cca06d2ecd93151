"""Records a servo run from Zenoh into a bag (`clients/bag.py`): every key of `clients.channels.run_channels`.

Zenoh callbacks only enqueue the raw payload with its arrival time; one writer thread validates (the protocol's
decoders: a malformed payload is counted as rejected, never written, so every recorded message decodes), writes,
and closes the open chunks every `BagWriter.flush_period_s`. Frames go through a bounded queue: when the disk or
the compression cannot keep up, frames beyond it are dropped and counted (`frames_dropped`); the small messages are
never dropped. `received` counts the samples that arrived per key, `writer.counts` those recorded per topic.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

from clients.channels import ChannelSpec, run_channels
from ddvs_service.protocol.keys import CAMERA_IMAGES

if TYPE_CHECKING:
    import zenoh

    from clients.bag import BagWriter
    from ddvs_service.protocol import Keys
    from ddvs_service.protocol.ros import Header

log = logging.getLogger(__name__)
FRAME_QUEUE = 64


class _Stamped(Protocol):
    """A decoded ROS message with a header (what `header_stamp_ns` reads)."""

    @property
    def header(self) -> Header: ...


def header_stamp_ns(key_name: str, payload: bytes) -> int:
    """Validate a CDR payload with the protocol's decoder of its key; returns its header stamp (ns)."""
    from ddvs_service.protocol import (
        decode_camera_info,
        decode_compressed_image,
        decode_image,
        decode_joint_state,
        decode_twist_stamped,
    )

    decoders: dict[str, Callable[[bytes], _Stamped]] = {
        "camera_image": decode_image, "camera_image_rect": decode_image, "servo_reference": decode_image,
        "servo_residual": decode_image, "camera_image_compressed": decode_compressed_image,
        "camera_image_rect_compressed": decode_compressed_image,
        "camera_info": decode_camera_info,
        "servo_twist": decode_twist_stamped, "arm_joint_states": decode_joint_state,
    }
    return decoders[key_name](payload).header.stamp.to_ns()


def check_json(key_name: str, payload: bytes) -> None:
    """Raise `ValueError` unless `payload` is a JSON object."""
    msg = json.loads(payload)
    if not isinstance(msg, dict):
        raise ValueError(f"{key_name} payload is a JSON {type(msg).__name__}; expected an object")


class BagRecorder:
    """Subscribes the run's keys on `session` and writes them with `writer` until `run`'s stop event is set.

    `frames`: `raw` (every camera row as published: Image and CompressedImage), `png`/`jpeg` (Image frames
    re-encoded as sensor_msgs/CompressedImage on their row's `/compressed`, compressed ones as published) or `none`;
    `frame_every`: keep every N-th camera frame of each row. `writer` must have the channels of
    `run_channels(keys, frames)`."""

    def __init__(self, session: zenoh.Session, keys: Keys, writer: BagWriter, frames: str = "raw",
                 frame_every: int = 1, jpeg_quality: int = 90) -> None:
        if frame_every < 1:
            raise ValueError(f"frame_every must be ≥ 1, got {frame_every}")
        self.writer = writer
        self.frames = frames
        self.frame_every = frame_every
        self.jpeg_quality = jpeg_quality
        self.rejected = 0
        self.frames_dropped = 0
        self.specs: dict[str, ChannelSpec] = {spec.key_name: spec for spec in run_channels(keys, frames)}
        rows = CAMERA_IMAGES if frames != "none" else ()
        self.received = dict.fromkeys((*rows, *(name for name in self.specs if name not in CAMERA_IMAGES)), 0)
        self._messages: queue.SimpleQueue[tuple[str, int, bytes]] = queue.SimpleQueue()
        self._frames: queue.Queue[tuple[str, int, bytes]] = queue.Queue(FRAME_QUEUE)
        self._subscribers = [session.declare_subscriber(keys.key(name), self._callback(name))
                             for name in self.received]

    def _callback(self, key_name: str):
        def on_sample(sample: zenoh.Sample) -> None:
            self.received[key_name] += 1
            if key_name not in CAMERA_IMAGES:
                self._messages.put((key_name, time.time_ns(), sample.payload.to_bytes()))
                return
            if (self.received[key_name] - 1) % self.frame_every:
                return
            try:
                self._frames.put_nowait((key_name, time.time_ns(), sample.payload.to_bytes()))
            except queue.Full:
                self.frames_dropped += 1

        return on_sample

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()

    def _write(self, key_name: str, recv_ns: int, payload: bytes) -> None:
        spec = self.specs[key_name]
        try:
            if spec.is_ros:
                stamp_ns = header_stamp_ns(key_name, payload)
            else:
                check_json(key_name, payload)
                stamp_ns = recv_ns
        except ValueError as exc:  # ProtocolError and JSONDecodeError are ValueErrors
            self.rejected += 1
            log.warning("not recording a %s sample: %s", key_name, exc)
            return
        self.writer.write(spec.topic, payload, recv_ns, stamp_ns)

    def _write_frame(self, key_name: str, recv_ns: int, payload: bytes) -> None:
        """A camera frame of row `key_name`: as published, or an Image re-encoded on its row's `/compressed`."""
        from clients.compressed_image import compress_image
        from ddvs_service.protocol import decode_image

        as_published = key_name in self.specs
        try:
            if as_published:
                data, stamp_ns = payload, header_stamp_ns(key_name, payload)
            else:
                image = decode_image(payload)
                data = compress_image(image, self.frames, self.jpeg_quality)
                stamp_ns = image.header.stamp.to_ns()
        except ValueError as exc:
            self.rejected += 1
            log.warning("not recording a frame: %s", exc)
            return
        self.writer.write(self.specs[key_name if as_published else f"{key_name}_compressed"].topic, data, recv_ns,
                          stamp_ns)

    def drain(self) -> int:
        """Write everything queued so far (closing the open chunks when due); returns the samples handled."""
        handled = _drain(self._messages, self._write)
        handled += _drain(self._frames, self._write_frame, self.writer.flush_if_due)
        self.writer.flush_if_due()
        return handled

    def run(self, stop: threading.Event, poll: float = 0.005) -> None:
        """Write samples as they arrive until `stop` is set, then write what is still queued."""
        while not stop.is_set():
            if not self.drain():
                stop.wait(poll)
        self.drain()


def _drain(source: queue.Queue | queue.SimpleQueue, write: Callable[..., None],
           after_each: Callable[[], object] | None = None) -> int:
    """Hand every queued item to `write` (then call `after_each`); returns how many there were."""
    handled = 0
    while True:
        try:
            item = source.get_nowait()
        except queue.Empty:
            return handled
        write(*item)
        handled += 1
        if after_each is not None:
            after_each()
