"""`ddvs record`: record a servo run from Zenoh into a rosbag2 bag (MCAP storage; `clients/bag.py`,
docs/recording.md) with `clients.bag_recorder.BagRecorder`; `ddvs record --recover BAG` makes a killed recorder's
bag whole.

`Recorder` writes the older JSON Lines recording (`clients/recording.py`) that `orchestration/arm_run.py` still
uses: `servo/status` and `servo/state` (JSON, every sample), `servo/twist`, `arm/joint_states`, `arm/ground_truth`,
`camera/info` (only when it changes) and optionally every N-th camera image (PNG). Zenoh callbacks only enqueue the
raw payload with its arrival time; one writer thread decodes and writes (frames beyond a bounded queue are dropped
and counted; the small messages are never dropped).
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import threading
import time
from typing import TYPE_CHECKING, Any

from clients.recording import RECORDED_KEYS, decode_record

if TYPE_CHECKING:
    import zenoh

    from clients.recording import RecordingWriter
    from ddvs_service.protocol import Keys

log = logging.getLogger(__name__)
FRAME_QUEUE = 64
class Recorder:
    """Subscribes the recorded keys on `session` and writes them with `writer` until `run`'s stop event is set."""

    def __init__(self, session: zenoh.Session, keys: Keys, writer: RecordingWriter, frame_every: int = 0) -> None:
        if frame_every < 0:
            raise ValueError(f"frame_every must be ≥ 0 (0: no frames), got {frame_every}")
        self.writer = writer
        self.frame_every = frame_every
        self.rejected = 0
        self.frames_dropped = 0
        self._messages: queue.SimpleQueue[tuple[str, int, bytes]] = queue.SimpleQueue()
        self._frames: queue.Queue[tuple[int, bytes]] = queue.Queue(FRAME_QUEUE)
        self._frames_seen = 0
        self._last_info: tuple | None = None
        self._subscribers = [
            session.declare_subscriber(keys.key(key_name), self._enqueue(stream))
            for stream, key_name in RECORDED_KEYS.items()
        ]
        if frame_every:
            self._subscribers.append(session.declare_subscriber(keys.camera_image, self._enqueue_frame))

    def _enqueue(self, stream: str):
        def callback(sample: zenoh.Sample) -> None:
            self._messages.put((stream, time.time_ns(), sample.payload.to_bytes()))

        return callback

    def _enqueue_frame(self, sample: zenoh.Sample) -> None:
        self._frames_seen += 1
        if (self._frames_seen - 1) % self.frame_every:
            return
        try:
            self._frames.put_nowait((time.time_ns(), sample.payload.to_bytes()))
        except queue.Full:
            self.frames_dropped += 1

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()

    def _write_message(self, stream: str, recv_ns: int, payload: bytes) -> None:
        try:
            record = decode_record(stream, payload, recv_ns)
        except ValueError as exc:
            self.rejected += 1
            log.warning("not recording a %s sample: %s", stream, exc)
            return
        if stream == "camera_info":
            fingerprint = (record["width"], record["height"], tuple(record["k"]), tuple(record["d"]))
            if fingerprint == self._last_info:
                return
            self._last_info = fingerprint
        self.writer.write(stream, record)

    def _write_frame(self, recv_ns: int, payload: bytes) -> None:
        from ddvs_service.protocol import decode_image

        try:
            image = decode_image(payload)
        except ValueError as exc:
            self.rejected += 1
            log.warning("not recording a frame: %s", exc)
            return
        pixels = image.array
        if image.encoding in ("rgb8", "rgba8"):
            import cv2

            pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR if image.encoding == "rgb8" else cv2.COLOR_RGBA2BGRA)
        self.writer.write_frame(pixels, {"recv_ns": recv_ns, "stamp_ns": image.header.stamp.to_ns(),
                                         "encoding": image.encoding})

    def drain(self) -> int:
        """Write everything queued so far; returns the number of samples handled."""
        handled = 0
        while True:
            try:
                self._write_message(*self._messages.get_nowait())
            except queue.Empty:
                break
            handled += 1
        while True:
            try:
                self._write_frame(*self._frames.get_nowait())
            except queue.Empty:
                break
            handled += 1
        return handled

    def run(self, stop: threading.Event, poll: float = 0.01) -> None:
        """Write samples as they arrive until `stop` is set, then write what is still queued."""
        while not stop.is_set():
            if not self.drain():
                stop.wait(poll)
        self.drain()


def recording_meta(keys: Keys, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A recording's metadata (`meta.json`, or a bag's `ddvs` metadata record): the recorded key expressions, the
    start time, and `extra` (e.g. a reference pose)."""
    return {"prefix": keys.prefix, "robot": keys.robot, "started_ns": time.time_ns(),
            "keys": {stream: keys.key(name) for stream, name in {**RECORDED_KEYS, "frames": "camera_image"}.items()},
            **(extra or {})}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments

    parser.add_argument("out", help="new (or empty) bag directory; with --recover: the bag of a killed recorder")
    parser.add_argument("--recover", action="store_true",
                        help="make a killed recorder's bag readable: rewrite its files from their complete chunks "
                             "and write metadata.yaml, then print the messages kept per topic")
    parser.add_argument("--frames", choices=("raw", "png", "jpeg", "none"), default="raw",
                        help="camera frames as published (raw sensor_msgs/Image, default), re-encoded as "
                             "sensor_msgs/CompressedImage (png, jpeg), or not at all")
    parser.add_argument("--frame-every", type=int, default=1, help="keep every N-th camera frame (default 1)")
    parser.add_argument("--jpeg-quality", type=int, default=90, help="with --frames jpeg (default 90)")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                        help="MCAP chunk compression (default zstd)")
    parser.add_argument("--flush-period", type=float, default=0.5,
                        help="seconds between chunk closes, at most 1 (crash safety; default 0.5)")
    parser.add_argument("--duration", type=float, default=None, help="stop after this many seconds (default: Ctrl-C)")
    parser.add_argument("--meta", action="append", default=[], metavar="KEY=JSON",
                        help="extra metadata entry, e.g. reference_pose='[1,0,...]' (repeatable)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)


def _parse_meta(items: list[str]) -> dict[str, Any]:
    meta = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--meta {item!r}: expected KEY=JSON")
        try:
            meta[key] = json.loads(text)
        except json.JSONDecodeError:
            meta[key] = text
    return meta


def run(args: argparse.Namespace) -> int:
    import signal

    from clients.bag import BagWriter, recover_bag
    from clients.bag_recorder import BagRecorder
    from clients.channels import run_channels
    from ddvs_service.logs import setup_logging
    from ddvs_service.protocol import Keys, open_session, session_config_from_args

    setup_logging("INFO")
    if args.recover:
        print(json.dumps(recover_bag(args.out, args.compression), indent=2))
        return 0
    keys = Keys(args.prefix, args.robot)
    writer = BagWriter(args.out, run_channels(keys, args.frames), recording_meta(keys, _parse_meta(args.meta)),
                       compression=args.compression, flush_period_s=args.flush_period)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    if args.duration is not None:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    with open_session(session_config_from_args(args)) as session:
        recorder = BagRecorder(session, keys, writer, args.frames, args.frame_every, args.jpeg_quality)
        try:
            recorder.run(stop)
        finally:
            recorder.close()
            recorder.drain()
            writer.close()
    log.info("recorded %s into %s (received %s, rejected %d, frames dropped %d)", writer.counts, args.out,
             recorder.received, recorder.rejected, recorder.frames_dropped)
    return 0
