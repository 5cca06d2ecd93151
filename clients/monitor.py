"""`ddvs monitor`: live terminal view of one servo (plain ANSI redraw), one JSON snapshot with `--once`, or a live
Foxglove view with `--foxglove` (`clients/foxglove_live.py`).

Shown: the servo state (from `servo/status`, or `servo/state` before any status), the control error vector ε̄ and its
norm (eq. 16, or 13 for DVS), the twist (m/s, rad/s, camera frame), arrival rates over the last `--window` seconds
of camera frames, twists and status messages (Hz) and, from the status counters, of frames the service rejected and
frames superseded before the loop took them (a flood: frames/s), the service's per-frame latency breakdown (ms) and
counters, and
the secured router's audit of this robot (`<prefix>/<robot>/router/audit`, docs/security.md): messages denied per
identity, sessions without a role, refused TLS and user/password handshakes.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import zenoh

    from ddvs_service.protocol import Keys

RATE_STREAMS = ("frames", "twists", "status")
"""The rates shown: camera frames (on any camera row: raw, rectified, compressed), twists, status messages."""
COUNTER_RATES = ("rejected", "dropped")
"""Status counters shown as rates (frames/s over the window): a flood of bad frames, or of frames faster than the
loop."""
CLEAR = "\x1b[H\x1b[2J"


class Monitor:
    """Collects the newest status and state and the arrival times of frames, twists and status (Zenoh callbacks
    only store; `snapshot` computes)."""

    def __init__(self, session: zenoh.Session, keys: Keys, window: float = 2.0) -> None:
        if window <= 0:
            raise ValueError(f"window must be > 0 seconds, got {window}")
        self.window = window
        self._lock = threading.Lock()
        self._arrivals: dict[str, collections.deque[float]] = {name: collections.deque() for name in RATE_STREAMS}
        self._status: dict[str, Any] | None = None
        self._counts: collections.deque[tuple[float, dict[str, int]]] = collections.deque()  # (arrival, counters)
        self._latest: dict[str, dict[str, Any] | None] = {"state": None, "audit": None}  # newest JSON message
        self.status_received = threading.Event()
        from ddvs_service.protocol.keys import CAMERA_IMAGES

        rows = {"frames": CAMERA_IMAGES, "twists": ("servo_twist",), "status": ("servo_status",)}
        self._subscribers = [session.declare_subscriber(keys.key(row), self._on_arrival(name))
                             for name in RATE_STREAMS for row in rows[name]]
        self._subscribers.append(session.declare_subscriber(keys.servo_state, self._on_json("state")))
        from ddvs_service.protocol.audit import audit_key

        self._subscribers.append(session.declare_subscriber(audit_key(keys.base), self._on_json("audit")))

    def _on_arrival(self, name: str):
        def callback(sample: zenoh.Sample) -> None:
            now = time.monotonic()
            payload = sample.payload.to_bytes() if name == "status" else None
            with self._lock:
                self._arrivals[name].append(now)
                if payload is not None:
                    try:
                        self._status = json.loads(payload)
                    except ValueError:
                        return
                    counters = self._status.get("counters") if isinstance(self._status, dict) else None
                    if isinstance(counters, dict):
                        self._counts.append((now, counters))
            if payload is not None:
                self.status_received.set()

        return callback

    def _on_json(self, name: str):
        def callback(sample: zenoh.Sample) -> None:
            try:
                message = json.loads(sample.payload.to_bytes())
            except ValueError:
                return
            with self._lock:
                self._latest[name] = message

        return callback

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()

    def _counter_rates(self, now: float) -> dict[str, float]:
        """Growth of the `COUNTER_RATES` counters over the window (frames/s), from the first and the newest status in
        it (the newest status before the window included: rejections are reported about once a second)."""
        counts = self._counts
        while len(counts) > 1 and counts[1][0] < now - self.window:
            counts.popleft()
        if len(counts) < 2 or counts[-1][0] <= counts[0][0]:
            return dict.fromkeys(COUNTER_RATES, 0.0)
        (t0, first), (t1, last) = counts[0], counts[-1]
        return {name: round(max(int(last.get(name, 0)) - int(first.get(name, 0)), 0) / (t1 - t0), 2)
                for name in COUNTER_RATES}

    def snapshot(self) -> dict[str, Any]:
        """JSON-ready view: state, status `seq`, error, twist, rates (Hz over the window), latency (ms), counters,
        message, the Taichi backend of the service's kernels (`backend`), and the router's audit summary (`audit`;
        None without a secured router)."""
        now = time.monotonic()
        with self._lock:
            rates = {}
            for name, arrivals in self._arrivals.items():
                while arrivals and arrivals[0] < now - self.window:
                    arrivals.popleft()
                rates[name] = round(len(arrivals) / self.window, 2)
            rates.update(self._counter_rates(now))
            status, state, audit = self._status, self._latest["state"], self._latest["audit"]
        snap: dict[str, Any] = {"state": None, "seq": None, "has_reference": None, "error_norm": None, "error": None,
                                "twist": None, "rates_hz": rates, "latency_ms": None, "counters": None,
                                "message": "", "audit": audit, "backend": None}
        if state is not None:
            snap.update(state=state.get("state"), has_reference=state.get("has_reference"),
                        message=state.get("message", ""))
        if status is not None:
            snap.update(state=status.get("state"), seq=status.get("seq"), error_norm=status.get("error_norm"),
                        error=status.get("error"),
                        twist=status.get("twist"), latency_ms=status.get("latency_ms"),
                        counters=status.get("counters"), message=status.get("message") or snap["message"],
                        backend=status.get("backend") or None)
        return snap


def _vector(values: list[float] | None, digits: int = 5) -> str:
    return "—" if values is None else "[" + ", ".join(f"{v:+.{digits}f}" for v in values) + "]"


def _audit_line(audit: dict[str, Any] | None) -> str:
    if audit is None:
        return "— (no audit from a secured router)"

    def counts(values: dict[str, int]) -> str:
        return ", ".join(f"{who} {n}" for who, n in sorted(values.items())) or "none"

    return (f"denied {counts(audit.get('denied', {}))}   without a role {counts(audit.get('no_role', {}))}   "
            f"TLS refused {audit.get('tls_refused', 0)}   password refused {audit.get('auth_refused', 0)}")


def render(snap: dict[str, Any], title: str) -> str:
    """The terminal view of a `Monitor.snapshot` (plain text lines)."""
    rates = snap["rates_hz"]
    latency = snap["latency_ms"] or {}
    counters = snap["counters"] or {}
    norm = snap["error_norm"]
    lines = [
        f"ddvs monitor — {title}    {time.strftime('%H:%M:%S')}",
        "",
        f"state        {snap['state'] or 'no service seen'}"
        + ("" if snap["has_reference"] is None else f"   (reference: {'yes' if snap['has_reference'] else 'no'})"),
        f"error norm   {'—' if norm is None else f'{norm:.3e}'}",
        f"error        {_vector(snap['error'])}",
        f"twist        {_vector(snap['twist'])}   (m/s, rad/s, camera frame)",
        f"rates        frames {rates['frames']:6.1f} Hz   twists {rates['twists']:6.1f} Hz   "
        f"status {rates['status']:6.1f} Hz",
        f"refused      rejected {rates['rejected']:6.1f} /s   superseded {rates['dropped']:6.1f} /s   (frames)",
        "latency ms   " + ("—" if not latency else "   ".join(f"{k} {v:.2f}" for k, v in latency.items())),
        "counters     " + ("—" if not counters else "   ".join(f"{k} {v}" for k, v in counters.items())),
        f"message      {snap['message'] or ''}",
        f"backend      {snap['backend'] or '—'}   (Taichi, the service's kernels)",
        f"security     {_audit_line(snap['audit'])}",
    ]
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ddvs_service.protocol import add_zenoh_arguments
    from ddvs_service.protocol.ros_cli import add_ros_arguments

    parser.add_argument("--foxglove", action="store_true",
                        help="serve a live Foxglove view (Foxglove WebSocket protocol, offered as foxglove.sdk.v1 "
                             "or foxglove.websocket.v1) instead of the terminal's")
    parser.add_argument("--host", default="127.0.0.1", help="--foxglove: address to listen on (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8765, help="--foxglove: port (default 8765)")
    parser.add_argument("--once", action="store_true",
                        help="wait for a status, measure rates over --window, print one JSON snapshot and exit")
    parser.add_argument("--window", type=float, default=2.0, help="seconds over which rates are counted (default 2)")
    parser.add_argument("--interval", type=float, default=0.5, help="seconds between redraws (default 0.5)")
    parser.add_argument("--timeout", type=float, default=5.0,
                        help="--once: seconds to wait for a first status before giving up (exit 2; default 5)")
    parser.add_argument("--prefix", default="ddvs", help="key prefix (default ddvs)")
    parser.add_argument("--robot", default="robot0", help="robot name in the keys (default robot0)")
    add_zenoh_arguments(parser)
    add_ros_arguments(parser)  # ROS 2 mode: the ROS-typed topics are on rmw_zenoh keys (docs/ros2.md)


def run(args: argparse.Namespace) -> int:
    from ddvs_service.protocol import Keys, open_session, session_config_from_args
    from ddvs_service.protocol.ros_cli import ros_settings_from_args

    keys = Keys(args.prefix, args.robot, ros_settings_from_args(args))
    if args.foxglove:
        return _serve_foxglove(args, keys)
    with open_session(session_config_from_args(args)) as session:
        monitor = Monitor(session, keys, args.window)
        try:
            if args.once:
                if not monitor.status_received.wait(args.timeout):
                    print(f"ddvs monitor: no status on {keys.servo_status} within {args.timeout} s", file=sys.stderr)
                    return 2
                time.sleep(args.window)
                print(json.dumps(monitor.snapshot(), indent=2))
                return 0
            while True:
                sys.stdout.write(CLEAR + render(monitor.snapshot(), keys.base) + "\n")
                sys.stdout.flush()
                time.sleep(args.interval)
        except KeyboardInterrupt:
            return 0
        finally:
            monitor.close()


def _serve_foxglove(args: argparse.Namespace, keys: Keys) -> int:
    import signal

    from clients.foxglove_live import serve
    from ddvs_service.protocol import open_session, session_config_from_args

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    with open_session(session_config_from_args(args)) as session:
        serve(session, keys, args.host, args.port, stop)
    return 0
